"""Values derived from one landmark set's arrays, computed once per set of arrays.

A loop detector matches a scan against several candidates, and one verified match reads the
same two sets many times (intra-scan distances, ground-free landmark arrays, extents). Anything
that depends on a set alone is a pure function of a few of its arrays, so it can be kept next
to copies of those arrays: a later call with the same arrays (same identities, equal contents)
gets the stored value, anything else (a new set, arrays edited in place, a reused id) recomputes
it. Entries hold copies, never the set, so no scan is kept alive; at most ``max_entries``
entries and ``max_bytes`` of arrays (a W3-size set's distance matrix is ~1 MB).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any

import numpy as np


class DerivedCache:
    """Least-recently-used store of ``make()`` results keyed by a name and the identities of the
    arrays they derive from; a hit is checked against copies of those arrays (``np.array_equal``,
    a few microseconds), so a stale value is never served."""

    def __init__(self, max_entries: int = 256, max_bytes: int = 64 << 20) -> None:
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._lock = threading.Lock()
        self._entries: OrderedDict[tuple, tuple[tuple, Any, int]] = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    def get(self, name: Hashable, arrays: tuple[np.ndarray | None, ...], make: Callable[[], Any]) -> Any:
        """``make()``, or the value stored for these arrays (``None`` entries allowed)."""
        if self.max_entries <= 0:
            return make()
        key = (name, *(id(a) for a in arrays))
        with self._lock:
            e = self._entries.get(key)
        if e is not None and all(
                (c is None and a is None) or (c is not None and a is not None and c.dtype == a.dtype
                                              and np.array_equal(c, a))
                for c, a in zip(e[0], arrays, strict=True)):
            with self._lock:
                if key in self._entries:
                    self._entries.move_to_end(key)
                self.hits += 1
            return e[1]
        value = make()
        copies = tuple(None if a is None else np.array(a, copy=True) for a in arrays)
        size = sum(c.nbytes for c in copies if c is not None) + _nbytes(value)
        with self._lock:
            self.misses += 1
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= old[2]
            self._entries[key] = (copies, value, size)
            self._bytes += size
            while self._entries and (len(self._entries) > self.max_entries or self._bytes > self.max_bytes):
                self._bytes -= self._entries.popitem(last=False)[1][2]
        return value

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self._bytes = 0

    @property
    def nbytes(self) -> int:
        """Bytes of arrays held (copies and values)."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._entries)


def _nbytes(value: Any) -> int:
    """Bytes of the arrays in a cached value (an array, or an object with array attributes)."""
    if isinstance(value, np.ndarray):
        return value.nbytes
    fields = getattr(value, "__dict__", None)
    if fields is None:
        return 0
    return sum(v.nbytes for v in fields.values() if isinstance(v, np.ndarray))


derived_cache = DerivedCache()
"""The process-wide cache of per-set derived values (distances, ground-free arrays, extents)."""


def kernel_input(a: np.ndarray, dtype: type) -> np.ndarray:
    """``a`` as a C-contiguous array of ``dtype``, always read-only (a view, no copy when it is
    one already).

    Why: numba compiles one signature per combination of read-only and writeable arguments.
    Cached values here are read-only and fresh ones are not, so a scan verified a second time
    (k candidates a query) met kernel variants that loaded, or on a fresh install compiled,
    inside a timed query (docs/loops.md, session 13). One flag gives one signature."""
    out = np.ascontiguousarray(a, dtype=dtype).view()
    out.setflags(write=False)
    return out

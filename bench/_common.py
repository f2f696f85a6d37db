"""Shared helpers of the benchmark scripts: timing, peak memory, tables, JSON."""

from __future__ import annotations

import json
import platform
import resource
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np


def time_calls(fn: Callable[[], object], repeats: int, warmup: int = 1) -> np.ndarray:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return np.array(out)


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far [MB] (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine() -> dict:
    import os

    return {"python": platform.python_version(), "cpus": os.cpu_count(), "machine": platform.machine(),
            "loadavg_1min": os.getloadavg()[0]}


def print_table(rows: list[dict], columns: list[str]) -> None:
    widths = [max(len(c), *(len(str(r.get(c, ""))) for r in rows)) for c in columns]
    print("  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True)))
    print("  ".join("-" * w for w in widths))
    for r in rows:
        print("  ".join(str(r.get(c, "")).ljust(w) for c, w in zip(columns, widths, strict=True)))


def write_json(path: str | None, payload: dict) -> None:
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(payload, indent=2, default=float))
        print(f"wrote {path}")


def apply_verification_overrides(config, pairs: list[str]) -> None:
    """``KEY=VALUE`` (JSON values) onto a loop config's ``verification``, or with a ``matcher.``
    prefix onto its verified matcher's own (e.g. ``matcher.point_hypotheses=true``): labelled
    variants of the defaults in the loop benchmarks."""
    for kv in pairs:
        key, val = kv.split("=", 1)
        target = config.verification
        if key.startswith("matcher."):
            key, target = key.removeprefix("matcher."), config.matcher.verification
        setattr(target, key, json.loads(val))

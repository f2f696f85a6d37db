"""Putative associations: which landmark of the source may correspond to which of the target."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graffmatch.errors import InvalidInputError


def all_to_all(types_i: ArrayLike, types_j: ArrayLike) -> NDArray[np.int64]:
    """Every same-type pair (a, b), the paper's default (lines never match planes).

    Ordered by type, then source index, then target index. Returns (m, 2).
    """
    ti = np.asarray(types_i).reshape(-1)
    tj = np.asarray(types_j).reshape(-1)
    blocks = []
    for t in np.union1d(np.unique(ti), np.unique(tj)):
        a = np.flatnonzero(ti == t)
        b = np.flatnonzero(tj == t)
        if a.size and b.size:
            aa, bb = np.meshgrid(a, b, indexing="ij")
            blocks.append(np.stack([aa.ravel(), bb.ravel()], axis=1))
    if not blocks:
        return np.zeros((0, 2), dtype=np.int64)
    return np.concatenate(blocks).astype(np.int64)


def check_associations(associations: ArrayLike, n_i: int, n_j: int) -> NDArray[np.int64]:
    """Validate an explicit (m, 2) association list against the set sizes."""
    A = np.asarray(associations)
    if A.ndim != 2 or A.shape[1] != 2:
        raise InvalidInputError(f"associations must have shape (m, 2), got {A.shape}")
    if A.size and not np.issubdtype(A.dtype, np.integer):
        raise InvalidInputError("associations must be integer indices")
    A = A.astype(np.int64)
    if A.size and (A.min() < 0 or A[:, 0].max() >= n_i or A[:, 1].max() >= n_j):
        raise InvalidInputError("association index out of range")
    if len(np.unique(A, axis=0)) != len(A):
        raise InvalidInputError("associations contain duplicates")
    return A


def count_all_to_all(types_i: ArrayLike, types_j: ArrayLike) -> int:
    """m = sum over types of n_i(type) * n_j(type), without building the list."""
    ti = np.asarray(types_i).reshape(-1)
    tj = np.asarray(types_j).reshape(-1)
    return int(sum(np.sum(ti == t) * np.sum(tj == t) for t in np.unique(ti)))

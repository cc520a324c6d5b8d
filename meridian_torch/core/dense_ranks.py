"""Dense ranks of integer keys for the compiled (numba) kernels: the outlines' grid cells and the
classical segmenter's region edges share it (np.unique's inverse, which numba does not have)."""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["dense_ranks"]


@njit(cache=True, nogil=True)
def dense_ranks(key: np.ndarray) -> tuple[np.ndarray, int]:
    """(rank (n,) of each key among the distinct keys in ascending order, number of distinct keys):
    np.unique(key, return_inverse=True)'s inverse and length."""
    n = key.shape[0]
    order = np.argsort(key, kind="mergesort")
    rank = np.empty(n, np.int64)
    n_distinct = 0
    for r in range(n):
        if r == 0 or key[order[r]] != key[order[r - 1]]:
            n_distinct += 1
        rank[order[r]] = n_distinct - 1
    return rank, n_distinct

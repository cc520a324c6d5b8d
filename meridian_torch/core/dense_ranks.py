"""Dense ranks of integer keys for the compiled (numba) kernels: the outlines' grid cells and the
classical segmenter's region edges share it (np.unique's inverse, which numba does not have)."""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["dense_ranks"]


@njit(cache=True, nogil=True)
def dense_ranks(key: np.ndarray) -> tuple[np.ndarray, int]:
    """(rank (n,) of each key among the distinct keys in ascending order, number of distinct keys):
    np.unique(key, return_inverse=True)'s inverse and length.

    Keys spanning fewer than 4 n values (the grid cells of a compact segment) are ranked through a
    table over their span in linear time; others by a stable sort."""
    n = key.shape[0]
    rank = np.empty(n, np.int64)
    if n == 0:
        return rank, 0
    lo, hi = key.min(), key.max()
    if 0 <= hi - lo < 4 * n:  # (a span past 2**63 wraps negative)
        table = np.zeros(hi - lo + 1, np.int64)
        for i in range(n):
            table[key[i] - lo] = 1
        n_distinct = 0
        for k in range(table.shape[0]):
            if table[k]:
                table[k] = n_distinct
                n_distinct += 1
        for i in range(n):
            rank[i] = table[key[i] - lo]
        return rank, n_distinct
    order = np.argsort(key, kind="mergesort")
    n_distinct = 0
    for r in range(n):
        if r == 0 or key[order[r]] != key[order[r - 1]]:
            n_distinct += 1
        rank[order[r]] = n_distinct - 1
    return rank, n_distinct

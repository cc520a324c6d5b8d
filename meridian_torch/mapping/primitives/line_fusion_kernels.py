"""Compiled (numba) kernel of line fusion (`line_fusion`): the pairs of lines with samples near each
other (`near_line_pairs`), on a grid of the search radius. Two scipy KD-trees per call (one over
all samples, one over the queried ones) cost about 0.9 ms per fusion sweep, half of fusing a
patch's lines, most of it building the trees; the pairs only pre-select the merge test's
candidates, so the fused lines are the same (tested against the all-pairs definition)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["near_line_pairs"]


@njit(cache=True, nogil=True)
def near_line_pairs(samples: np.ndarray, owner: np.ndarray, n_lines: int, radius: float, query: np.ndarray) -> np.ndarray:
    """Sorted unique keys lo * n_lines + hi (lo < hi) of the line pairs owning two samples (S, 2)
    within `radius` (squared distance <= radius^2); with `query` (n_lines,) bool non-empty, only
    pairs with at least one queried line. `owner` (S,) is each sample's line; with a line's samples
    together (non-decreasing) each pair is recorded once."""
    n = samples.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    x0, y0 = samples[:, 0].min(), samples[:, 1].min()
    cx = np.empty(n, np.int64)
    cy = np.empty(n, np.int64)
    for i in range(n):  # cells of the radius; +1 keeps every neighbour cell's key positive
        cx[i] = np.int64(math.floor((samples[i, 0] - x0) / radius)) + 1
        cy[i] = np.int64(math.floor((samples[i, 1] - y0) / radius)) + 1
    width = cy.max() + 2
    key = cx * width + cy
    order = np.argsort(key, kind="mergesort")
    sorted_key = key[order]
    limit = radius * radius
    use_query = query.shape[0] > 0
    # A pair is found from one side only: its lower line, or its queried line when only one is;
    # stamp[l] == la + 1 once the pair (la, l) is found, so each pair is kept once.
    stamp = np.zeros(n_lines, np.int64)
    found = np.empty(64, np.int64)
    count = 0
    for i in range(n):
        la = owner[i]
        if use_query and not query[la]:
            continue
        for dx in range(-1, 2):
            low = key[i] + dx * width - 1  # the three cells dy = -1, 0, 1 are consecutive keys
            for b in range(np.searchsorted(sorted_key, low), n):
                if sorted_key[b] > low + 2:
                    break
                j = order[b]
                lb = owner[j]
                if lb == la or stamp[lb] == la + 1 or (lb < la and (not use_query or query[lb])):
                    continue
                ex, ey = samples[i, 0] - samples[j, 0], samples[i, 1] - samples[j, 1]
                if ex * ex + ey * ey <= limit:
                    stamp[lb] = la + 1
                    if count == found.shape[0]:
                        more = np.empty(2 * count, np.int64)
                        more[:count] = found
                        found = more
                    found[count] = min(la, lb) * n_lines + max(la, lb)
                    count += 1
    return np.unique(found[:count])

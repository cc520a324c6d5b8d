"""Compiled (numba) kernels of the consistency graph, for CPU arrays.

- `ball_heading_pairs`: the candidate pairs of `consistency._submap_edges`, the points within a
  radius of each centre (the test of scipy's `cKDTree.query_ball_point`) whose heading is within
  a gap of the centre's (the test of torch's `wrap_angle(...).abs() < gap`), found on a grid in
  one pass. The tree query returned every point of the disk as a Python list and the heading test
  then dropped most of them (about 20 M hits for 0.1 M edges before a fix).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from meridian_torch.matching.kernels import grown

__all__ = ["ball_heading_pairs"]

# Grid cells per side at most: cells stay >= the extent / this, however small the radii.
_MAX_CELLS_PER_SIDE = 1024


@njit(cache=True, nogil=True, error_model="numpy")
def ball_heading_pairs(
    points: np.ndarray, heading: np.ndarray, centres: np.ndarray, radius: np.ndarray, centre_heading: np.ndarray,
    max_gap: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(centre, point) index pairs with

        (x_p - x_c)^2 + (y_p - y_c)^2 <= radius_c^2        (scipy's query_ball_point test, p = 2)
        |wrap_angle(heading_p - centre_heading_c)| < max_gap_c  (torch's remainder, then abs)

    for points (N, 2), heading (N,), centres (K, 2), radius, centre_heading, max_gap (K,), all
    float64; ordered by centre, then point (as the tree's sorted hits, centre by centre).
    Non-finite points and centres pair with nothing."""
    n, k = points.shape[0], centres.shape[0]
    centre_out = np.empty(1024, np.int64)
    point_out = np.empty(1024, np.int64)
    n_out = 0
    finite = np.empty(n, np.bool_)
    for p in range(n):
        finite[p] = np.isfinite(points[p, 0]) and np.isfinite(points[p, 1])
    if k == 0 or not finite.any():
        return centre_out[:0].copy(), point_out[:0].copy()
    x0, y0 = points[finite, 0].min(), points[finite, 1].min()
    extent = max(points[finite, 0].max() - x0, points[finite, 1].max() - y0)
    # Cells about a typical radius wide: a centre visits ~9 cells, each holding ~its disk's points.
    cell = max(np.median(radius), extent / _MAX_CELLS_PER_SIDE, 1e-9)
    width = int((points[finite, 0].max() - x0) / cell) + 1
    height = int((points[finite, 1].max() - y0) / cell) + 1
    point_cell = np.full(n, -1, np.int64)
    starts = np.zeros(width * height + 1, np.int64)
    for p in range(n):
        if finite[p]:
            ix = min(int((points[p, 0] - x0) / cell), width - 1)
            iy = min(int((points[p, 1] - y0) / cell), height - 1)
            point_cell[p] = iy * width + ix
            starts[point_cell[p] + 1] += 1
    starts = np.cumsum(starts)
    slot = starts[:-1].copy()
    cell_points = np.empty(starts[-1], np.int64)
    for p in range(n):  # ascending within each cell
        if point_cell[p] >= 0:
            cell_points[slot[point_cell[p]]] = p
            slot[point_cell[p]] += 1
    two_pi = 2.0 * math.pi
    for c in range(k):
        cx, cy, r = centres[c, 0], centres[c, 1], radius[c]
        if not (np.isfinite(cx) and np.isfinite(cy) and r >= 0):
            continue
        bound = r * r
        # the cells of the disk's box, widened a hair for the rounding of the test
        reach = r * (1.0 + 1e-9) + 1e-9
        ix0 = max(int(np.floor((cx - reach - x0) / cell)), 0)
        ix1 = min(int(np.floor((cx + reach - x0) / cell)), width - 1)
        iy0 = max(int(np.floor((cy - reach - y0) / cell)), 0)
        iy1 = min(int(np.floor((cy + reach - y0) / cell)), height - 1)
        first = n_out
        for iy in range(iy0, iy1 + 1):
            for ix in range(ix0, ix1 + 1):
                cid = iy * width + ix
                for e in range(starts[cid], starts[cid + 1]):
                    p = cell_points[e]
                    dx = points[p, 0] - cx
                    dy = points[p, 1] - cy
                    if not dx * dx + dy * dy <= bound:
                        continue
                    # torch's remainder: fmod, then the divisor's sign
                    mod = np.fmod(heading[p] - centre_heading[c] + math.pi, two_pi)
                    if mod != 0 and mod < 0:
                        mod += two_pi
                    if not abs(mod - math.pi) < max_gap[c]:
                        continue
                    if n_out == len(point_out):
                        centre_out = grown(centre_out, 2 * n_out)
                        point_out = grown(point_out, 2 * n_out)
                    centre_out[n_out] = c
                    point_out[n_out] = p
                    n_out += 1
        point_out[first:n_out].sort()
    return centre_out[:n_out].copy(), point_out[:n_out].copy()

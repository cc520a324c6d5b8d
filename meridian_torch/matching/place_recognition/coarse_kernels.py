"""Compiled (numba) passes of the coarse search over its (yaws, H, W) volumes: the chain step (the
previous chain volume max-pooled over the drift slack, moved by the odometry step and added to
the new submap's scores, one pass per yaw) and the best yaw of every cell.

Torch's separable passes over the whole (yaws, H, W) volume read and wrote it about ten times
and allocated two copies of it (0.5 GB each at 10 000 patches); here each yaw plane is read a few
times while it is in cache. A yaw range runs in one call, so two ranges can run side by side
(the kernel releases the GIL). The arithmetic is torch's: maxima (exact), the decay product and
the sum in float32, so the volume is bitwise that of max_pool2d, rolls over the yaws and
grid_sample (tests).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["best_yaws", "chain_yaws"]


@njit(cache=True, nogil=True)
def chain_yaws(previous: np.ndarray, scores: np.ndarray, rows: np.ndarray, cols: np.ndarray, slack: int,
               decay: float, first: int, stop: int, below: np.ndarray, above: np.ndarray, out: np.ndarray) -> None:
    """out[y] = scores[y] + decay * pooled[y] moved, for the yaws y in first..stop-1.

    previous, scores, out: (K, H, W) float32; `out` may be `previous` or `scores` (each plane is
    read before it is written). pooled[y] is the maximum of previous over the yaws y - 1, y, y + 1
    (circular) and the (2 slack + 1)^2 cells around each cell that lie on the grid; moved, the
    pooled plane read at the source row `rows[y, i]` (K, H) and column `cols[y, j]` (K, W) of each
    output cell, 0 where either is -1. `below` and `above` (H, W) are copies of the original planes
    first - 1 and stop (circular), which other calls may be overwriting.
    """
    _, h, w = previous.shape
    d32 = np.float32(decay)
    saved = np.empty((h, w), np.float32)  # the original of the plane before y, once out[y - 1] is written
    yaw_max = np.empty((h, w), np.float32)
    along_x = np.empty((h, w), np.float32)
    pooled_row = np.empty(w, np.float32)
    for y in range(first, stop):
        lower = below if y == first else saved
        upper = above if y == stop - 1 else previous[y + 1]
        current = previous[y]
        # plain selects, so that the loops vectorize (no NaN in a volume)
        for i in range(h):
            for j in range(w):
                a, b, c = lower[i, j], current[i, j], upper[i, j]
                m = a if a > b else b
                yaw_max[i, j] = m if m > c else c
                along_x[i, j] = yaw_max[i, j]
        for d in range(1, slack + 1):  # each pass reads yaw_max, which it does not write
            for i in range(h):
                for j in range(w - d):
                    a, b = along_x[i, j], yaw_max[i, j + d]
                    along_x[i, j] = a if a > b else b
                for j in range(d, w):
                    a, b = along_x[i, j], yaw_max[i, j - d]
                    along_x[i, j] = a if a > b else b
        if y + 1 < stop:
            saved[:, :] = current  # read by the next yaw; out[y] may be this very plane
        for i in range(h):
            src = rows[y, i]
            if src < 0:
                pooled_row[:] = 0.0
            else:
                pooled_row[:] = along_x[src]
                for ii in range(max(src - slack, 0), min(src + slack + 1, h)):
                    for j in range(w):
                        a, b = pooled_row[j], along_x[ii, j]
                        pooled_row[j] = a if a > b else b
            for j in range(w):
                c = cols[y, j]
                moved = pooled_row[c] if c >= 0 else np.float32(0.0)
                out[y, i, j] = scores[y, i, j] + moved * d32


@njit(cache=True, nogil=True)
def best_yaws(volume: np.ndarray, first: int, stop: int, best: np.ndarray, best_yaw: np.ndarray) -> None:
    """For the cells first..stop-1 of a (K, H * W) volume: the maximum over the yaws into `best` and
    its yaw into `best_yaw` (the first yaw of a tie, as argmax), one pass over the cells' yaws."""
    for cell in range(first, stop):
        b = volume[0, cell]
        k = 0
        for y in range(1, volume.shape[0]):
            if volume[y, cell] > b:
                b = volume[y, cell]
                k = y
        best[cell] = b
        best_yaw[cell] = k

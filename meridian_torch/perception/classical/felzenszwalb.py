"""Felzenszwalb-Huttenlocher graph segmentation, label-for-label equal to scikit-image's.

`skimage.segmentation.felzenszwalb` spends most of its time outside the algorithm: it builds
(E, 2) int64 edge arrays with np.c_/vstack, reorders them by cost, and unravels the union-find
forest with repeated fancy indexing and np.unique. Here the smoothing, the edge costs and their
np.argsort stay NumPy/SciPy calls with skimage's exact expressions (so costs and the tie order of
equal costs are the same bits), and one compiled kernel does the rest: it derives each sorted
edge's pixels from its index, runs both union-find passes and numbers the components.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import ndimage as ndi
from skimage.util import img_as_float64

__all__ = ["felzenszwalb"]


def felzenszwalb(image: np.ndarray, scale: float = 1.0, sigma: float = 0.8, min_size: int = 20) -> np.ndarray:
    """Over-segment an (H, W) or (H, W, C) image; returns (H, W) int64 labels 0..K-1.

    The same labels as `skimage.segmentation.felzenszwalb(image, scale=scale, sigma=sigma,
    min_size=min_size)` (scikit-image 0.26, channel axis last), bit for bit: components are
    numbered in the order of their first pixel in row-major order.
    """
    if image.ndim not in (2, 3):
        raise ValueError(f"felzenszwalb: image must be (H, W) or (H, W, C), got shape {image.shape}")
    if sigma < 0:
        raise ValueError(f"felzenszwalb: sigma must be >= 0, got {sigma}")
    image = img_as_float64(np.atleast_3d(image))
    image = ndi.gaussian_filter(image, sigma=[sigma, sigma, 0], mode="reflect", cval=0, truncate=4.0)
    height, width = image.shape[:2]
    # Edge costs in skimage's order (right, down, down-right, up-right), same expressions.
    right = image[:, 1:, :] - image[:, : width - 1, :]
    down = image[1:, :, :] - image[: height - 1, :, :]
    dright = image[1:, 1:, :] - image[: height - 1, : width - 1, :]
    uright = image[1:, : width - 1, :] - image[: height - 1, 1:, :]
    costs = np.concatenate([np.sqrt(np.sum(d * d, axis=-1)).ravel() for d in (right, down, dright, uright)])
    order = np.argsort(costs)
    labels = _segment_sorted_edges(costs, order, height, width, float(scale) / 255.0, int(min_size))
    return labels.reshape(height, width)


@numba.njit(cache=True, nogil=True)
def _find(parent: np.ndarray, node: int) -> int:
    # Path halving: every visited node skips to its grandparent.
    while parent[node] != node:
        parent[node] = parent[parent[node]]
        node = parent[node]
    return node


@numba.njit(cache=True, nogil=True)
def _union(parent: np.ndarray, size: np.ndarray, ra: int, rb: int) -> int:
    """Hang the smaller of roots `ra`, `rb` under the larger; returns the surviving root."""
    if size[ra] < size[rb]:
        ra, rb = rb, ra
    parent[rb] = ra
    size[ra] += size[rb]
    return ra


@numba.njit(cache=True, nogil=True)
def _edge_pixels(edge: int, height: int, width: int) -> tuple[int, int]:
    """The two flat pixel indices of edge `edge` in skimage's order: right, down, down-right, up-right."""
    # One int32 division per edge: several times cheaper than int64 on x86; pixel indices fit.
    w1, w = np.int32(width - 1), np.int32(width)
    n_right = height * (width - 1)
    n_down = (height - 1) * width
    n_diag = (height - 1) * (width - 1)
    if edge < n_right:
        q = np.int32(edge)
        row = q // w1
        left = row * w + q - row * w1
        return left + np.int32(1), left
    if edge < n_right + n_down:
        top = np.int32(edge - n_right)
        return top + w, top
    if edge < n_right + n_down + n_diag:
        q = np.int32(edge - n_right - n_down)
        row = q // w1
        top_left = row * w + q - row * w1
        return top_left + w + np.int32(1), top_left
    q = np.int32(edge - n_right - n_down - n_diag)
    row = q // w1
    top_left = row * w + q - row * w1
    return top_left + np.int32(1), top_left + w


@numba.njit(cache=True, nogil=True)
def _segment_sorted_edges(
    costs: np.ndarray, order: np.ndarray, height: int, width: int, scale: float, min_size: int
) -> np.ndarray:
    n = height * width
    n_edges = order.shape[0]
    parent = np.arange(n, dtype=np.int32)
    size = np.ones(n, dtype=np.int32)
    internal = np.zeros(n)  # largest merged edge cost of each component, kept at its root
    pixel_a = np.empty(n_edges, dtype=np.int32)  # endpoints in sorted order, for the second pass
    pixel_b = np.empty(n_edges, dtype=np.int32)
    for k in range(n_edges):
        a, b = _edge_pixels(order[k], height, width)
        pixel_a[k], pixel_b[k] = a, b
        ra, rb = _find(parent, a), _find(parent, b)
        if ra == rb:
            continue
        cost = costs[order[k]]
        # skimage holds the two thresholds in C floats: round to float32 as it does.
        threshold = np.float32(min(internal[ra] + scale / size[ra], internal[rb] + scale / size[rb]))
        if cost < np.float64(threshold):
            internal[_union(parent, size, ra, rb)] = cost
    # Components under min_size join a neighbour, cheapest edges first.
    for k in range(n_edges):
        ra, rb = _find(parent, pixel_a[k]), _find(parent, pixel_b[k])
        if ra != rb and (size[ra] < min_size or size[rb] < min_size):
            _union(parent, size, ra, rb)
    # Number components by their first pixel, as np.unique over skimage's min-index roots does.
    labels = np.empty(n, dtype=np.int64)
    label_of_root = np.full(n, -1, dtype=np.int64)
    count = 0
    for p in range(n):
        r = _find(parent, p)
        if label_of_root[r] < 0:
            label_of_root[r] = count
            count += 1
        labels[p] = label_of_root[r]
    return labels

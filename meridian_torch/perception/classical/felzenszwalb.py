"""Felzenszwalb-Huttenlocher graph segmentation, label-for-label equal to scikit-image's.

`skimage.segmentation.felzenszwalb` spends most of its time outside the algorithm: np.argsort
of the edge costs, (E, 2) int64 edge arrays built with np.c_/vstack and reordered by cost, and
the union-find forest unravelled with repeated fancy indexing and np.unique. Here the smoothing
stays skimage's SciPy call, the edge costs are computed in one compiled pass with NumPy's
rounding steps (the same bits), the costs are sorted by a radix sort whose order is provably
np.argsort's (else np.argsort itself runs), and one compiled kernel derives each sorted edge's
pixels from its index, runs both union-find passes and numbers the components."""

from __future__ import annotations

import numba
import numpy as np
from scipy import ndimage as ndi
from skimage.util import img_as_float64

from meridian_torch.core.union_find import find_root

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
    if 4 * height * width >= 2**32:  # edge indices are packed into 32 bits, pixel indices into int32
        raise ValueError(f"felzenszwalb: image of {height}x{width} pixels is too large (limit 2**30 pixels)")
    costs = _edge_costs(np.ascontiguousarray(image))
    scale = float(scale) / 255.0
    order, sorted_costs, ties = _sort_costs(costs)
    # Only np.argsort knows how it orders equal costs. Ties at cost 0 alone cannot change the
    # labels: zero-cost edges come first and each joins two components (thresholds are >= the
    # float32 scale / n > 0, as no component has merged a positive cost yet), so the partition
    # after them does not depend on their order, and the min_size pass finds them inside one
    # component. Any other tie is left to np.argsort.
    if ties == _OTHER_TIES or (ties == _ZERO_TIES and not np.float32(scale / (height * width)) > 0):
        order = np.argsort(costs)
        sorted_costs = costs[order]
    labels = _segment_sorted_edges(sorted_costs, order, height, width, scale, int(min_size))
    return labels.reshape(height, width)


_NO_TIES, _ZERO_TIES, _OTHER_TIES = 0, 1, 2


@numba.njit(cache=True, nogil=True)
def _edge_costs(image: np.ndarray) -> np.ndarray:
    """(E,) edge costs of an (H, W, C) float64 image in skimage's order (right, down, down-right,
    up-right): sqrt(sum_c d_c^2) of each neighbour difference, with NumPy's rounding steps (each
    difference and square rounded, the channels summed in order), so the same bits as skimage's
    `np.sqrt(np.sum(d * d, axis=-1))` in one pass instead of a dozen array passes."""
    height, width, channels = image.shape
    n_right, n_down, n_diag = height * (width - 1), (height - 1) * width, (height - 1) * (width - 1)
    costs = np.empty(n_right + n_down + 2 * n_diag)
    # per direction, (row, column) of an edge's pixels a and b relative to its row r and column c,
    # as skimage's slices pair them (up-right: image[1:, :-1] - image[:-1, 1:]); d = image[b] - image[a]
    offsets = np.array([[0, 0, 0, 1], [0, 0, 1, 0], [0, 0, 1, 1], [0, 1, 1, 0]])
    k = 0
    for direction in range(4):
        ra, ca, rb, cb = offsets[direction]
        rows = height if direction == 0 else height - 1
        cols = width if direction == 1 else width - 1
        for r in range(rows):
            for c in range(cols):
                total = 0.0
                for ch in range(channels):
                    d = image[r + rb, c + cb, ch] - image[r + ra, c + ca, ch]
                    total += d * d
                costs[k] = np.sqrt(total)
                k += 1
    return costs


@numba.njit(cache=True, nogil=True)
def _sort_costs(costs: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(E,) edge indices sorting the non-negative `costs`, the sorted costs, and their ties.

    With no ties the sorting order is unique, so it is np.argsort's. LSD radix sort (four 8-bit
    digits) of each cost's float32 bits, carrying the edge index in the low 32 bits of one
    uint64; float32 rounding is monotone, so only costs sharing a float32 value can be out of
    order, and an insertion pass puts those in float64 order. _OTHER_TIES also reports NaN and a
    fix-up too long to be worth finishing (the caller then uses np.argsort).
    """
    n = costs.shape[0]
    keys = np.empty(n, dtype=np.uint64)
    counts = np.zeros((4, 256), dtype=np.int64)
    for i in range(n):
        bits = np.uint64(np.float32(costs[i]).view(np.uint32))
        keys[i] = (bits << np.uint64(32)) | np.uint64(i)
        for digit in range(4):
            counts[digit, (bits >> np.uint64(8 * digit)) & np.uint64(255)] += 1
    spare = np.empty_like(keys)
    offsets = np.empty(256, dtype=np.int64)
    for digit in range(4):
        total, one_value = 0, False
        for d in range(256):
            offsets[d] = total
            total += counts[digit, d]
            one_value |= counts[digit, d] == n
        if one_value:
            continue  # every key has this digit: the pass would move nothing
        shift = np.uint64(32 + 8 * digit)
        for i in range(n):
            d = (keys[i] >> shift) & np.uint64(255)
            spare[offsets[d]] = keys[i]
            offsets[d] += 1
        keys, spare = spare, keys
    order = np.empty(n, dtype=np.int64)
    sorted_costs = np.empty(n)
    for i in range(n):
        order[i] = keys[i] & np.uint64(0xFFFFFFFF)
        sorted_costs[i] = costs[order[i]]
    moves = 0
    for i in range(1, n):
        cost, edge = sorted_costs[i], order[i]
        j = i
        while j > 0 and sorted_costs[j - 1] > cost:
            sorted_costs[j], order[j] = sorted_costs[j - 1], order[j - 1]
            j -= 1
        sorted_costs[j], order[j] = cost, edge
        moves += i - j
        if moves > n:
            return order, sorted_costs, _OTHER_TIES
    ties = _NO_TIES
    for i in range(1, n):
        if not sorted_costs[i - 1] < sorted_costs[i]:
            if sorted_costs[i - 1] != 0.0 or sorted_costs[i] != 0.0:  # a positive tie, or NaN
                return order, sorted_costs, _OTHER_TIES
            ties = _ZERO_TIES
    return order, sorted_costs, ties


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
    sorted_costs: np.ndarray, order: np.ndarray, height: int, width: int, scale: float, min_size: int
) -> np.ndarray:
    """Both union-find passes over the edges in sorted order; (H * W,) labels by first pixel."""
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
        ra, rb = find_root(parent, a), find_root(parent, b)
        if ra == rb:
            continue
        cost = sorted_costs[k]
        # skimage holds the two thresholds in C floats: round to float32 as it does.
        threshold = np.float32(min(internal[ra] + scale / size[ra], internal[rb] + scale / size[rb]))
        if cost < np.float64(threshold):
            internal[_union(parent, size, ra, rb)] = cost
    # Components under min_size join a neighbour, cheapest edges first. Components only grow, so
    # an edge between pixels of two components already at min_size never merges: skip its finds.
    small = np.empty(n, dtype=np.bool_)
    for p in range(n):
        small[p] = size[find_root(parent, p)] < min_size
    for k in range(n_edges):
        if not (small[pixel_a[k]] or small[pixel_b[k]]):
            continue
        ra, rb = find_root(parent, pixel_a[k]), find_root(parent, pixel_b[k])
        if ra != rb and (size[ra] < min_size or size[rb] < min_size):
            _union(parent, size, ra, rb)
    # Number components by their first pixel, as np.unique over skimage's min-index roots does.
    labels = np.empty(n, dtype=np.int64)
    label_of_root = np.full(n, -1, dtype=np.int64)
    count = 0
    for p in range(n):
        r = find_root(parent, p)
        if label_of_root[r] < 0:
            label_of_root[r] = count
            count += 1
        labels[p] = label_of_root[r]
    return labels

"""Compiled (numba) hierarchical merging of the classical segmenter's regions (`segmenter`).

The region adjacency graph of an over-segmentation: per region its pixel count and feature sums,
per undirected edge its border length (4-neighbour pixel pairs) and summed colour step. Merging
only aggregates these sums, so it never touches the pixels again. As NumPy array steps (np.unique
of the edge keys, lexsort for each region's best edge, bincounts) it was about a quarter of
segmenting an aerial patch, most of it per-step overhead on a few hundred regions. Every sum here
adds in NumPy's order (bincount: input order from 0.0) and every weight is the same expression, so
the labels are the array steps' (tested against them). Also here: the weighted colour step of
every 4-neighbour pixel pair (`colour_steps`), in NumPy's rounding."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from meridian_torch.core.dense_ranks import dense_ranks
from meridian_torch.core.union_find import find_root

__all__ = ["colour_steps", "merge_regions"]


@njit(cache=True, nogil=True, inline="always")
def _colour_step(image: np.ndarray, weights: np.ndarray, y: int, x: int, y2: int, x2: int) -> np.float32:
    total = np.float32(0.0)
    for k in range(image.shape[2]):
        d = (image[y2, x2, k] - image[y, x, k]) * weights[k]
        total += d * d
    return np.sqrt(total)


@njit(cache=True, nogil=True)
def colour_steps(image: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|(b - a) * weights| of the horizontal (H, W - 1) and vertical (H - 1, W) neighbour pairs of an
    (H, W, C) float32 image, in float32: each difference, product and square rounded, the channels
    summed in order, so the bits of NumPy's `np.linalg.norm((b - a) * weights, axis=-1)` without
    its six array passes."""
    h, w, _ = image.shape
    step_h = np.empty((h, max(w - 1, 0)), np.float32)
    step_v = np.empty((max(h - 1, 0), w), np.float32)
    for y in range(h):
        for x in range(w - 1):
            step_h[y, x] = _colour_step(image, weights, y, x, y, x + 1)
    for y in range(h - 1):
        for x in range(w):
            step_v[y, x] = _colour_step(image, weights, y, x, y + 1, x)
    return step_h, step_v


@njit(cache=True, nogil=True)
def _set_edges(
    a: np.ndarray, b: np.ndarray, length: np.ndarray, step: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The undirected edges (sorted by lo * n + hi) of the pairs (a, b) with a != b, and the sums
    of their pairs' length and step, each in the pairs' order."""
    m = a.shape[0]
    key = np.empty(m, np.int64)
    source = np.empty(m, np.int64)
    k = 0
    for i in range(m):
        lo, hi = min(a[i], b[i]), max(a[i], b[i])
        if lo != hi:
            key[k] = lo * n + hi
            source[k] = i
            k += 1
    key, source = key[:k], source[:k]
    unique_of, n_edges = dense_ranks(key)
    edges = np.empty((n_edges, 2), np.int64)
    border_len = np.zeros(n_edges)
    border_step = np.zeros(n_edges)
    for j in range(k):
        e = unique_of[j]
        edges[e, 0], edges[e, 1] = key[j] // n, key[j] % n
        border_len[e] += length[source[j]]
        border_step[e] += step[source[j]]
    return edges, border_len, border_step


@njit(cache=True, nogil=True)
def _weights(
    edges: np.ndarray, count: np.ndarray, sums: np.ndarray, border_len: np.ndarray, border_step: np.ndarray,
    lightness_weight: float, texture_weight: float, boundary_weight: float,
) -> np.ndarray:
    """(E,) dissimilarity in Lab units: mean-colour distance + texture + mean border colour step."""
    weight = np.empty(edges.shape[0])
    for e in range(edges.shape[0]):
        u, v = edges[e, 0], edges[e, 1]
        d0 = sums[u, 0] / count[u] - sums[v, 0] / count[v]
        d1 = sums[u, 1] / count[u] - sums[v, 1] / count[v]
        d2 = sums[u, 2] / count[u] - sums[v, 2] / count[v]
        d3 = sums[u, 3] / count[u] - sums[v, 3] / count[v]
        ld0 = lightness_weight * d0
        colour = math.sqrt(ld0 * ld0 + d1 * d1 + d2 * d2)
        weight[e] = colour + texture_weight * abs(d3) + boundary_weight * border_step[e] / border_len[e]
    return weight


@njit(cache=True, nogil=True)
def _best_edges(edges: np.ndarray, weight: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """For every region with an edge, ascending: (region, its lowest-weight edge). Ties go to the
    first edge naming it as the lower region, then as the higher one (a stable sort's order)."""
    best = np.full(n, -1, np.int64)
    for side in range(2):
        for e in range(edges.shape[0]):
            u = edges[e, side]
            b = best[u]
            if b < 0 or weight[e] < weight[b]:
                best[u] = e
    nodes = np.flatnonzero(best >= 0)
    return nodes, best[nodes]


@njit(cache=True, nogil=True)
def _components(edges: np.ndarray, chosen: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """Connected components of regions 0..n-1 joined by the chosen edges, numbered in the order of
    each component's smallest region (as scipy's connected_components)."""
    parent = np.arange(n)
    for c in chosen:
        u, v = find_root(parent, edges[c, 0]), find_root(parent, edges[c, 1])
        if u != v:  # the smaller root stays a root: every component's root is its smallest region
            parent[max(u, v)] = min(u, v)
    comp = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        root = find_root(parent, i)
        if root == i:
            comp[i] = m
            m += 1
        else:
            comp[i] = comp[root]
    return m, comp


@njit(cache=True, nogil=True)
def _merge(
    edges: np.ndarray, border_len: np.ndarray, border_step: np.ndarray, count: np.ndarray, sums: np.ndarray,
    chosen: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Union the regions joined by the chosen edges; returns the merged graph and old -> new region."""
    n = count.shape[0]
    m, comp = _components(edges, chosen, n)
    new_count = np.zeros(m)
    new_sums = np.zeros((m, sums.shape[1]))
    for i in range(n):
        new_count[comp[i]] += count[i]
    for c in range(sums.shape[1]):
        for i in range(n):
            new_sums[comp[i], c] += sums[i, c]
    a = np.empty(edges.shape[0], np.int64)
    b = np.empty(edges.shape[0], np.int64)
    for e in range(edges.shape[0]):
        a[e], b[e] = comp[edges[e, 0]], comp[edges[e, 1]]
    new_edges, new_len, new_step = _set_edges(a, b, border_len, border_step, m)
    return new_edges, new_len, new_step, new_count, new_sums, comp


@njit(cache=True, nogil=True)
def merge_regions(
    labels: np.ndarray, feats: np.ndarray, step_h: np.ndarray, step_v: np.ndarray,
    lightness_weight: float, texture_weight: float, boundary_weight: float,
    merge_threshold: float, merge_levels: int, min_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Hierarchical merging of the regions of `labels` (H, W) int64 0..n-1 with per-pixel features
    feats (H, W, 4) float64 (Lab and local contrast) and colour steps to the right (H, W-1) and down
    (H-1, W): at each of `merge_levels` increasing thresholds up to `merge_threshold`, every region
    joins its most similar neighbour while that dissimilarity is under the threshold (a Boruvka
    step), repeated to convergence; then regions under `min_px` pixels join their most similar
    neighbour whatever the weight.

    Returns (old region -> merged region (n,), the merged graph's edges (E, 2), their weights (E,)
    and border lengths (E,))."""
    h, w = labels.shape
    n = labels.max() + 1
    count = np.zeros(n)
    sums = np.zeros((n, feats.shape[2]))
    for r in range(h):
        for c in range(w):
            count[labels[r, c]] += 1.0
    for f in range(feats.shape[2]):  # np.bincount per feature: pixels in row-major order
        for r in range(h):
            for c in range(w):
                sums[labels[r, c], f] += feats[r, c, f]
    # The 4-neighbour pixel pairs, horizontal then vertical, row-major: their borders.
    n_pairs = h * (w - 1) + (h - 1) * w
    a = np.empty(n_pairs, np.int64)
    b = np.empty(n_pairs, np.int64)
    step = np.empty(n_pairs)
    k = 0
    for r in range(h):
        for c in range(w - 1):
            a[k], b[k], step[k] = labels[r, c], labels[r, c + 1], step_h[r, c]
            k += 1
    for r in range(h - 1):
        for c in range(w):
            a[k], b[k], step[k] = labels[r, c], labels[r + 1, c], step_v[r, c]
            k += 1
    edges, border_len, border_step = _set_edges(a, b, np.ones(n_pairs), step, n)
    lut = np.arange(n)

    for level in range(1, merge_levels + 1):
        tau = merge_threshold * level / merge_levels
        while edges.shape[0]:
            weight = _weights(edges, count, sums, border_len, border_step, lightness_weight, texture_weight,
                              boundary_weight)
            _, best = _best_edges(edges, weight, count.shape[0])
            chosen = best[weight[best] < tau]
            if chosen.size == 0:
                break
            edges, border_len, border_step, count, sums, comp = _merge(edges, border_len, border_step, count, sums,
                                                                       chosen)
            lut = comp[lut]

    while edges.shape[0]:
        weight = _weights(edges, count, sums, border_len, border_step, lightness_weight, texture_weight, boundary_weight)
        nodes, best = _best_edges(edges, weight, count.shape[0])
        chosen = best[count[nodes] < min_px]
        if chosen.size == 0:
            break
        edges, border_len, border_step, count, sums, comp = _merge(edges, border_len, border_step, count, sums, chosen)
        lut = comp[lut]

    weight = _weights(edges, count, sums, border_len, border_step, lightness_weight, texture_weight, boundary_weight)
    return lut, edges, weight, border_len

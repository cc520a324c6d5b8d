"""Line fusion: the pairwise merge test of lines and the sweeps that merge fine lines into coarse ones."""

from __future__ import annotations

import numpy as np
import torch

from meridian_torch.config.mapping import PrimitiveConfig
from meridian_torch.geometry.segments import closest_point_on_segment
from meridian_torch.mapping.primitives.line_fusion_kernels import near_line_pairs

__all__ = ["fuse_lines", "fuse_indexed_lines", "mergeable_line_pairs"]

PARALLEL_SIN = 1e-3  # |sin| below this: the parallel-lines branch of the merge test (reference)
SHORT_LINE_MAX_ANGLE = np.pi / 4  # cap of the relaxed angle tolerance of short lines (reference)
COST_BIN = 0.02  # merge priority is |sin angle| in bins of this width; ties broken pseudo-randomly
SEMANTIC_CHUNK = 16384  # pairs per descriptor dot-product chunk (bounds memory for D = 1024)


def _line_samples(endpoints: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Midpoints of the pieces (no longer than h) each line is cut into, and the owning line."""
    lengths = np.linalg.norm(endpoints[:, 1] - endpoints[:, 0], axis=1)
    pieces = np.maximum(np.ceil(lengths / h), 1).astype(np.int64)
    owner = np.repeat(np.arange(len(endpoints)), pieces)
    first = np.cumsum(pieces) - pieces
    frac = (np.arange(len(owner)) - first[owner] + 0.5) / pieces[owner]
    samples = endpoints[owner, 0] + frac[:, None] * (endpoints[owner, 1] - endpoints[owner, 0])
    return samples, owner


def _candidate_pairs(endpoints: np.ndarray, max_dist: float, query: np.ndarray | None = None) -> np.ndarray:
    """Pairs (i < j) whose segments may be closer than `max_dist` (a superset), (E, 2), sorted.

    Each line is cut into pieces no longer than h = max_dist / 2 and represented by the piece
    midpoints; every point of a line is within h / 2 of one, so two lines closer than max_dist
    have midpoints closer than max_dist + h (searched with a 1e-9 relative margin against
    rounding). With `query` (sorted line indices), only the pairs with at least one line in it.
    """
    n = len(endpoints)
    h = 0.5 * max_dist
    radius = (max_dist + h) * (1.0 + 1e-9)
    samples, owner = _line_samples(endpoints, h)
    is_query = np.zeros(0 if query is None else n, dtype=bool)
    if query is not None:
        is_query[query] = True
    key = near_line_pairs(samples, owner, n, radius, is_query)
    return np.stack([key // n, key % n], axis=1)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _merge_test(
    endpoints: np.ndarray, pairs: np.ndarray, cfg: PrimitiveConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Geometric merge test of line pairs (A = pairs[:, 0], B = pairs[:, 1]): (ok, |sin angle|).

    The angle test runs first; the distance tests only on the pairs passing it.
    """
    vec = endpoints[:, 1] - endpoints[:, 0]
    length = np.linalg.norm(vec, axis=1)
    direction = vec / length[:, None]
    len_a, len_b = length[pairs[:, 0]], length[pairs[:, 1]]
    # antiparallel lines count as parallel
    sin = np.abs(_cross(direction[pairs[:, 0]], direction[pairs[:, 1]]))

    theta = np.deg2rad(cfg.line_merge_angle_deg)
    shortest = np.minimum(len_a, len_b)
    relaxed = np.minimum(theta * cfg.line_merge_short_m / shortest, SHORT_LINE_MAX_ANGLE)
    tol = np.where(shortest < cfg.line_merge_short_m, np.maximum(relaxed, theta), theta)
    ok = sin < np.sin(tol)
    sub = np.flatnonzero(ok)
    ok[sub] = _distance_test(endpoints, direction, pairs[sub], sin[sub], cfg)
    return ok, sin


def _distance_test(
    endpoints: np.ndarray, direction: np.ndarray, pairs: np.ndarray, sin: np.ndarray, cfg: PrimitiveConfig
) -> np.ndarray:
    """Gap and offset tests of the merge test (see `mergeable_line_pairs`)."""
    a0, a1 = endpoints[pairs[:, 0], 0], endpoints[pairs[:, 0], 1]
    b0, b1 = endpoints[pairs[:, 1], 0], endpoints[pairs[:, 1], 1]
    dir_a, dir_b = direction[pairs[:, 0]], direction[pairs[:, 1]]
    # Closest points between the segments: candidates are each endpoint against the other segment.
    q = np.stack(
        [
            closest_point_on_segment(a0, b0, b1),
            closest_point_on_segment(a1, b0, b1),
            closest_point_on_segment(b0, a0, a1),
            closest_point_on_segment(b1, a0, a1),
        ]
    )  # (4, E, 2)
    p = np.stack([a0, a1, b0, b1])
    d = np.linalg.norm(p - q, axis=-1)
    k = d.argmin(axis=0)
    rows = np.arange(len(pairs))
    gap = d[k, rows]
    on_a = np.where((k < 2)[:, None], p[k, rows], q[k, rows])  # closest point on A
    on_b = np.where((k < 2)[:, None], q[k, rows], p[k, rows])  # closest point on B

    # Proper intersection of non-parallel segments: closest points coincide, gap and offsets 0.
    denom = _cross(a1 - a0, b1 - b0)
    safe = np.where(denom == 0, 1.0, denom)
    s = _cross(b0 - a0, b1 - b0) / safe
    t = _cross(b0 - a0, a1 - a0) / safe
    crossing = (sin >= PARALLEL_SIN) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
    gap = np.where(crossing, 0.0, gap)
    off_a = np.where(crossing, 0.0, np.abs(_cross(dir_b, on_a - b0)))  # A's point from line B
    off_b = np.where(crossing, 0.0, np.abs(_cross(dir_a, on_b - a0)))  # B's point from line A

    perp = cfg.line_merge_perp_dist_m
    parallel_ok = np.abs(_cross(dir_a, b0 - a0)) <= perp
    general_ok = (off_a <= perp) & (off_b <= perp)
    return np.where(sin < PARALLEL_SIN, parallel_ok, general_ok) & (gap < cfg.line_merge_dist_m)


def _semantic_ok(table: torch.Tensor, rows: np.ndarray, pairs: np.ndarray, min_sim: float) -> np.ndarray:
    """Descriptor test of line pairs whose descriptors are table[rows] (rows L2-normalized).

    Lines sharing a table row pass without a dot product; each distinct row pair is computed once.
    """
    ra, rb = rows[pairs[:, 0]], rows[pairs[:, 1]]
    ok = ra == rb
    differ = np.flatnonzero(~ok)
    if differ.size:
        n = len(table)
        lo_hi = np.minimum(ra, rb)[differ] * n + np.maximum(ra, rb)[differ]
        key, inverse = np.unique(lo_hi, return_inverse=True)
        lo, hi = torch.from_numpy(key // n), torch.from_numpy(key % n)
        chunks = torch.split(torch.arange(len(key)), SEMANTIC_CHUNK)
        sim = torch.cat([(table[lo[c]] * table[hi[c]]).sum(-1) for c in chunks])
        ok[differ] = (sim >= min_sim).cpu().numpy()[inverse.ravel()]
    return ok


def _mergeable(
    endpoints: np.ndarray,
    table: torch.Tensor,
    rows: np.ndarray,
    cfg: PrimitiveConfig,
    query: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mergeable pairs (i < j, sorted) and their |sin angle|; with `query`, only pairs touching it."""
    pairs = _candidate_pairs(endpoints, cfg.line_merge_dist_m, query)
    ok, sin = _merge_test(endpoints, pairs, cfg)
    pairs, sin = pairs[ok], sin[ok]
    keep = _semantic_ok(table, rows, pairs, cfg.line_merge_semantic_sim)
    return pairs[keep], sin[keep]


def mergeable_line_pairs(
    endpoints: np.ndarray, descriptors: torch.Tensor, cfg: PrimitiveConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i < j) of lines (N, 2, 2) passing the merge test, (E, 2), and its |sin angle| (E,).

    The test (reference `clean_up_line_map`, with A = line i, B = line j): angle below the
    tolerance (relaxed for lines shorter than `line_merge_short_m`); descriptor cosine
    similarity >= `line_merge_semantic_sim`; gap between the segments < `line_merge_dist_m`;
    nearly parallel lines (|sin| < 1e-3): B's first endpoint within `line_merge_perp_dist_m` of
    line A; otherwise the segments' closest points each within that distance of the other line.
    Vectorized over the candidate pairs of a grid search (a superset of the pairs closer than the gap
    limit), never over all N^2 pairs.
    """
    endpoints = np.asarray(endpoints, dtype=np.float64).reshape(-1, 2, 2)
    if len(endpoints) < 2:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0)
    table = torch.nn.functional.normalize(descriptors, dim=-1)
    return _mergeable(endpoints, table, np.arange(len(endpoints)), cfg)


def _pseudo_random(keys: np.ndarray) -> np.ndarray:
    """splitmix64 of int keys: a deterministic, order-free tie-break."""
    z = keys.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _greedy_matching(pairs: np.ndarray, cost: np.ndarray, n: int) -> np.ndarray:
    """Disjoint pairs picked greedily by (binned cost, pseudo-random tie-break), (K, 2).

    Computed in rounds: a pair that ranks first for both of its lines is taken, all its lines'
    other pairs are dropped, repeat. This equals the sequential greedy matching, and the random
    tie-break keeps the number of rounds logarithmic on chains of equal-cost pairs.
    """
    order = np.lexsort((_pseudo_random(pairs[:, 0] * n + pairs[:, 1]), np.floor(cost / COST_BIN)))
    rank = np.empty(len(pairs), dtype=np.int64)
    rank[order] = np.arange(len(pairs))
    active = np.arange(len(pairs))
    matched = np.zeros(n, dtype=bool)
    chosen = []
    while active.size:
        best = np.full(n, len(pairs), dtype=np.int64)
        a, b, r = pairs[active, 0], pairs[active, 1], rank[active]
        np.minimum.at(best, a, r)
        np.minimum.at(best, b, r)
        dominant = active[(best[a] == r) & (best[b] == r)]
        chosen.append(dominant)
        matched[pairs[dominant].ravel()] = True
        active = active[~matched[a] & ~matched[b]]
    return pairs[np.concatenate(chosen)]


def _refit(original: np.ndarray, label: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """PCA line through all original endpoints of each group, clipped to their extreme projections."""
    members = np.flatnonzero(np.isin(label, groups))
    pts = original[members].reshape(-1, 2)
    gi = np.searchsorted(groups, np.repeat(label[members], 2))  # groups is sorted
    n = np.bincount(gi, minlength=len(groups)).astype(np.float64)
    mean = np.stack([np.bincount(gi, pts[:, k], minlength=len(groups)) for k in range(2)], 1) / n[:, None]
    c = pts - mean[gi]
    sxx, syy, sxy = (
        np.bincount(gi, w, minlength=len(groups)) for w in (c[:, 0] ** 2, c[:, 1] ** 2, c[:, 0] * c[:, 1])
    )
    phi = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # major axis of the 2x2 scatter matrix
    direction = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    t = (c * direction[gi]).sum(1)
    t_min = np.full(len(groups), np.inf)
    t_max = np.full(len(groups), -np.inf)
    np.minimum.at(t_min, gi, t)
    np.maximum.at(t_max, gi, t)
    return np.stack([mean + t_min[:, None] * direction, mean + t_max[:, None] * direction], axis=1)


def fuse_indexed_lines(
    original: np.ndarray, table: torch.Tensor, rows: np.ndarray, cfg: PrimitiveConfig
) -> tuple[np.ndarray, torch.Tensor, np.ndarray, np.ndarray]:
    """Fusion sweeps over lines whose descriptors are rows of a table (L2-normalized).

    Descriptors stay deduplicated: a merge of two lines on one row keeps that row, only a
    merge of different rows appends one. Returns (endpoints, table, rows, label: input line ->
    fused line).
    """
    current = original.copy()
    label = np.arange(len(original))
    pairs, sin = None, None
    for sweep in range(cfg.line_merge_max_sweeps):
        if len(current) < 2:
            break
        if pairs is None:
            pairs, sin = _mergeable(current, table, rows, cfg)
        if len(pairs) == 0:
            break
        merged = _greedy_matching(pairs, sin, len(current))
        a, b = merged[:, 0], merged[:, 1]
        mixed = rows[a] != rows[b]
        if mixed.any():
            lengths = torch.from_numpy(np.linalg.norm(current[:, 1] - current[:, 0], axis=1)).to(table)
            am, bm = torch.from_numpy(a[mixed]), torch.from_numpy(b[mixed])
            ra, rb = torch.from_numpy(rows[a[mixed]]), torch.from_numpy(rows[b[mixed]])
            new = lengths[am, None] * table[ra] + lengths[bm, None] * table[rb]
            rows = rows.copy()
            rows[a[mixed]] = len(table) + np.arange(int(mixed.sum()))
            table = torch.cat([table, torch.nn.functional.normalize(new, dim=-1)])
        keep = np.ones(len(current), dtype=bool)
        keep[b] = False
        target = np.arange(len(current))
        target[b] = a
        remap = (np.cumsum(keep) - 1)[target]
        label = remap[label]
        # Pairs of two untouched lines keep their geometry and descriptors, hence their test
        # result: keep them (renumbered; the order and i < j survive) and test only the pairs
        # of the refitted lines. The pair set equals a full recomputation.
        touched = ~keep
        touched[a] = True
        untouched = ~(touched[pairs[:, 0]] | touched[pairs[:, 1]])
        pairs, sin = remap[pairs[untouched]], sin[untouched]
        current, rows = current[keep], rows[keep]
        groups = np.sort(remap[a])
        current[groups] = _refit(original, label, groups)
        if sweep + 1 < cfg.line_merge_max_sweeps and len(current) >= 2:
            new_pairs, new_sin = _mergeable(current, table, rows, cfg, groups)
            pairs = np.concatenate([pairs, new_pairs])
            sin = np.concatenate([sin, new_sin])
            order = np.argsort(pairs[:, 0] * len(current) + pairs[:, 1])  # keys are distinct
            pairs, sin = pairs[order], sin[order]
    return current, table, rows, label


def fuse_lines(
    endpoints: np.ndarray, descriptors: torch.Tensor, cfg: PrimitiveConfig
) -> tuple[np.ndarray, torch.Tensor, list[np.ndarray]]:
    """Fuse fine lines (N, 2, 2) with descriptors (N, D) into coarse lines.

    Returns (endpoints (M, 2, 2) float64, L2-normalized descriptors (M, D), member indices: for
    each fused line the sorted input lines it holds). Lines must have positive length.

    Each sweep finds every mergeable pair at once (`mergeable_line_pairs`), picks disjoint
    pairs greedily, best aligned first, and merges them all: the merged line is the PCA fit to
    all pooled original endpoints, clipped to their extreme projections, and its descriptor the
    length-weighted sum of both, normalized. Sweeps repeat until nothing merges. Every merge
    passes the same test as in the reference; the reference instead merges each line with the
    first later mergeable line, one at a time, so its result depends on input order. Ours does
    not (up to index tie-breaks), takes ~log2(N) sweeps instead of up to N, and merges the
    best-aligned pairs first, so short corner edges are not absorbed before collinear ones.
    The mergeable pairs are carried over between sweeps: only the pairs of refitted lines are
    tested again (pairs of untouched lines keep their result), which gives the same pair sets.
    """
    original = np.asarray(endpoints, dtype=np.float64).reshape(-1, 2, 2)
    if len(original) != len(descriptors):
        raise ValueError("fuse_lines: one descriptor per line expected")
    if (np.linalg.norm(original[:, 1] - original[:, 0], axis=1) <= 0).any():
        raise ValueError("fuse_lines: lines must have positive length")
    table, rows = torch.unique(torch.nn.functional.normalize(descriptors, dim=-1), dim=0, return_inverse=True)
    lines, table, rows, label = fuse_indexed_lines(original, table, rows.cpu().numpy(), cfg)
    return lines, table[torch.from_numpy(rows)], _members(label, len(lines))


def _members(label: np.ndarray, n: int) -> list[np.ndarray]:
    order = np.argsort(label, kind="stable")
    return np.split(order, np.cumsum(np.bincount(label, minlength=n))[:-1])

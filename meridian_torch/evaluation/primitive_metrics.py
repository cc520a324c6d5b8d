"""Extracted point/line primitives against ground truth (pure numpy; world metres).

Points
    `point_metrics` matches predictions to ground truth one-to-one with an optimal assignment
    (Hungarian, `scipy.optimize.linear_sum_assignment`, run per connected component of the
    "within `radius`" graph): it finds the largest number of pairs closer than `radius` and,
    among those, the smallest total distance. precision = matched / predictions,
    recall = matched / ground truth.

Lines, measured by length
    Every predicted segment and every ground-truth polyline is cut into pieces of at most
    `sample_step` metres, each represented by its midpoint and weighted by its length. A piece is
    *covered* when a segment of the other side lies within `dist` of its midpoint (measured
    perpendicularly: the foot of the perpendicular must fall on the segment, so a line does not
    cover `dist` metres beyond its ends) and its direction (undirected) is within `angle_deg`.
    precision = covered predicted length / predicted length; recall = covered GT length / GT length.

Duplicates (overlapping patches)
    An aerial map tiles the image with 50 % overlap, so most primitives appear in 2-4 patches.
    Points are de-duplicated first (`dedup_points`: leader clustering within `merge_m` = 0.5 m,
    each cluster replaced by its mean). Lines are evaluated as a union: a predicted piece that
    lies within `merge_m` of a piece of an *earlier* predicted segment with a compatible
    direction is a duplicate and counts neither in the predicted length nor in the covered length
    (`union_mask`). Recall is coverage and needs no de-duplication (any copy covers); GT pieces
    are de-duplicated the same way, so a GT edge listed twice is counted once.

Region
    With `region` = (x_min, x_max, y_min, y_max) shrunk by `margin`, only predictions and ground
    truth inside the region are counted, but they may be matched/covered by partners just outside
    it (within `radius` / `dist`), so objects on the region's edge are not penalised.
    Pass the image extent and a margin (e.g. a few metres) so image borders do not count.
    Empty denominators give NaN.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = [
    "Region",
    "shrink_region",
    "in_region",
    "dedup_points",
    "point_metrics",
    "sample_segments",
    "union_mask",
    "line_metrics",
    "polygon_ring",
    "polygon_area",
    "world_ground_truth",
    "batch_primitives",
    "COMPACT_MAX_AREA_M2",
]

Region = tuple[float, float, float, float]  # x_min, x_max, y_min, y_max


def shrink_region(region: Region, margin: float) -> Region:
    x0, x1, y0, y1 = region
    return (x0 + margin, x1 - margin, y0 + margin, y1 - margin)


def in_region(xy: np.ndarray, region: Region | None, pad: float = 0.0) -> np.ndarray:
    """(N,) mask of the points inside `region` grown by `pad` (all True without a region)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if region is None:
        return np.ones(len(xy), dtype=bool)
    x0, x1, y0, y1 = region
    return (xy[:, 0] >= x0 - pad) & (xy[:, 0] <= x1 + pad) & (xy[:, 1] >= y0 - pad) & (xy[:, 1] <= y1 + pad)


def polygon_ring(polygon_xy: np.ndarray) -> np.ndarray:
    """A closed polygon (K, 2) without repeated first vertex -> polyline (K+1, 2) closing the ring."""
    p = np.asarray(polygon_xy, dtype=np.float64).reshape(-1, 2)
    if len(p) and not np.array_equal(p[0], p[-1]):
        p = np.vstack([p, p[:1]])
    return p


# ------------------------------------------------------------------------------------ points


def dedup_points(xy: np.ndarray, merge_m: float = 0.5) -> np.ndarray:
    """Merge points closer than `merge_m` (leader clustering in input order; cluster -> mean).

    Each not-yet-assigned point in turn takes all unassigned points within `merge_m` of it; no
    chaining, so a cluster never spans more than 2 * merge_m.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) < 2 or merge_m <= 0:
        return xy.copy()
    neighbours = cKDTree(xy).query_ball_point(xy, merge_m)
    assigned = np.zeros(len(xy), dtype=bool)
    out = []
    for i, nb in enumerate(neighbours):
        if assigned[i]:
            continue
        nb = np.asarray(nb, dtype=np.int64)
        nb = nb[~assigned[nb]]
        assigned[nb] = True
        out.append(xy[nb].mean(axis=0))
    return np.asarray(out).reshape(-1, 2)


def _match_points(pred: np.ndarray, gt: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Optimal one-to-one matching (max pairs within radius, then min total distance): (pred_idx, gt_idx)."""
    if len(pred) == 0 or len(gt) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = cKDTree(pred).sparse_distance_matrix(cKDTree(gt), radius, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pi, gi, d = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64), pairs["v"]
    n_p = len(pred)
    graph = coo_matrix((np.ones(len(pi)), (pi, gi + n_p)), shape=(n_p + len(gt),) * 2)
    _, label = connected_components(graph, directed=False)
    comp = label[pi]
    order = np.argsort(comp, kind="stable")
    pi, gi, d, comp = pi[order], gi[order], d[order], comp[order]
    splits = np.flatnonzero(np.diff(comp)) + 1
    out_p, out_g = [], []
    for sl in np.split(np.arange(len(pi)), splits):
        up, ip = np.unique(pi[sl], return_inverse=True)
        ug, ig = np.unique(gi[sl], return_inverse=True)
        if len(sl) == 1:
            out_p.append(up)
            out_g.append(ug)
            continue
        big = radius * (min(len(up), len(ug)) + 1) + 1.0  # > any sum of allowed costs: cardinality first
        cost = np.full((len(up), len(ug)), big)
        cost[ip, ig] = d[sl]
        r, c = linear_sum_assignment(cost)
        ok = cost[r, c] <= radius
        out_p.append(up[r[ok]])
        out_g.append(ug[c[ok]])
    return np.concatenate(out_p), np.concatenate(out_g)


def _ratio(num: float, den: float) -> float:
    return float(num) / float(den) if den > 0 else float("nan")


def point_metrics(
    pred_xy: np.ndarray,
    gt_xy: np.ndarray,
    radius: float = 2.0,
    *,
    region: Region | None = None,
    margin: float = 0.0,
    merge_m: float | None = 0.5,
) -> dict[str, float]:
    """Precision/recall of predicted points within `radius` of GT points (optimal one-to-one matching).

    Predictions are de-duplicated with `dedup_points(merge_m)` first (None or 0: not). With a
    `region` (shrunk by `margin`), counts are restricted to it; partners within `radius` outside
    it still match. Returns precision, recall, n_pred, n_gt (counts inside the region, after
    de-duplication) and n_matched.
    """
    pred = np.asarray(pred_xy, dtype=np.float64).reshape(-1, 2)
    gt = np.asarray(gt_xy, dtype=np.float64).reshape(-1, 2)
    if merge_m:
        pred = dedup_points(pred, merge_m)
    reg = None if region is None else shrink_region(region, margin)
    pred = pred[in_region(pred, reg, radius)]
    gt = gt[in_region(gt, reg, radius)]
    p_in, g_in = in_region(pred, reg), in_region(gt, reg)
    mp, mg = _match_points(pred, gt, radius)
    tp_p = int(p_in[mp].sum())
    tp_g = int(g_in[mg].sum())
    n_pred, n_gt = int(p_in.sum()), int(g_in.sum())
    return {
        "precision": _ratio(tp_p, n_pred),
        "recall": _ratio(tp_g, n_gt),
        "n_pred": n_pred,
        "n_gt": n_gt,
        "n_matched": int(min(tp_p, tp_g)),
    }


# ------------------------------------------------------------------------------------- lines


def _as_segments(polylines: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """(N, 2, 2) segments from an (N, 2, 2) array or a list of (K, 2) polylines."""
    if isinstance(polylines, np.ndarray) and polylines.ndim == 3 and polylines.shape[1:] == (2, 2):
        return polylines.astype(np.float64)
    segs = []
    for pl in polylines:
        pl = np.asarray(pl, dtype=np.float64).reshape(-1, 2)
        if len(pl) >= 2:
            segs.append(np.stack([pl[:-1], pl[1:]], axis=1))
    return np.concatenate(segs) if segs else np.zeros((0, 2, 2))


def sample_segments(segments: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cut segments (N, 2, 2) into pieces of at most `step`: (midpoints (S,2), unit dirs (S,2),
    lengths (S,), segment index (S,)). Zero-length segments give no pieces."""
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    vec = segments[:, 1] - segments[:, 0]
    length = np.linalg.norm(vec, axis=1)
    keep = length > 1e-9
    seg_idx = np.flatnonzero(keep)
    n = np.maximum(1, np.ceil(length[keep] / step)).astype(np.int64)
    rep = np.repeat(np.arange(len(seg_idx)), n)
    k = np.arange(len(rep)) - np.repeat(np.cumsum(n) - n, n)
    t = (k + 0.5) / n[rep]
    a, v = segments[seg_idx][rep, 0], vec[seg_idx][rep]
    mids = a + t[:, None] * v
    dirs = v / length[seg_idx][rep, None]
    return mids, dirs, (length[keep] / n)[rep], seg_idx[rep]


def _near_compatible_pairs(
    xy: np.ndarray, dirs: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray, dist: float, cos_min: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (sample i, target segment j) with the segment within `dist` of the sample's point
    and directions within the angle (|cos| >= cos_min)."""
    if len(xy) == 0 or len(seg_a) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # Targets cut into pieces <= piece_m so that a KD-tree on piece midpoints finds every candidate.
    piece_m = max(2.0 * dist, 1.0)
    t_mid, _, t_len, t_seg = sample_segments(np.stack([seg_a, seg_b], axis=1), piece_m)
    if len(t_mid) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    r = dist + 0.5 * float(t_len.max()) + 1e-9
    pairs = cKDTree(xy).sparse_distance_matrix(cKDTree(t_mid), r, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i = pairs["i"].astype(np.int64)
    j = t_seg[pairs["j"]]
    a, b = seg_a[j], seg_b[j]
    v = b - a
    L2 = np.maximum((v * v).sum(1), 1e-18)
    t = ((xy[i] - a) * v).sum(1) / L2
    on = (t >= -1e-9) & (t <= 1.0 + 1e-9)  # the perpendicular foot lies on the segment (no end caps)
    d = np.linalg.norm(xy[i] - (a + t[:, None] * v), axis=1)
    cos = np.abs((dirs[i] * v).sum(1)) / np.sqrt(L2)
    ok = on & (d <= dist) & (cos >= cos_min)
    return i[ok], j[ok]


def union_mask(
    mids: np.ndarray, dirs: np.ndarray, seg_idx: np.ndarray, segments: np.ndarray, merge_m: float, cos_min: float
) -> np.ndarray:
    """(S,) True for the pieces that are not duplicates: a piece is a duplicate when a segment of
    lower index lies within `merge_m` with a compatible direction (the union keeps the first copy)."""
    keep = np.ones(len(mids), dtype=bool)
    if not merge_m or len(mids) == 0:
        return keep
    i, j = _near_compatible_pairs(mids, dirs, segments[:, 0], segments[:, 1], merge_m, cos_min)
    dup = j < seg_idx[i]
    keep[i[dup]] = False
    return keep


def line_metrics(
    pred_segments: np.ndarray,
    gt_polylines: Sequence[np.ndarray] | np.ndarray,
    dist: float = 1.0,
    angle_deg: float = 10.0,
    sample_step: float = 0.25,
    *,
    region: Region | None = None,
    margin: float = 0.0,
    merge_m: float | None = 0.5,
) -> dict[str, float]:
    """Length-weighted precision/recall of predicted segments (N, 2, 2) against GT polylines.

    See the module docstring. Returns precision, recall, pred_length, gt_length (union lengths in
    metres inside the region), covered_pred_length, covered_gt_length, n_pred (segments given).
    """
    pred = _as_segments(np.asarray(pred_segments, dtype=np.float64).reshape(-1, 2, 2))
    gt = _as_segments(gt_polylines)
    cos_min = float(np.cos(np.radians(angle_deg)))
    reg = None if region is None else shrink_region(region, margin)

    def side(segs: np.ndarray, targets: np.ndarray) -> tuple[float, float]:
        mids, dirs, w, idx = sample_segments(segs, sample_step)
        keep = in_region(mids, reg) & union_mask(mids, dirs, idx, segs, merge_m or 0.0, cos_min)
        mids, dirs, w = mids[keep], dirs[keep], w[keep]
        i, _ = _near_compatible_pairs(mids, dirs, targets[:, 0], targets[:, 1], dist, cos_min)
        covered = np.zeros(len(mids), dtype=bool)
        covered[i] = True
        return float(w.sum()), float(w[covered].sum())

    pred_len, pred_cov = side(pred, gt)
    gt_len, gt_cov = side(gt, pred)
    return {
        "precision": _ratio(pred_cov, pred_len),
        "recall": _ratio(gt_cov, gt_len),
        "pred_length": pred_len,
        "gt_length": gt_len,
        "covered_pred_length": pred_cov,
        "covered_gt_length": gt_cov,
        "n_pred": int(len(pred)),
    }


# ------------------------------------------------------------------------- inputs / ground truth

COMPACT_MAX_AREA_M2 = 50.0  # simulated objects below this footprint are point ground truth


def polygon_area(polygon_xy: np.ndarray) -> float:
    p = np.asarray(polygon_xy, dtype=np.float64).reshape(-1, 2)
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)))


def world_ground_truth(
    world, compact_max_area_m2: float = COMPACT_MAX_AREA_M2
) -> tuple[np.ndarray, list[np.ndarray]]:
    """(points (M, 2), polylines) of a simulated `World` (meridian_torch.sim.world):

    points = centres of the compact non-building objects (tree, bush, rock, car) with footprint
    area < `compact_max_area_m2`; lines = every region border polyline plus every building
    footprint outline (closed ring). Fences are neither.
    """
    from meridian_torch.sim.classes import SimClass

    compact = (SimClass.TREE, SimClass.BUSH, SimClass.ROCK, SimClass.CAR)
    points = [o.centre_xy for o in world.objects
              if o.class_id in compact and polygon_area(o.footprint_xy) < compact_max_area_m2]
    lines = [np.asarray(b.polyline_xy, dtype=np.float64) for b in world.borders]
    lines += [polygon_ring(o.footprint_xy) for o in world.objects if o.class_id == SimClass.BUILDING]
    return np.asarray(points, dtype=np.float64).reshape(-1, 2), lines


def batch_primitives(primitives) -> tuple[np.ndarray, np.ndarray, int]:
    """(points (N, 2), segments (L, 2, 2), n_unbounded) of all valid entries of a `PrimitiveBatch`.

    Lines of kind RAY / INFINITE (not produced with the default config) are taken as the segment
    between their two stored endpoints; their number is returned so callers can report it.
    """
    pv = primitives.point_valid.cpu().numpy()
    lv = primitives.line_valid.cpu().numpy()
    points = primitives.points_xy.cpu().numpy()[pv].astype(np.float64)
    segments = primitives.line_endpoints.cpu().numpy()[lv].astype(np.float64)
    n_unbounded = int((primitives.line_kinds.cpu().numpy()[lv] != 0).sum())
    return points.reshape(-1, 2), segments.reshape(-1, 2, 2), n_unbounded

"""Segments to primitives: the per-segment point/line rules and the conversion of a set of segments
(rules in order, then fusion of all lines)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from meridian_torch.config.mapping import PrimitiveConfig
from meridian_torch.mapping.primitives.line_fusion import fuse_indexed_lines
from meridian_torch.mapping.primitives.outline import (
    alpha_shape_outline,
    inside_box,
    signed_area,
    simplified_outline_edges,
)
from meridian_torch.mapping.primitives.outline_kernels import convex_hull, minor_variance_lower_bound
from meridian_torch.types import LineKind, PrimitiveSet

__all__ = ["segments_to_primitives", "fit_circle"]

BorderBox = tuple[float, float, float, float]


def fit_circle(points: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """Least-squares (algebraic, Kasa) circle through 2D points: (centre (2,), radius, RMS radial residual).

    None for fewer than 3 points or collinear points.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(points) < 3:
        return None
    offset = points.mean(axis=0)  # centred for conditioning
    p = points - offset
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    b = (p**2).sum(axis=1)
    sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    if rank < 3:
        return None
    centre = sol[:2]
    r2 = sol[2] + centre @ centre
    if not r2 > 0:
        return None
    radius = float(np.sqrt(r2))
    residual = float(np.sqrt(np.mean((np.linalg.norm(p - centre, axis=1) - radius) ** 2)))
    return centre + offset, radius, residual


def _diameter(points: np.ndarray) -> float:
    """Largest distance between two points (over the convex hull's corners)."""
    if len(points) < 2:
        return 0.0
    corners = convex_hull(points)
    if len(corners) < 3:  # collinear: the extent along the principal axis
        centred = points - points.mean(axis=0)
        t = centred @ np.linalg.svd(centred, full_matrices=False)[2][0]
        return float(t.max() - t.min())
    hull = points[corners]
    return float(np.sqrt(((hull[:, None, :] - hull[None, :, :]) ** 2).sum(-1).max()))


def _covariance(points: np.ndarray) -> np.ndarray:
    """np.cov(points, rowvar=False, bias=True) of points (n, 2), n >= 1: its operations on the same
    memory layouts, so the same bits (tested), without its argument handling, which was half of a
    segment's principal-axes test."""
    x = np.array(points, dtype=np.float64).T  # a copy, one variable per row
    x -= x.mean(axis=1)[:, None]
    return np.dot(x, x.T.conj()) * np.true_divide(1, x.shape[1])


def _convert_segment(
    points: np.ndarray, area: float | None, box: np.ndarray, cfg: PrimitiveConfig
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Classify one segment: (point (2,) or None, lines (n, 2, 2) or None)."""
    if area is not None and area < cfg.min_area_m2:  # the outline cannot rescue it: skip that cost
        return None, None
    alpha = cfg.alpha
    if cfg.alpha_ref_size_m is not None:
        alpha *= min(1.0, cfg.alpha_ref_size_m / max(_diameter(points), 1e-9))
    outline = alpha_shape_outline(points, alpha, cfg.alpha_grid_m, cfg.alpha_max_points)
    if area is None:
        if outline is not None:
            area = abs(signed_area(outline))
        else:  # rasterized footprint, used only by the thin-line rule below
            area = len(np.unique(np.floor(points / cfg.alpha_grid_m), axis=0)) * cfg.alpha_grid_m**2
    if area < cfg.min_area_m2:
        return None, None

    if outline is not None and area < cfg.point_max_area_m2 and _diameter(points) < cfg.point_max_len_m:
        centre = points.mean(axis=0)
        return (centre, None) if inside_box(centre, box) else (None, None)

    max_minor_var = cfg.thin_line_max_minor_var_m2
    if max_minor_var > 0 and len(points) > 1 and minor_variance_lower_bound(points) < max_minor_var:
        mean = points.mean(axis=0)
        evals, evecs = np.linalg.eigh(_covariance(points - mean))
        if evals[0] < max_minor_var:
            t = (points - mean) @ evecs[:, 1]
            line = mean + np.outer([t.min(), t.max()], evecs[:, 1])
            ok = inside_box(line, box).all() and t.max() - t.min() > cfg.line_min_length_m
            return None, (line[None] if ok else None)
    if outline is None:
        return None, None

    if area < cfg.circle_max_area_m2:
        circle = fit_circle(outline)
        if circle is not None:
            centre, radius, residual = circle
            max_radius = np.sqrt(cfg.circle_max_area_m2 / np.pi)
            if 0 < radius < max_radius and residual < cfg.circle_max_fit_error_frac * radius:
                return (centre, None) if inside_box(centre, box) else (None, None)

    if cfg.outline_simplify_m > 0:
        edges = simplified_outline_edges(outline, box, cfg.outline_simplify_m)
    else:
        edges = np.stack([outline, np.roll(outline, -1, axis=0)], axis=1)  # closing edge included
        edges = edges[inside_box(edges, box).all(axis=1)]
    ok = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1) > cfg.line_min_length_m
    return None, (edges[ok] if ok.any() else None)


def _border_boxes(border_box: BorderBox | np.ndarray | None, n: int, margin: float) -> np.ndarray:
    if border_box is None:
        return np.tile(np.array([-np.inf, np.inf, -np.inf, np.inf]), (n, 1))
    boxes = np.broadcast_to(np.asarray(border_box, dtype=np.float64), (n, 4)).copy()
    return boxes + np.array([margin, -margin, margin, -margin])


def segments_to_primitives(
    segment_points: Sequence[np.ndarray],
    descriptors: torch.Tensor,
    cfg: PrimitiveConfig,
    *,
    areas_m2: np.ndarray | None = None,
    border_box: BorderBox | np.ndarray | None = None,
    segment_ids: Sequence[int] | np.ndarray | None = None,
) -> PrimitiveSet:
    """Convert S segments (point sets (K, 2) in metres) with descriptors (S, D) to points and lines.

    `areas_m2` (S,) overrides the outline area (aerial: pixel-count area). `border_box` is
    (x_min, x_max, y_min, y_max) in the points' frame, or (S, 4) per segment (segments of several
    sub-crops converted and fused in one call); primitives must lie `border_margin_m` inside it.
    None means unbounded (ground). `segment_ids` default to 0..S-1. Points and lines inherit
    their segment's normalized descriptor; fused lines the length-weighted mean, normalized,
    and the id of the segment contributing most of their length. Everything stays in the
    caller's frame; floating outputs take the descriptor dtype (float32 if it is not floating).
    """
    n_seg = len(segment_points)
    if descriptors.ndim != 2 or descriptors.shape[0] != n_seg:
        raise ValueError(f"descriptors: expected shape ({n_seg}, D), got {tuple(descriptors.shape)}")
    dtype = descriptors.dtype if descriptors.is_floating_point() else torch.float32
    device = descriptors.device
    desc = torch.nn.functional.normalize(descriptors.detach().to("cpu", torch.float64), dim=-1)
    ids = np.arange(n_seg) if segment_ids is None else np.asarray(segment_ids, dtype=np.int64)
    if ids.shape != (n_seg,):
        raise ValueError(f"segment_ids: expected {n_seg} ids")
    if areas_m2 is not None and np.shape(areas_m2) != (n_seg,):
        raise ValueError(f"areas_m2: expected shape ({n_seg},)")
    boxes = _border_boxes(border_box, n_seg, cfg.border_margin_m)

    point_xy, point_seg, line_ep, line_seg = [], [], [], []
    for s, pts in enumerate(segment_points):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            continue
        area = None if areas_m2 is None else float(areas_m2[s])
        point, lines = _convert_segment(pts, area, boxes[s], cfg)
        if point is not None:
            point_xy.append(point)
            point_seg.append(s)
        if lines is not None:
            line_ep.append(lines)
            line_seg.append(np.full(len(lines), s))

    if line_ep:
        fine = np.concatenate(line_ep)
        fine_seg = np.concatenate(line_seg)
        lines, table, rows, label = fuse_indexed_lines(fine, desc, fine_seg, cfg)
        line_desc = table[torch.from_numpy(rows)]
        # the segment contributing most of each fused line's length
        fine_len = np.linalg.norm(fine[:, 1] - fine[:, 0], axis=1)
        order = np.lexsort((-fine_len, label))
        first = np.searchsorted(label[order], np.arange(len(lines)))
        line_src = fine_seg[order[first]]
    else:
        lines, line_desc, line_src = np.zeros((0, 2, 2)), desc[:0], np.zeros(0, dtype=np.int64)
    kinds = np.full(len(lines), int(LineKind.SEGMENT), dtype=np.int64)
    if cfg.line_len_to_infinite is not None:
        too_long = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1) > cfg.line_len_to_infinite
        kinds[too_long] = int(LineKind.INFINITE)

    point_seg_arr = np.asarray(point_seg, dtype=np.int64)
    f = dict(dtype=dtype, device=device)
    return PrimitiveSet(
        points_xy=torch.as_tensor(np.asarray(point_xy).reshape(-1, 2)).to(**f),
        point_descriptors=desc[torch.from_numpy(point_seg_arr)].to(**f),
        point_segment_ids=torch.from_numpy(ids[point_seg_arr]).to(device),
        line_endpoints=torch.as_tensor(lines).to(**f),
        line_kinds=torch.from_numpy(kinds).to(device),
        line_descriptors=line_desc.to(**f),
        line_segment_ids=torch.from_numpy(ids[line_src]).to(device),
    )

"""Per-frame ground observations: RGB-D frame + masks -> 3D segment point clouds in the odom frame.

For every mask of a frame (reference `Segmenter.segment`, paper III-A):
1. erode it with an elliptical kernel (radius `erosion_px`) and back-project the valid depth
   pixels inside it on a `pixel_stride` grid (0 < depth < `max_depth_m`);
2. voxel-downsample (global lattice floor(p / voxel_m)), remove statistical outliers and keep the
   largest DBSCAN cluster;
3. mark *occluded* points, where the object may continue outside the view: the mask's pixels
   deeper than `occlusion_max_depth_m` (depth-cutoff band) or in the image-edge band
   (`edge_band`), back-projected at full resolution (the reference takes the deep points of the
   cleaned cloud, which at the sparsely sampled far range are often cleaned away); real points
   deeper than that or closer than `occluded_clearance_m` to an occluded point are deleted, and a
   mask left without real points gives no observation.

All masks of a frame are processed together: the clouds are stored flat with an observation
index (`point_obs`), and the point-cloud operations below work on such grouped clouds in one
call (compiled kernels in `cloud_kernels` search each group on its own grid).

Points are moved to the odom frame before the voxel grid, so every voxel key of the pipeline
lives on one global lattice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from meridian_torch.config import GroundObservationConfig
from meridian_torch.core.parallel import thread_map
from meridian_torch.core.timing import stage
from meridian_torch.io.camera import CameraModel
from meridian_torch.mapping.cloud_kernels import (
    group_any_within,
    group_dbscan_labels,
    group_knn_distances,
    group_voxel_order,
    run_means,
)
from meridian_torch.perception.protocols import SegmentDescriber, Segmenter

__all__ = [
    "FrameObservations",
    "VOXEL_INDEX_LIMIT",
    "voxel_hash",
    "voxel_unhash",
    "separate_groups",
    "group_key_runs",
    "group_voxel_runs",
    "group_unique",
    "group_voxel_downsample",
    "group_any_point_within",
    "group_outlier_mask",
    "group_largest_cluster",
    "edge_band",
    "erode_masks",
    "pixel_stride",
    "backproject",
    "frame_observations",
    "observe_frames",
]

VOXEL_INDEX_LIMIT = 1 << 20  # 21 bits per axis in a voxel hash: +-2^20 voxels (105 km at 0.1 m)
_BITS = 21
_MASK = (1 << _BITS) - 1


@dataclass(frozen=True)
class FrameObservations:
    """The K observations (3D segments) of one frame, odom frame, stored flat by observation."""

    time: float
    T_odom_camera: np.ndarray  # (4, 4)
    points: np.ndarray  # (N, 3) float64, odom frame, voxel-downsampled and cleaned
    point_obs: np.ndarray  # (N,) int64 observation index in 0..K-1, non-decreasing
    occluded: np.ndarray  # (Q, 3) float64 occluded points, odom frame
    occluded_obs: np.ndarray  # (Q,) int64 observation index, non-decreasing
    descriptors: torch.Tensor  # (K, D) L2-normalized
    mask_index: np.ndarray  # (K,) int64 index of the source mask among the frame's valid masks

    def __len__(self) -> int:
        return int(self.descriptors.shape[0])


# ------------------------------------------------------------------------- grouped point clouds


def voxel_hash(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N,) int64 key of each point's voxel on the global lattice floor(p / voxel_m) (x, y, z).

    2D points (N, 2) use z index 0. Raises ValueError beyond +-2^20 voxels per axis.
    """
    idx = np.floor(np.asarray(points, dtype=np.float64) / voxel_m).astype(np.int64)
    if idx.shape[1] == 2:
        idx = np.concatenate([idx, np.zeros((len(idx), 1), np.int64)], axis=1)
    if idx.size and np.abs(idx).max() >= VOXEL_INDEX_LIMIT:
        raise ValueError(f"points beyond {VOXEL_INDEX_LIMIT} voxels of {voxel_m} m from the origin")
    idx += VOXEL_INDEX_LIMIT
    return (idx[:, 0] << (2 * _BITS)) | (idx[:, 1] << _BITS) | idx[:, 2]


def voxel_unhash(keys: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N, 3) centres of the voxels with these keys (inverse of `voxel_hash`)."""
    keys = np.asarray(keys, dtype=np.int64)
    idx = np.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], axis=1)
    return (idx - VOXEL_INDEX_LIMIT + 0.5) * voxel_m


def group_key_runs(keys: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stable sort by (group, key): (order (N,), first (N,) bool, True where a sorted row starts a
    run of equal (group, key); a run starts at its first occurrence)."""
    order = np.lexsort((keys, groups))
    k, g = keys[order], groups[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = (k[1:] != k[:-1]) | (g[1:] != g[:-1])
    return order, first


def group_voxel_runs(points: np.ndarray, groups: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """`group_key_runs(voxel_hash(points, voxel_m), groups)`, the same order, in one compiled pass
    (a radix sort of frame-sized index ranges instead of NumPy's two-key merge sort)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    order, first, largest = group_voxel_order(points, np.ascontiguousarray(groups, dtype=np.int64), float(voxel_m))
    if largest >= VOXEL_INDEX_LIMIT:
        raise ValueError(f"points beyond {VOXEL_INDEX_LIMIT} voxels of {voxel_m} m from the origin")
    if len(order) != len(points):  # ranges too wide for one key
        return group_key_runs(voxel_hash(points, voxel_m), groups)
    return order, first


def group_unique(keys: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`np.unique(return_index=True)` of every group's keys in one sort: (keys, groups, index of
    each key's first occurrence), sorted by group, then key."""
    order, first = group_key_runs(keys, groups)
    at = order[first]
    return keys[at], groups[at], at


def group_voxel_downsample(
    values: np.ndarray, groups: np.ndarray, voxel_m: float, dims: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Mean of `values` (N, C) float64 per (group, voxel of the first `dims` columns): (values (M, C), groups (M,)).

    Output is sorted by group, then voxel key.
    """
    if len(values) == 0:
        return values.reshape(0, values.shape[1]), groups[:0]
    order, first = group_voxel_runs(values[:, :dims], groups, voxel_m)
    means, heads, _ = run_means(np.ascontiguousarray(values, dtype=np.float64), order, first)
    return means, groups[heads]


def separate_groups(points: np.ndarray, groups: np.ndarray, gap: float) -> np.ndarray:
    """Points of each group moved along x so that groups are at least `gap` apart (the coordinates
    the former KD-tree searches saw, kept so that distances stay bitwise the same)."""
    if len(points) == 0:
        return points.astype(np.float64)
    # per-group minimum by one sort and reduceat (np.minimum.at is ~10x slower); the sort is
    # linear on the already sorted groups of the cleaning steps
    order = np.argsort(groups, kind="stable")
    sorted_groups = groups[order]
    start = _group_starts(sorted_groups)[:-1]
    lo = np.full((int(groups.max()) + 1, points.shape[1]), np.inf)
    lo[sorted_groups[start]] = np.minimum.reduceat(points[order], start, axis=0)
    local = points - lo[groups]
    width = float(local.max()) + gap
    shifted = local.copy()
    shifted[:, 0] += groups * width
    return shifted


def _group_starts(sorted_groups: np.ndarray) -> np.ndarray:
    """(G + 1,) first row of every group of a sorted group column, and the row count."""
    return np.r_[0, np.flatnonzero(sorted_groups[1:] != sorted_groups[:-1]) + 1, len(sorted_groups)]


def group_any_point_within(queries: np.ndarray, query_groups: np.ndarray, points: np.ndarray,
                           point_groups: np.ndarray, radius: float) -> np.ndarray:
    """(Q,) whether some point of each query's group lies within `radius` of it (squared distance
    < radius^2, as cKDTree's distance_upper_bound), on the groups moved apart as for the former
    KD-tree (`separate_groups`: the same coordinates, hence the same decisions). Groups need not
    be sorted."""
    found = np.zeros(len(queries), dtype=bool)
    if len(queries) == 0 or len(points) == 0:
        return found
    both = separate_groups(np.concatenate([queries, points]), np.concatenate([query_groups, point_groups]), 1e6)
    by_query, by_point = np.argsort(query_groups, kind="stable"), np.argsort(point_groups, kind="stable")
    bounds = np.arange(max(query_groups.max(), point_groups.max()) + 2)
    found[by_query] = group_any_within(
        np.ascontiguousarray(both[: len(queries)][by_query]), np.searchsorted(query_groups[by_query], bounds),
        np.ascontiguousarray(both[len(queries):][by_point]), np.searchsorted(point_groups[by_point], bounds),
        float(radius))
    return found


def group_outlier_mask(points: np.ndarray, groups: np.ndarray, neighbours: int, std_ratio: float) -> np.ndarray:
    """Statistical outlier removal per group: (N,) True for points whose mean distance to their
    `neighbours` nearest neighbours (same group) is at most the group's mean + std_ratio * std.

    Points without any neighbour in their group are kept. Points are (N, 2) or (N, 3).
    """
    keep = np.ones(len(points), dtype=bool)
    if len(points) < 2:
        return keep
    # the exact k-NN distances on the groups moved apart as for the former KD-tree: the same
    # coordinates give the same distances bitwise, hence the same mask
    shifted = separate_groups(points, groups, 1e6)
    order = np.argsort(groups, kind="stable")
    dist = np.empty((len(points), neighbours))
    dist[order] = group_knn_distances(np.ascontiguousarray(shifted[order]), _group_starts(groups[order]), neighbours)
    found = np.isfinite(dist)
    n_found = found.sum(axis=1)
    mean_d = np.where(found, dist, 0.0).sum(axis=1) / np.maximum(n_found, 1)
    has = n_found > 0
    n_groups = int(groups.max()) + 1
    cnt = np.bincount(groups[has], minlength=n_groups)
    mu = np.bincount(groups[has], mean_d[has], minlength=n_groups) / np.maximum(cnt, 1)
    var = np.bincount(groups[has], (mean_d[has] - mu[groups[has]]) ** 2, minlength=n_groups) / np.maximum(cnt, 1)
    keep[has] = mean_d[has] <= mu[groups[has]] + std_ratio * np.sqrt(var[groups[has]])
    return keep


def group_largest_cluster(
    points: np.ndarray, groups: np.ndarray, eps: float, min_points: int
) -> tuple[np.ndarray, np.ndarray]:
    """DBSCAN per group, keeping each group's largest cluster: (keep (N,), has_cluster (G,)).

    For speed the points are first binned to a grid of eps / 4 cells; each occupied cell is one
    point (the mean of its points) weighted by its count (neighbour counts and cluster sizes are
    weighted sums). Distances are then off by at most a cell diagonal; on clouds voxelized at
    eps / 4 or finer (e.g. 0.1 m voxels and eps >= 0.4 m) this changes few points. A cell is core
    when the weight within eps, its own included, reaches `min_points`; core cells within eps are
    connected; a border cell joins the cluster of its nearest core cell within eps (ties: the
    lowest cell in (group, voxel key) order); noise is dropped. The largest cluster by weight wins
    (ties: the one whose first core cell comes first).
    """
    n_groups = int(groups.max()) + 1 if len(groups) else 0
    if len(points) == 0:
        return np.zeros(0, dtype=bool), np.zeros(n_groups, dtype=bool)
    cell = eps / 4.0
    order, first = group_voxel_runs(points, groups, cell)
    cell_of = np.empty(len(points), dtype=np.int64)
    cell_of[order] = np.cumsum(first) - 1
    rep, heads, counts = run_means(np.ascontiguousarray(points, dtype=np.float64), order, first)
    weight = counts.astype(np.float64)
    rep_group = groups[heads]
    n = len(rep)
    label = group_dbscan_labels(rep, weight, _group_starts(rep_group), float(eps), float(min_points))
    clustered = label >= 0
    has_cluster = np.zeros(n_groups, dtype=bool)
    keep_cell = np.zeros(n, dtype=bool)
    if clustered.any():
        size = np.bincount(label[clustered], weight[clustered])
        cluster_group = np.zeros(len(size), dtype=np.int64)
        cluster_group[label[clustered]] = rep_group[clustered]
        # largest cluster per group (ties: lowest label)
        by = np.lexsort((np.arange(len(size)), -size, cluster_group))
        first = by[np.r_[True, cluster_group[by][1:] != cluster_group[by][:-1]]]
        first = first[size[first] > 0]
        best = np.zeros(len(size), dtype=bool)
        best[first] = True
        has_cluster[cluster_group[first]] = True
        keep_cell[clustered] = best[label[clustered]]
    return keep_cell[cell_of], has_cluster


# ------------------------------------------------------------------------------- one frame


def edge_band(valid_depth: np.ndarray, frac: float, max_frac: float) -> np.ndarray:
    """(H, W) bool band along the image border / the border of the valid-depth region.

    Per row, the left band is [0, min(first valid column + e, E)) and the right band
    [max(last valid column - e, W - E), W); per column the same for top and bottom, with
    e = frac * max(H, W) and E = max_frac * max(H, W) (reference rule). Rows / columns without
    valid depth have no band.
    """
    h, w = valid_depth.shape
    e = frac * max(h, w)
    cap = max_frac * max(h, w)

    def bands(valid: np.ndarray) -> np.ndarray:  # along axis 1
        length = valid.shape[1]
        first = valid.argmax(axis=1)
        last = length - 1 - valid[:, ::-1].argmax(axis=1)
        idx = np.arange(length)[None]
        band = (idx < np.minimum(first + e, cap)[:, None]) | (idx >= np.maximum(last - e, length - cap)[:, None])
        return band & valid.any(axis=1)[:, None]

    return bands(valid_depth) | bands(valid_depth.T).T


def backproject(u: np.ndarray, v: np.ndarray, z: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Pixels (u column, v row) with depth z along the optical axis -> (N, 3) camera-frame points."""
    z = z.astype(np.float64)
    return np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], axis=1)


def _nonzero(a: np.ndarray) -> tuple[np.ndarray, ...]:
    # np.nonzero's result, ~6x faster on the (M, H, W) masks (flat indices, then unravelled)
    return np.unravel_index(np.flatnonzero(a), a.shape)


def _transform(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    # a contiguous rotation: matmul with the transposed view is 3-4x slower (~8 ms on 90k points)
    return points @ np.ascontiguousarray(T[:3, :3].T) + T[:3, 3]


def erode_masks(masks: np.ndarray, radius: int) -> np.ndarray:
    """(M, H, W) bool masks eroded by an elliptical kernel of size 2r+1 (cv2.MORPH_ELLIPSE);
    pixels outside the image count as inside, so masks touching the border are not cut there."""
    import cv2

    if radius <= 0 or len(masks) == 0:
        return masks
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    out = np.empty_like(masks)
    for i, m in enumerate(masks):  # one C call per mask (~0.2 ms at 480x270)
        out[i] = cv2.erode(m.view(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=1).view(bool)
    return out


REFERENCE_STRIDE_WIDTH_PX = 1280  # image width at which the reference's stride of 4 applies


def pixel_stride(cfg: GroundObservationConfig, width: int) -> int:
    """The configured pixel stride, or 4 scaled to the image width and rounded down (at least 1).

    Rounded down because far ground is foreshortened: at 480 px (demo camera) a stride of 2
    leaves ~0.5 m between sampled rows at 8-9 m, which the 0.5 m DBSCAN cuts off (demo line
    precision 0.44 vs 0.72 with stride 1, scripts/eval_submaps.py).
    """
    if cfg.pixel_stride is not None:
        return cfg.pixel_stride
    return max(1, 4 * width // REFERENCE_STRIDE_WIDTH_PX)


def frame_observations(
    masks: torch.Tensor | np.ndarray,
    descriptors: torch.Tensor,
    depth: torch.Tensor | np.ndarray,
    T_odom_camera: np.ndarray,
    time: float,
    camera: CameraModel,
    cfg: GroundObservationConfig,
) -> FrameObservations:
    """Observations of one frame from its M valid masks (M, H, W) bool, their descriptors (M, D)
    and the depth image (H, W) in metres (0 or non-finite = no depth)."""
    masks = masks.cpu().numpy() if isinstance(masks, torch.Tensor) else np.asarray(masks, dtype=bool)
    depth = depth.cpu().numpy() if isinstance(depth, torch.Tensor) else np.asarray(depth)
    depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    T = np.asarray(T_odom_camera, dtype=np.float64)
    stride = pixel_stride(cfg, depth.shape[1])
    mask_ids = np.flatnonzero(masks.reshape(len(masks), -1).sum(axis=1) >= max(cfg.min_mask_pixels, 1))
    masks = masks[mask_ids]

    # 1. eroded masks on the strided pixel grid, valid depth only
    z_grid = depth[::stride, ::stride]
    ok_depth = (z_grid > 0) & (z_grid < cfg.max_depth_m)
    eroded = erode_masks(masks, cfg.erosion_px)[:, ::stride, ::stride]
    obs_m, row, col = _nonzero(eroded & ok_depth[None])
    z = z_grid[row, col]
    pts = _transform(backproject(col * float(stride), row * float(stride), z, camera), T)
    values = np.concatenate([pts, z[:, None].astype(np.float64)], axis=1)  # keep depth per point

    # 2. voxel grid, statistical outliers, largest DBSCAN cluster
    clean = cfg.cleanup
    values, groups = group_voxel_downsample(values, obs_m.astype(np.int64), clean.voxel_m)
    keep = group_outlier_mask(values[:, :3], groups, clean.outlier_neighbours, clean.outlier_std_ratio)
    values, groups = values[keep], groups[keep]
    keep, _ = group_largest_cluster(values[:, :3], groups, clean.dbscan_eps_m, clean.dbscan_min_points)
    values, groups = values[keep], groups[keep]

    # 3. occluded points: the mask's pixels (all, not strided or cleaned) in the depth-cutoff band
    # or the image-edge band. Far ground is sampled sparsely and the cleaning often drops it, so
    # the cloud's own deep points (the reference's rule) would leave the cutoff unmarked.
    deep = values[:, 3] > cfg.occlusion_max_depth_m
    band = edge_band(depth > 0, cfg.occlusion_edge_frac, cfg.occlusion_edge_max_frac)
    band |= depth > cfg.occlusion_max_depth_m
    band &= (depth > 0) & (depth < cfg.max_depth_m)
    b_row, b_col = _nonzero(band)
    b_m, b_k = _nonzero(masks[:, b_row, b_col])
    band_pts = _transform(backproject(b_col[b_k].astype(np.float64), b_row[b_k].astype(np.float64),
                                      depth[b_row[b_k], b_col[b_k]], camera), T)
    band_pts, band_groups = group_voxel_downsample(band_pts, b_m.astype(np.int64), clean.voxel_m)
    occ, occ_groups = band_pts, band_groups
    real, real_groups = values[~deep, :3], groups[~deep]
    if cfg.occluded_clearance_m > 0:
        clear = ~group_any_point_within(real, real_groups, occ, occ_groups, cfg.occluded_clearance_m)
        real, real_groups = real[clear], real_groups[clear]

    # observations = masks with real points left; renumber 0..K-1
    present = np.unique(real_groups)
    remap = np.full(len(mask_ids), -1, dtype=np.int64)
    remap[present] = np.arange(len(present))
    occ_keep = remap[occ_groups] >= 0
    occ, occ_groups = occ[occ_keep], remap[occ_groups[occ_keep]]
    order = np.argsort(occ_groups, kind="stable")
    src = mask_ids[present]
    return FrameObservations(
        time=float(time),
        T_odom_camera=T,
        points=real,
        point_obs=remap[real_groups],
        occluded=occ[order],
        occluded_obs=occ_groups[order],
        descriptors=descriptors[torch.from_numpy(src).to(descriptors.device)],
        mask_index=src,
    )


def observe_frames(
    images: torch.Tensor,
    depths: np.ndarray,
    T_odom_camera: np.ndarray,
    times: np.ndarray,
    segmenter: Segmenter,
    describer: SegmentDescriber,
    camera: CameraModel,
    cfg: GroundObservationConfig,
) -> list[FrameObservations]:
    """Observations of B frames: images (B, 3, H, W) in [0, 1], depths (B, H, W) metres,
    T_odom_camera (B, 4, 4), times (B,). Segmentation and description run on the whole batch, the
    3D work one frame per thread (`thread_map`)."""
    with stage("segmentation"):
        seg = segmenter.segment(images, None)
    with stage("segment descriptors"):
        desc = describer.describe(images, seg.masks, seg.valid)
    with stage("observations"):
        return thread_map(
            lambda b: frame_observations(seg.masks[b][seg.valid[b]], desc[b][seg.valid[b]], depths[b],
                                         T_odom_camera[b], float(times[b]), camera, cfg),
            range(images.shape[0]),
        )

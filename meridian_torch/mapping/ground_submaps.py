"""Ground submaps: tracked 3D segments -> 2D point/line primitives in the odom x-y plane.

Trigger and selection (reference `process_submaps_2d`): every segment id that leaves the nursery
joins a "new" list; with `submap_trigger_new_segments` new ids (or, if `submap_trigger_path_m`
is set, any new id after that much travel) a submap takes them all plus the most recently seen
other segments, `submap_max_segments` in total (consecutive submaps
overlap). A submap sooner than `submap_min_interval_s` or `submap_min_path_m` of odometry after
the previous one is skipped and the new list cleared (newer reference gates). Once the robot is
localized, `SubmapTrigger.use_spacing` may switch the three spacing values
(`submap_spacing_after_fix`); a submap too close to the previous one is then postponed instead
of skipped: the submap centre (the new segments' median time) trails the robot, so skipping
would space submaps by much more than the configured travel.

Conversion (`submap_primitives`, reference `convert_submap_to_sparse_2d`):
1. crop every segment to `submap_radius_m` (3D distance) around the centre camera position;
   occluded points sharing an `occluded_grid_m` x-y cell with a real point are cleared, and the
   real points of the outer ring (radius - `occluded_ring_m`, radius] become occluded (the
   artificial cut of the crop);
2. flatten along the odom z axis (z = 0), clean each segment (voxel grid, statistical outliers,
   largest DBSCAN cluster), area = convex-hull area;
3. convert with `segments_to_primitives` (the aerial converter, no border box); points of flat
   segments (odom-z extent, 95th - 5th percentile, below `point_min_height_m`) are dropped - not
   in the reference: on the demo world such points are compact pieces of ground regions cut by
   the view (none within 2 m of a true object), while true object points come from segments
   0.8 m or more tall;
4. drop FOV / depth-cutoff artefact lines (`artifact_line_mask`): a line needs at least
   `artifact_min_near_fraction` of its `artifact_line_samples` samples within `artifact_dist_m`
   of its segment's points and at least `artifact_min_clear_fraction` farther than that from
   every occluded point of its segment.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from meridian_torch.config import GroundMapConfig
from meridian_torch.config.mapping import PrimitiveConfig, SubmapSpacingConfig
from meridian_torch.mapping.ground_observations import (
    VOXEL_INDEX_LIMIT,
    group_any_point_within,
    group_largest_cluster,
    group_outlier_mask,
    group_voxel_downsample,
    voxel_hash,
    voxel_unhash,
)
from meridian_torch.mapping.ground_tracking import SegmentStatus, SegmentTracker, TrackedSegment
from meridian_torch.mapping.primitives.conversion import segments_to_primitives
from meridian_torch.mapping.primitives.outline import signed_area
from meridian_torch.mapping.primitives.outline_kernels import convex_hull
from meridian_torch.types import LineKind, PrimitiveSet

__all__ = ["SubmapTrigger", "SubmapGeometry", "submap_primitives", "artifact_line_mask", "thin_by_distance"]

# margin of the box tests of the radius crop (a point's distance rounds far less)
_BOX_SLACK_M = 1e-6


@dataclass
class SubmapTrigger:
    """Bookkeeping of which segments are not yet in any submap."""

    cfg: GroundMapConfig
    pending: list[int] = field(default_factory=list)  # new ids, in order of appearance
    known: set[int] = field(default_factory=set)
    in_submap: set[int] = field(default_factory=set)
    last_time: float | None = None
    last_path_m: float | None = None
    spacing: SubmapSpacingConfig | None = None  # None: the cfg's submap_trigger_path_m / min_interval_s / min_path_m

    def use_spacing(self, spacing: SubmapSpacingConfig | None) -> None:
        """Space the following submaps by `spacing` (e.g. from the global fix on; None: the cfg's)."""
        self.spacing = spacing

    def observe(self, tracker: SegmentTracker) -> None:
        """Register the ids that left the nursery; forget ids that vanished (merged, deleted)."""
        live = {s.id for s in tracker.segments.values() if s.status != SegmentStatus.NURSERY}
        for sid in sorted(live - self.known):
            self.pending.append(sid)
        self.known = live
        self.pending = [sid for sid in self.pending if sid in live]
        self.in_submap &= live

    def select(self, tracker: SegmentTracker, path_m: float, force: bool = False) -> list[TrackedSegment] | None:
        """The segments of the next submap if it triggers at odometry path length `path_m`
        (`force`: any new id is enough)."""
        travelled = path_m - (self.last_path_m or 0.0)
        trigger_m = self.cfg.submap_trigger_path_m if self.spacing is None else self.spacing.trigger_path_m
        by_path = trigger_m is not None and travelled >= trigger_m
        needed = 1 if force or by_path else self.cfg.submap_trigger_new_segments
        if not self.pending or len(self.pending) < needed:
            return None
        chosen = [tracker.segments[sid] for sid in self.pending]
        taken = set(self.pending)
        others = sorted((s for s in tracker.segments.values() if s.status != SegmentStatus.NURSERY and s.id not in taken),
                        key=lambda s: (-s.last_seen, s.id))
        chosen += others[: max(0, self.cfg.submap_max_segments - len(chosen))]
        return chosen

    def gate(self, time: float, path_m: float) -> bool:
        """True if a submap at (time, path length) may be made. False skips it and clears the new
        list; with `use_spacing` it is only postponed (the new list stays, so the next frames
        try again), which spaces submap centres by the configured travel."""
        c, sp = self.cfg, self.spacing
        min_interval_s, min_path_m = (c.submap_min_interval_s, c.submap_min_path_m) if sp is None else (
            sp.min_interval_s, sp.min_path_m)
        ok = self.last_time is None or (time - self.last_time >= min_interval_s and path_m - self.last_path_m >= min_path_m)
        if not ok and sp is None:
            self.pending.clear()
        return ok

    def commit(self, segments: list[TrackedSegment], time: float, path_m: float) -> None:
        self.in_submap.update(s.id for s in segments)
        self.pending.clear()
        self.last_time, self.last_path_m = time, path_m

    def prune(self, tracker: SegmentTracker) -> None:
        """Delete retired segments that no future submap can select: already in a submap and
        not among the `submap_max_segments` most recently seen."""
        ranked = sorted((s.last_seen for s in tracker.segments.values() if s.status != SegmentStatus.NURSERY),
                        reverse=True)
        if len(ranked) <= self.cfg.submap_max_segments:
            return
        cutoff = ranked[self.cfg.submap_max_segments - 1]
        for seg in list(tracker.segments.values()):
            if seg.status == SegmentStatus.RETIRED and seg.id in self.in_submap and seg.last_seen < cutoff:
                del tracker.segments[seg.id]
                self.known.discard(seg.id)
                self.in_submap.discard(seg.id)


@dataclass(frozen=True)
class SubmapGeometry:
    """The flattened segments of one submap (odom x-y), for the artefact test, plots and evaluation."""

    points_xy: np.ndarray  # (N, 2) cleaned flattened points
    point_segment: np.ndarray  # (N,) index into segment_ids
    occluded_xy: np.ndarray  # (Q, 2)
    occluded_segment: np.ndarray  # (Q,)
    segment_ids: np.ndarray  # (S,) tracked segment ids


def _shares_cell(xy: np.ndarray, groups: np.ndarray, others_xy: np.ndarray, others_groups: np.ndarray,
                 grid_m: float) -> np.ndarray:
    """(N,) whether each point of `xy` shares its `grid_m` x-y cell with a point of `others_xy` of
    the same group (groups < 2^20: a 2D key's z field holds the group, keeping groups apart)."""
    largest = max(groups.max(initial=0), others_groups.max(initial=0))
    if largest >= VOXEL_INDEX_LIMIT:
        raise ValueError(f"at most {VOXEL_INDEX_LIMIT} groups, got group {largest}")
    cells = voxel_hash(xy, grid_m) + groups
    unique = np.unique(cells)
    other = voxel_hash(others_xy, grid_m) + others_groups
    pos = np.minimum(np.searchsorted(unique, other), len(unique) - 1)
    taken = np.zeros(len(unique), dtype=bool)
    taken[pos[unique[pos] == other]] = True
    return taken[np.searchsorted(unique, cells)]


def _convex_hull_area(points: np.ndarray) -> float:
    corners = convex_hull(points)
    return abs(signed_area(points[corners])) if len(corners) >= 3 else 0.0  # 0 when collinear


def submap_primitives(
    segments: list[TrackedSegment],
    centre_xyz: np.ndarray,
    cfg: GroundMapConfig,
    primitives: PrimitiveConfig,
    occluded_voxel_m: float,
) -> tuple[PrimitiveSet, SubmapGeometry]:
    """Primitives (odom x-y) of the segments cropped around `centre_xyz`, with their 2D geometry."""
    radius = cfg.submap_radius_m
    pts_l, grp_l, ring_l, rgrp_l, occ_l, ogrp_l = [], [], [], [], [], []
    height = np.zeros(len(segments))
    # a segment whose box lies beyond the radius has no point inside; one whose box lies within
    # the inner ring has all points inside and none in the ring (no per-point distances needed)
    lo = np.stack([s.lo for s in segments]) - centre_xyz if segments else np.zeros((0, 3))
    hi = np.stack([s.hi for s in segments]) - centre_xyz if segments else np.zeros((0, 3))
    box_near = np.linalg.norm(np.maximum(0.0, np.maximum(lo, -hi)), axis=1)
    box_far = np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi)), axis=1)
    for g, seg in enumerate(segments):
        if box_near[g] > radius + _BOX_SLACK_M or len(seg.points) == 0:
            continue
        if box_far[g] < radius - cfg.occluded_ring_m - _BOX_SLACK_M:
            pts = seg.points
        else:
            d = np.linalg.norm(seg.points - centre_xyz, axis=1)
            inside = d <= radius
            if not inside.any():
                continue
            pts = seg.points[inside]
            ring_l.append(pts[d[inside] > radius - cfg.occluded_ring_m, :2])
            rgrp_l.append(np.full(len(ring_l[-1]), g))
        low, high = np.percentile(pts[:, 2], [5, 95])
        height[g] = high - low
        pts_l.append(pts[:, :2])
        grp_l.append(np.full(len(pts), g))
        occ_l.append(seg.occluded_keys)
        ogrp_l.append(np.full(len(seg.occluded_keys), g))
    descriptor_dim = int(segments[0].descriptor_sum.shape[0]) if segments else 1
    if not pts_l:
        empty = SubmapGeometry(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64),
                               np.zeros(0, np.int64))
        return PrimitiveSet.empty(descriptor_dim), empty
    pts, grp = np.concatenate(pts_l), np.concatenate(grp_l)
    # occluded points within the radius, cleared where a real point of their segment shares the
    # x-y cell; the real points of the outer ring join them (after each segment's occluded ones)
    occ, ogrp = voxel_unhash(np.concatenate(occ_l), occluded_voxel_m), np.concatenate(ogrp_l)
    within = np.linalg.norm(occ - centre_xyz, axis=1) <= radius
    occ, ogrp = occ[within, :2], ogrp[within]
    if len(occ):
        clear = ~_shares_cell(occ, ogrp, pts, grp, cfg.occluded_grid_m)
        occ, ogrp = occ[clear], ogrp[clear]
    if ring_l:
        occ, ogrp = np.concatenate([occ, *ring_l]), np.concatenate([ogrp, *rgrp_l])
        by_segment = np.argsort(ogrp, kind="stable")
        occ, ogrp = occ[by_segment], ogrp[by_segment]

    # flatten along odom z, then clean every segment in one batch
    clean = cfg.flatten_cleanup
    pts, grp = group_voxel_downsample(pts, grp, clean.voxel_m, dims=2)
    keep = group_outlier_mask(pts, grp, clean.outlier_neighbours, clean.outlier_std_ratio)
    pts, grp = pts[keep], grp[keep]
    keep, _ = group_largest_cluster(pts, grp, clean.dbscan_eps_m, clean.dbscan_min_points)
    pts, grp = pts[keep], grp[keep]
    used, counts = np.unique(grp, return_counts=True)
    used = used[counts >= 2]
    remap = np.full(len(segments), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    pts, grp = pts[remap[grp] >= 0], remap[grp][remap[grp] >= 0]
    occ_ok = remap[ogrp] >= 0
    occ, ogrp = occ[occ_ok], remap[ogrp[occ_ok]]
    bounds = np.searchsorted(grp, np.arange(len(used) + 1))
    per_segment = [pts[bounds[s] : bounds[s + 1]] for s in range(len(used))]
    areas = np.array([_convex_hull_area(p) for p in per_segment])
    ids = np.array([segments[g].id for g in used], dtype=np.int64)
    geometry = SubmapGeometry(pts, grp, occ, ogrp, ids)
    if not len(used):
        return PrimitiveSet.empty(descriptor_dim), geometry
    desc = torch.stack([segments[g].descriptor for g in used]).float()
    prims = segments_to_primitives(per_segment, desc, primitives, areas_m2=areas, border_box=None, segment_ids=ids)

    # FOV / depth-cutoff artefact lines; a fused line's parent is its main contributing segment
    order = np.argsort(ids)
    parent = order[np.searchsorted(ids[order], prims.line_segment_ids.numpy())]
    keep = artifact_line_mask(prims.line_endpoints.double().numpy(), prims.line_kinds.numpy(), parent, geometry, cfg)
    keep_t = torch.from_numpy(keep)
    # flat segments give no points: a compact piece of ground is a view-cut fragment of a region
    point_parent = order[np.searchsorted(ids[order], prims.point_segment_ids.numpy())]
    tall = torch.from_numpy(height[used][point_parent] >= cfg.point_min_height_m)
    prims = PrimitiveSet(
        points_xy=prims.points_xy[tall], point_descriptors=prims.point_descriptors[tall],
        point_segment_ids=prims.point_segment_ids[tall],
        line_endpoints=prims.line_endpoints[keep_t], line_kinds=prims.line_kinds[keep_t],
        line_descriptors=prims.line_descriptors[keep_t], line_segment_ids=prims.line_segment_ids[keep_t],
    )
    return prims, geometry


def artifact_line_mask(
    endpoints: np.ndarray, kinds: np.ndarray, parent: np.ndarray, geometry: SubmapGeometry, cfg: GroundMapConfig
) -> np.ndarray:
    """(L,) True for lines to keep: not FOV / depth-cutoff / crop artefacts of their parent segment.

    endpoints (L, 2, 2), kinds (L,) LineKind, parent (L,) index of each line's segment in
    `geometry`. Only bounded segments are tested (as in the reference).
    """
    n = len(endpoints)
    keep = np.ones(n, dtype=bool)
    test = np.flatnonzero(kinds == int(LineKind.SEGMENT))
    if len(test) == 0:
        return keep
    k = cfg.artifact_line_samples
    t = np.linspace(0.0, 1.0, k)
    samples = endpoints[test, 0, None] + t[None, :, None] * (endpoints[test, 1] - endpoints[test, 0])[:, None]
    samples = samples.reshape(-1, 2)
    owner = np.repeat(parent[test], k)
    dist = cfg.artifact_dist_m

    # each sample against the points of its own segment
    near_real = group_any_point_within(samples, owner, geometry.points_xy, geometry.point_segment, dist)
    near_occluded = group_any_point_within(samples, owner, geometry.occluded_xy, geometry.occluded_segment, dist)
    near_real = near_real.reshape(-1, k).mean(axis=1)
    clear = (~near_occluded).reshape(-1, k).mean(axis=1)
    keep[test] = (near_real >= cfg.artifact_min_near_fraction) & (clear >= cfg.artifact_min_clear_fraction)
    return keep


def thin_by_distance(positions: np.ndarray, min_dist: float) -> np.ndarray:
    """Indices of positions (N, D) kept walking in order, each >= min_dist from the last kept one."""
    kept: list[int] = []
    for i, p in enumerate(positions):
        if not kept or np.linalg.norm(p - positions[kept[-1]]) >= min_dist:
            kept.append(i)
    return np.array(kept, dtype=np.int64)

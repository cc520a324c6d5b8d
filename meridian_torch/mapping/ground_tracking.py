"""Tracking 3D segments over frames: association, life cycle and merging (ROMAN-style, paper III-A).

Association (per frame): observations against the nursery and active segments. A pair is valid
when its voxel overlap IoM >= `min_iom` and its descriptor cosine >= `min_cosine`. IoM is
|A n B| / min(|A|, |B|) over occupied voxels of ONE global lattice floor(p / iom_voxel_m) (the
reference anchors each cloud's grid at its own minimum; a global lattice makes the sets
comparable). Score = geometric mean of both components normalized to [0, 1] over their ranges;
the Hungarian method (scipy) maximizes the total score, every observation also having a "no
association" option worse than any valid pair.

Life cycle: an unmatched observation starts a *nursery* segment; seen `min_sightings` times it
becomes *active*. Unseen for more than `max_unseen_s`: nursery segments are deleted, active ones
get the final cleanup (largest DBSCAN cluster at `cleanup_dbscan_eps_m`) and become *inactive*.
Inactive segments *retire* after `retire_after_s` unseen or when the camera is `retire_distance_m`
from where they were last seen. Retired segments are final; they stay available for submaps.

Merging (after every frame, up to `max_merge_passes` passes): active x (active or inactive) pairs
whose centroids are within half the sum of their largest extents and that pass the association
test are merged into the smaller id. Inactive segments smaller than `min_max_extent_m` are
dropped.

Segment clouds are kept on the `segment_voxel_m` lattice: each voxel keeps the first point that
fell into it (the reference re-voxelizes with a mean; keeping one point lets a segment grow in
O(new points) with sorted int64 voxel keys). Occluded points are voxel keys; an occluded voxel
is cleared when a real point is within `unocclude_dist_m` of its centre.

Speed (the tracker runs on the main thread for every frame): a frame's points are hashed once
per lattice and grouped by observation with one sort; a voxel's point never changes once set,
so an occluded voxel that survived is only tested again against the voxels added since, and new
occluded voxels against the whole cloud; centroid and extent are computed when first read after
the cloud changed, and merging reads them only for the pairs that pass the box, cosine and IoM
tests.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from meridian_torch.config import GroundTrackingConfig
from meridian_torch.mapping.cloud_kernels import merge_sorted_rows, voxels_reached
from meridian_torch.mapping.ground_observations import (
    FrameObservations,
    group_largest_cluster,
    group_unique,
    voxel_hash,
    voxel_unhash,
)

__all__ = ["SegmentStatus", "TrackedSegment", "SegmentTracker", "sorted_overlap", "association_scores"]

_INVALID = 1e9
_NO_ASSOCIATION = 1.0
# hash offsets (x, y, z fields of `voxel_hash`) of the lowest voxel (dz = -1) of the 9 columns
# of the 27 voxels around a voxel; the 27 offsets are symmetric
_COLUMN_OFFSETS = np.array([(dx << 42) + (dy << 21) - 1 for dx in (-1, 0, 1) for dy in (-1, 0, 1)], dtype=np.int64)
# margin of the box test before merging reads centroids and extents (their rounding is far smaller)
_BOX_SLACK_M = 1e-3


class SegmentStatus(IntEnum):
    NURSERY = 0
    ACTIVE = 1
    INACTIVE = 2
    RETIRED = 3


@dataclass
class TrackedSegment:
    """One 3D segment; `keys` (sorted) are the voxel keys of `points` (same order)."""

    id: int
    status: SegmentStatus
    points: np.ndarray  # (N, 3) odom frame
    keys: np.ndarray  # (N,) sorted int64 voxel keys at segment_voxel_m
    iom_keys: np.ndarray  # sorted unique int64 voxel keys at iom_voxel_m
    occluded_keys: np.ndarray  # sorted unique int64 voxel keys at segment_voxel_m
    descriptor_sum: torch.Tensor  # (D,) sum of normalized observation descriptors
    descriptor_count: int
    first_seen: float
    last_seen: float
    sightings: int
    last_camera_xyz: np.ndarray  # (3,)
    lo: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))  # bounding box of `points`
    hi: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))
    _shape: tuple[np.ndarray, float] | None = field(default=None, repr=False)  # (centroid, max_extent) cache

    @property
    def descriptor(self) -> torch.Tensor:
        return torch.nn.functional.normalize(self.descriptor_sum, dim=0)

    @property
    def centroid(self) -> np.ndarray:
        return self._cached_shape()[0]

    @property
    def max_extent(self) -> float:
        """Largest extent of the points along their principal axes."""
        return self._cached_shape()[1]

    def cloud_changed(self) -> None:
        """Forget centroid and extent; whoever changes `points` calls it."""
        self._shape = None

    def _cached_shape(self) -> tuple[np.ndarray, float]:
        if self._shape is None:
            centroid = self.points.mean(axis=0) if len(self.points) else np.zeros(3)
            self._shape = (centroid, _pca_extent(self.points))
        return self._shape

    def occluded_points(self, voxel_m: float) -> np.ndarray:
        return voxel_unhash(self.occluded_keys, voxel_m)


def _in_sorted(values: np.ndarray, sorted_keys: np.ndarray) -> np.ndarray:
    """(N,) whether each of `values` is in the sorted array `sorted_keys`."""
    if len(sorted_keys) == 0:
        return np.zeros(len(values), dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_keys, values), len(sorted_keys) - 1)
    return sorted_keys[pos] == values


def _insert_sorted(sorted_keys: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Sorted union of a sorted array and sorted keys it does not hold."""
    no_rows = np.empty((len(sorted_keys) + len(new), 0))
    return merge_sorted_rows(sorted_keys, no_rows[: len(sorted_keys)], new, no_rows[len(sorted_keys):])[0]


def sorted_overlap(a: np.ndarray, b: np.ndarray) -> int:
    """Number of common elements of two sorted unique int64 arrays."""
    if len(a) > len(b):
        a, b = b, a
    return int(_in_sorted(a, b).sum())


def association_scores(iom: np.ndarray, cosine: np.ndarray, cfg: GroundTrackingConfig) -> np.ndarray:
    """Score in [0, 1] of pairs (geometric mean of normalized IoM and cosine); -1 where invalid."""
    valid = (iom >= cfg.min_iom) & (cosine >= cfg.min_cosine)
    g = np.clip((iom - cfg.min_iom) / (1.0 - cfg.min_iom), 0.0, 1.0)
    s = np.clip((cosine - cfg.min_cosine) / (1.0 - cfg.min_cosine), 0.0, 1.0)
    return np.where(valid, np.sqrt(g * s), -1.0)


def _pca_extent(points: np.ndarray) -> float:
    """Largest extent of the points along their principal axes."""
    if len(points) < 2:
        return 0.0
    centred = points - points.mean(axis=0)
    _, vecs = np.linalg.eigh(centred.T @ centred)
    t = centred @ vecs[:, -1]
    return float(t.max() - t.min())


class SegmentTracker:
    """Segments of one run; `update` consumes the observations of one frame."""

    def __init__(self, cfg: GroundTrackingConfig) -> None:
        self.cfg = cfg
        self.segments: dict[int, TrackedSegment] = {}
        self._next_id = 0

    # ------------------------------------------------------------------ segment geometry

    def _set_points(self, seg: TrackedSegment, keys: np.ndarray, points: np.ndarray, coarse: np.ndarray) -> None:
        """Replace a segment's cloud: sorted unique voxel `keys`, the first point per voxel, and
        the points' keys at iom_voxel_m."""
        seg.points, seg.keys = points, keys
        self._refresh(seg, coarse)

    def _add_points(self, seg: TrackedSegment, keys: np.ndarray, points: np.ndarray,
                    coarse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Add the voxels the segment lacks (arguments as `_set_points`); returns their keys and points."""
        new = ~_in_sorted(keys, seg.keys)
        keys, points = keys[new], points[new]
        if len(keys):
            seg.keys, seg.points = merge_sorted_rows(seg.keys, seg.points, keys, points)
            # incremental: merge the new coarse keys into the sorted set, grow the box
            coarse = np.unique(coarse[new])
            seg.iom_keys = _insert_sorted(seg.iom_keys, coarse[~_in_sorted(coarse, seg.iom_keys)])
            seg.lo, seg.hi = np.minimum(seg.lo, points.min(axis=0)), np.maximum(seg.hi, points.max(axis=0))
            seg.cloud_changed()
        return keys, points

    def _refresh(self, seg: TrackedSegment, coarse: np.ndarray | None = None) -> None:
        """Recompute the derived fields after the cloud was replaced (`coarse`: its IoM keys, if known)."""
        seg.iom_keys = np.unique(voxel_hash(seg.points, self.cfg.iom_voxel_m) if coarse is None else coarse)
        empty = len(seg.points) == 0
        seg.lo = np.full(3, np.inf) if empty else seg.points.min(axis=0)
        seg.hi = np.full(3, -np.inf) if empty else seg.points.max(axis=0)
        seg.cloud_changed()

    def _reached(self, occluded_keys: np.ndarray, keys: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(Q,) whether a point of a cloud (sorted unique `keys`, their `points`) lies within
        unocclude_dist_m of each occluded voxel's centre (`voxels_reached`: only points in the 27
        voxels around can)."""
        centres = voxel_unhash(occluded_keys, self.cfg.segment_voxel_m)
        return voxels_reached(occluded_keys, centres, keys, points, _COLUMN_OFFSETS, self.cfg.unocclude_dist_m)

    def _grow(self, seg: TrackedSegment, keys: np.ndarray, points: np.ndarray, coarse: np.ndarray,
              occluded_keys: np.ndarray) -> None:
        """Add a cloud (arguments as `_set_points`) and occluded voxel keys (sorted unique), then
        clear the occluded voxels a real point reaches. A voxel's point never changes, so the
        occluded voxels kept so far are tested against the added voxels only."""
        old = seg.occluded_keys
        fresh = occluded_keys[~_in_sorted(occluded_keys, old)]
        keys, points = self._add_points(seg, keys, points, coarse)
        old = old[~self._reached(old, keys, points)]
        fresh = fresh[~self._reached(fresh, seg.keys, seg.points)]
        seg.occluded_keys = _insert_sorted(old, fresh)

    def final_cleanup(self, seg: TrackedSegment) -> None:
        """Keep the largest DBSCAN cluster (all points if there is none)."""
        if len(seg.points) == 0:
            return
        keep, has = group_largest_cluster(
            seg.points, np.zeros(len(seg.points), np.int64), self.cfg.cleanup_dbscan_eps_m,
            self.cfg.cleanup_dbscan_min_points,
        )
        if has[0] and not keep.all():
            seg.points, seg.keys = seg.points[keep], seg.keys[keep]
            self._refresh(seg)

    # ------------------------------------------------------------------------ per frame

    def by_status(self, *status: SegmentStatus) -> list[TrackedSegment]:
        return [s for s in self.segments.values() if s.status in status]

    def update(self, obs: FrameObservations) -> None:
        """Associate one frame's observations, then run the life cycle and merging."""
        cfg = self.cfg
        t = obs.time
        camera_xyz = obs.T_odom_camera[:3, 3]
        candidates = self.by_status(SegmentStatus.NURSERY, SegmentStatus.ACTIVE)
        k = len(obs)
        # the frame's points hashed once per lattice; per observation: its voxels (first point
        # each), its IoM keys and its occluded voxels
        coarse = voxel_hash(obs.points, cfg.iom_voxel_m)
        keys, key_obs, first = group_unique(voxel_hash(obs.points, cfg.segment_voxel_m), obs.point_obs)
        iom_keys, iom_obs, _ = group_unique(coarse, obs.point_obs)
        occ_keys, occ_obs, _ = group_unique(voxel_hash(obs.occluded, cfg.segment_voxel_m), obs.occluded_obs)
        key_bounds = np.searchsorted(key_obs, np.arange(k + 1))
        occ_bounds = np.searchsorted(occ_obs, np.arange(k + 1))
        descriptors = torch.nn.functional.normalize(obs.descriptors.detach().to("cpu", torch.float64), dim=1)

        match = np.full(k, -1, dtype=np.int64)
        if k and candidates:
            score = self._scores(obs, iom_keys, iom_obs, descriptors, candidates)
            cost = np.where(score >= 0, -score, _INVALID)
            pad = np.full((k, k), _INVALID)
            np.fill_diagonal(pad, _NO_ASSOCIATION)
            rows, cols = linear_sum_assignment(np.concatenate([cost, pad], axis=1))
            ok = (cols < len(candidates)) & (cost[rows, np.minimum(cols, len(candidates) - 1)] < _NO_ASSOCIATION)
            match[rows[ok]] = cols[ok]

        for i in range(k):
            at = first[key_bounds[i] : key_bounds[i + 1]]
            cloud = (keys[key_bounds[i] : key_bounds[i + 1]], obs.points[at], coarse[at])
            occluded = occ_keys[occ_bounds[i] : occ_bounds[i + 1]]
            if match[i] >= 0:
                seg = candidates[match[i]]
                self._grow(seg, *cloud, occluded)
                seg.descriptor_sum = seg.descriptor_sum + descriptors[i]
                seg.descriptor_count += 1
                seg.last_seen = t
                seg.sightings += 1
                seg.last_camera_xyz = camera_xyz.copy()
                if seg.status == SegmentStatus.NURSERY and seg.sightings >= cfg.min_sightings:
                    seg.status = SegmentStatus.ACTIVE
            else:
                self._create(cloud, occluded, descriptors[i], t, camera_xyz)

        self._life_cycle(t, camera_xyz)
        self._merge()

    def _create(self, cloud: tuple[np.ndarray, np.ndarray, np.ndarray], occluded_keys: np.ndarray,
                descriptor: torch.Tensor, t: float, camera_xyz: np.ndarray) -> TrackedSegment:
        status = SegmentStatus.ACTIVE if self.cfg.min_sightings <= 1 else SegmentStatus.NURSERY
        seg = TrackedSegment(
            id=self._next_id, status=status, points=np.zeros((0, 3)), keys=np.zeros(0, np.int64),
            iom_keys=np.zeros(0, np.int64), occluded_keys=occluded_keys, descriptor_sum=descriptor.clone(),
            descriptor_count=1, first_seen=t, last_seen=t, sightings=1, last_camera_xyz=camera_xyz.copy(),
        )
        self._next_id += 1
        self._set_points(seg, *cloud)
        seg.occluded_keys = occluded_keys[~self._reached(occluded_keys, seg.keys, seg.points)]
        self.segments[seg.id] = seg
        return seg

    def _scores(self, obs: FrameObservations, iom_keys: np.ndarray, iom_obs: np.ndarray, descriptors: torch.Tensor,
                candidates: list[TrackedSegment]) -> np.ndarray:
        """(K, C) association scores of observations (their IoM keys: `group_unique` by
        observation) against candidate segments (-1 = invalid)."""
        cfg = self.cfg
        k = len(descriptors)
        cand_desc = torch.stack([c.descriptor for c in candidates])
        cosine = (descriptors @ cand_desc.T).numpy()
        # overlap is only possible where bounding boxes (grown by a voxel) intersect
        starts = np.searchsorted(obs.point_obs, np.arange(k))
        obs_lo = np.minimum.reduceat(obs.points, starts) - cfg.iom_voxel_m
        obs_hi = np.maximum.reduceat(obs.points, starts) + cfg.iom_voxel_m
        cand_lo = np.stack([c.lo for c in candidates])
        cand_hi = np.stack([c.hi for c in candidates])
        touch = ((obs_lo[:, None] <= cand_hi[None]) & (obs_hi[:, None] >= cand_lo[None])).all(axis=2)
        touch &= cosine >= cfg.min_cosine
        # common IoM voxels: one search of all observations' keys per touched candidate
        inter = np.zeros(cosine.shape, dtype=np.int64)
        for j in np.flatnonzero(touch.any(axis=0)):
            inter[:, j] = np.bincount(iom_obs[_in_sorted(iom_keys, candidates[j].iom_keys)], minlength=k)
        obs_size = np.bincount(iom_obs, minlength=k)
        cand_size = np.array([len(c.iom_keys) for c in candidates])
        iom = np.where(touch, inter / np.maximum(1, np.minimum(obs_size[:, None], cand_size[None])), 0.0)
        return association_scores(iom, cosine, cfg)

    def _life_cycle(self, t: float, camera_xyz: np.ndarray) -> None:
        cfg = self.cfg
        for seg in list(self.segments.values()):
            unseen = t - seg.last_seen
            if seg.status == SegmentStatus.NURSERY and unseen > cfg.max_unseen_s:
                del self.segments[seg.id]
            elif seg.status == SegmentStatus.ACTIVE and unseen > cfg.max_unseen_s:
                self.final_cleanup(seg)
                seg.status = SegmentStatus.INACTIVE
            if seg.status == SegmentStatus.INACTIVE and (
                unseen > cfg.retire_after_s or np.linalg.norm(camera_xyz - seg.last_camera_xyz) > cfg.retire_distance_m
            ):
                seg.status = SegmentStatus.RETIRED

    def _merge(self) -> None:
        cfg = self.cfg
        for seg in self.by_status(SegmentStatus.INACTIVE, SegmentStatus.ACTIVE):
            if len(seg.points) == 0 or (seg.status == SegmentStatus.INACTIVE and seg.max_extent < cfg.min_max_extent_m):
                del self.segments[seg.id]
        for _ in range(cfg.max_merge_passes):
            active = self.by_status(SegmentStatus.ACTIVE)
            pool = active + self.by_status(SegmentStatus.INACTIVE)
            if not active or len(pool) < 2:
                return
            na = len(active)
            desc = torch.stack([s.descriptor for s in pool])
            cosine = (desc[:na] @ desc.T).numpy()
            # candidate pairs: i < j, i active, cosine and IoM pass the association test, centroids
            # within half the sum of the extents. A centroid lies in its box and an extent is at most
            # the box diagonal, so far boxes are dropped first; centroids and extents (a pass over
            # the cloud) are read last, for the few pairs left
            lo, hi = np.stack([s.lo for s in pool]), np.stack([s.hi for s in pool])
            box_gap = np.linalg.norm(np.maximum(0.0, np.maximum(lo[:na, None] - hi[None], lo[None] - hi[:na, None])), axis=2)
            diagonal = np.linalg.norm(hi - lo, axis=1)
            maybe = box_gap <= 0.5 * (diagonal[:na, None] + diagonal[None]) + _BOX_SLACK_M
            maybe &= np.arange(na)[:, None] < np.arange(len(pool))[None]
            maybe &= cosine >= cfg.min_cosine
            rows, cols = np.nonzero(maybe)
            iom = np.array([sorted_overlap(pool[i].iom_keys, pool[j].iom_keys)
                            / max(1, min(len(pool[i].iom_keys), len(pool[j].iom_keys))) for i, j in zip(rows, cols)])
            valid = association_scores(iom, cosine[rows, cols], cfg) >= 0
            rows, cols = rows[valid], cols[valid]
            if not len(rows):
                return
            centroid = np.stack([pool[i].centroid for i in rows]), np.stack([pool[j].centroid for j in cols])
            extent = np.array([pool[i].max_extent for i in rows]), np.array([pool[j].max_extent for j in cols])
            near = np.linalg.norm(centroid[0] - centroid[1], axis=1) <= 0.5 * (extent[0] + extent[1])
            merged_any, used = False, set()
            for i, j in zip(rows[near], cols[near]):
                a, b = pool[i], pool[j]
                if a.id in used or b.id in used:
                    continue
                self._merge_pair(a, b)
                used.update((a.id, b.id))
                merged_any = True
            if not merged_any:
                return

    def _merge_pair(self, a: TrackedSegment, b: TrackedSegment) -> None:
        keep, gone = (a, b) if a.id < b.id else (b, a)
        keep.status = SegmentStatus.ACTIVE  # a merge pair always holds an active segment
        self._grow(keep, gone.keys, gone.points, voxel_hash(gone.points, self.cfg.iom_voxel_m), gone.occluded_keys)
        keep.descriptor_sum = keep.descriptor_sum + gone.descriptor_sum
        keep.descriptor_count += gone.descriptor_count
        keep.first_seen = min(keep.first_seen, gone.first_seen)
        if gone.last_seen > keep.last_seen:
            keep.last_seen, keep.last_camera_xyz = gone.last_seen, gone.last_camera_xyz
        keep.sightings += gone.sightings
        del self.segments[gone.id]

    def finish(self) -> None:
        """End of run: final cleanup of the nursery and active segments, which become inactive."""
        for seg in self.by_status(SegmentStatus.NURSERY, SegmentStatus.ACTIVE):
            self.final_cleanup(seg)
            seg.status = SegmentStatus.INACTIVE

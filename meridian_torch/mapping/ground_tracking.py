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
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from meridian_torch.config import GroundTrackingConfig
from meridian_torch.mapping.ground_observations import (
    FrameObservations,
    group_largest_cluster,
    voxel_hash,
    voxel_unhash,
)

__all__ = ["SegmentStatus", "TrackedSegment", "SegmentTracker", "sorted_overlap", "association_scores"]

_INVALID = 1e9
_NO_ASSOCIATION = 1.0
# hash offsets of the 27 voxels around a voxel (x, y, z fields of `voxel_hash`)
_NEIGHBOUR_OFFSETS = np.array(
    [(dx << 42) + (dy << 21) + dz for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)], dtype=np.int64
)


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
    centroid: np.ndarray = field(default_factory=lambda: np.zeros(3))
    max_extent: float = 0.0
    lo: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))  # bounding box of `points`
    hi: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))

    @property
    def descriptor(self) -> torch.Tensor:
        return torch.nn.functional.normalize(self.descriptor_sum, dim=0)

    def occluded_points(self, voxel_m: float) -> np.ndarray:
        return voxel_unhash(self.occluded_keys, voxel_m)


def sorted_overlap(a: np.ndarray, b: np.ndarray) -> int:
    """Number of common elements of two sorted unique int64 arrays."""
    if len(a) > len(b):
        a, b = b, a
    if len(a) == 0:
        return 0
    pos = np.searchsorted(b, a)
    pos[pos == len(b)] = 0
    return int((b[pos] == a).sum())


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

    def _set_points(self, seg: TrackedSegment, points: np.ndarray) -> None:
        """Replace a segment's cloud (voxelized on the segment lattice, first point per voxel)."""
        keys = voxel_hash(points, self.cfg.segment_voxel_m)
        keys, first = np.unique(keys, return_index=True)
        seg.points, seg.keys = points[first], keys
        self._refresh(seg)

    def _add_points(self, seg: TrackedSegment, points: np.ndarray) -> None:
        keys = voxel_hash(points, self.cfg.segment_voxel_m)
        keys, first = np.unique(keys, return_index=True)
        pos = np.searchsorted(seg.keys, keys)
        new = (pos == len(seg.keys)) | (seg.keys[np.minimum(pos, len(seg.keys) - 1)] != keys)
        if new.any():
            added = points[first[new]]
            seg.keys = np.insert(seg.keys, pos[new], keys[new])
            seg.points = np.insert(seg.points, pos[new], added, axis=0)
            # incremental: merge the new coarse keys into the sorted set, grow the box
            coarse = np.unique(voxel_hash(added, self.cfg.iom_voxel_m))
            at = np.searchsorted(seg.iom_keys, coarse)
            fresh = (at == len(seg.iom_keys)) | (seg.iom_keys[np.minimum(at, len(seg.iom_keys) - 1)] != coarse)
            seg.iom_keys = np.insert(seg.iom_keys, at[fresh], coarse[fresh])
            seg.lo, seg.hi = np.minimum(seg.lo, added.min(axis=0)), np.maximum(seg.hi, added.max(axis=0))
            self._shape(seg)

    def _refresh(self, seg: TrackedSegment) -> None:
        """Recompute the derived fields after the cloud was replaced."""
        seg.iom_keys = np.unique(voxel_hash(seg.points, self.cfg.iom_voxel_m))
        empty = len(seg.points) == 0
        seg.lo = np.full(3, np.inf) if empty else seg.points.min(axis=0)
        seg.hi = np.full(3, -np.inf) if empty else seg.points.max(axis=0)
        self._shape(seg)

    @staticmethod
    def _shape(seg: TrackedSegment) -> None:
        seg.centroid = seg.points.mean(axis=0) if len(seg.points) else np.zeros(3)
        seg.max_extent = _pca_extent(seg.points)

    def _unocclude(self, seg: TrackedSegment) -> None:
        """Clear occluded voxels whose centre has a real point within unocclude_dist_m."""
        if len(seg.occluded_keys) == 0 or len(seg.keys) == 0:
            return
        voxel = self.cfg.segment_voxel_m
        near = (seg.occluded_keys[:, None] + _NEIGHBOUR_OFFSETS[None]).ravel()
        pos = np.minimum(np.searchsorted(seg.keys, near), len(seg.keys) - 1)
        hit = seg.keys[pos] == near
        owner = np.repeat(np.arange(len(seg.occluded_keys)), len(_NEIGHBOUR_OFFSETS))[hit]
        centres = voxel_unhash(seg.occluded_keys, voxel)
        d = np.linalg.norm(seg.points[pos[hit]] - centres[owner], axis=1)
        cleared = np.zeros(len(seg.occluded_keys), dtype=bool)
        cleared[owner[d <= self.cfg.unocclude_dist_m]] = True
        seg.occluded_keys = seg.occluded_keys[~cleared]

    def _add_occluded(self, seg: TrackedSegment, occluded: np.ndarray) -> None:
        if len(occluded):
            keys = voxel_hash(occluded, self.cfg.segment_voxel_m)
            seg.occluded_keys = np.union1d(seg.occluded_keys, keys)

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
        bounds = np.searchsorted(obs.point_obs, np.arange(k + 1))
        obs_points = [obs.points[bounds[i] : bounds[i + 1]] for i in range(k)]
        occ_bounds = np.searchsorted(obs.occluded_obs, np.arange(k + 1))
        obs_occluded = [obs.occluded[occ_bounds[i] : occ_bounds[i + 1]] for i in range(k)]
        descriptors = torch.nn.functional.normalize(obs.descriptors.detach().to("cpu", torch.float64), dim=1)

        match = np.full(k, -1, dtype=np.int64)
        if k and candidates:
            score = self._scores(obs_points, descriptors, candidates)
            cost = np.where(score >= 0, -score, _INVALID)
            pad = np.full((k, k), _INVALID)
            np.fill_diagonal(pad, _NO_ASSOCIATION)
            rows, cols = linear_sum_assignment(np.concatenate([cost, pad], axis=1))
            ok = (cols < len(candidates)) & (cost[rows, np.minimum(cols, len(candidates) - 1)] < _NO_ASSOCIATION)
            match[rows[ok]] = cols[ok]

        for i in range(k):
            if match[i] >= 0:
                seg = candidates[match[i]]
                self._add_occluded(seg, obs_occluded[i])
                self._add_points(seg, obs_points[i])
                self._unocclude(seg)
                seg.descriptor_sum = seg.descriptor_sum + descriptors[i]
                seg.descriptor_count += 1
                seg.last_seen = t
                seg.sightings += 1
                seg.last_camera_xyz = camera_xyz.copy()
                if seg.status == SegmentStatus.NURSERY and seg.sightings >= cfg.min_sightings:
                    seg.status = SegmentStatus.ACTIVE
            else:
                self._create(obs_points[i], obs_occluded[i], descriptors[i], t, camera_xyz)

        self._life_cycle(t, camera_xyz)
        self._merge()

    def _create(self, points: np.ndarray, occluded: np.ndarray, descriptor: torch.Tensor, t: float,
                camera_xyz: np.ndarray) -> TrackedSegment:
        status = SegmentStatus.ACTIVE if self.cfg.min_sightings <= 1 else SegmentStatus.NURSERY
        seg = TrackedSegment(
            id=self._next_id, status=status, points=np.zeros((0, 3)), keys=np.zeros(0, np.int64),
            iom_keys=np.zeros(0, np.int64), occluded_keys=np.zeros(0, np.int64), descriptor_sum=descriptor.clone(),
            descriptor_count=1, first_seen=t, last_seen=t, sightings=1, last_camera_xyz=camera_xyz.copy(),
        )
        self._next_id += 1
        self._add_occluded(seg, occluded)
        self._set_points(seg, points)
        self._unocclude(seg)
        self.segments[seg.id] = seg
        return seg

    def _scores(self, obs_points: list[np.ndarray], descriptors: torch.Tensor,
                candidates: list[TrackedSegment]) -> np.ndarray:
        """(K, C) association scores of observations against candidate segments (-1 = invalid)."""
        cfg = self.cfg
        cand_desc = torch.stack([c.descriptor for c in candidates])
        cosine = (descriptors @ cand_desc.T).numpy()
        obs_keys = [np.unique(voxel_hash(p, cfg.iom_voxel_m)) for p in obs_points]
        # overlap is only possible where bounding boxes (grown by a voxel) intersect
        obs_lo = np.stack([p.min(axis=0) for p in obs_points]) - cfg.iom_voxel_m
        obs_hi = np.stack([p.max(axis=0) for p in obs_points]) + cfg.iom_voxel_m
        cand_lo = np.stack([c.lo for c in candidates])
        cand_hi = np.stack([c.hi for c in candidates])
        touch = ((obs_lo[:, None] <= cand_hi[None]) & (obs_hi[:, None] >= cand_lo[None])).all(axis=2)
        touch &= cosine >= cfg.min_cosine
        iom = np.zeros(cosine.shape)
        for i, j in zip(*np.nonzero(touch)):
            inter = sorted_overlap(obs_keys[i], candidates[j].iom_keys)
            iom[i, j] = inter / max(1, min(len(obs_keys[i]), len(candidates[j].iom_keys)))
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
            centroid = np.stack([s.centroid for s in pool])
            extent = np.array([s.max_extent for s in pool])
            near = np.linalg.norm(centroid[: len(active), None] - centroid[None], axis=2) <= 0.5 * (
                extent[: len(active), None] + extent[None]
            )
            near &= np.arange(len(active))[:, None] < np.arange(len(pool))[None]  # pairs i < j, i active
            if not near.any():
                return
            desc = torch.stack([s.descriptor for s in pool])
            cosine = (desc[: len(active)] @ desc.T).numpy()
            near &= cosine >= cfg.min_cosine
            merged_any, used = False, set()
            for i, j in zip(*np.nonzero(near)):
                a, b = pool[i], pool[j]
                if a.id in used or b.id in used:
                    continue
                inter = sorted_overlap(a.iom_keys, b.iom_keys)
                iom = inter / max(1, min(len(a.iom_keys), len(b.iom_keys)))
                if association_scores(np.array(iom), cosine[i, j], cfg) >= 0:
                    self._merge_pair(a, b)
                    used.update((a.id, b.id))
                    merged_any = True
            if not merged_any:
                return

    def _merge_pair(self, a: TrackedSegment, b: TrackedSegment) -> None:
        keep, gone = (a, b) if a.id < b.id else (b, a)
        keep.status = SegmentStatus.ACTIVE  # a merge pair always holds an active segment
        keep.occluded_keys = np.union1d(keep.occluded_keys, gone.occluded_keys)
        self._add_points(keep, gone.points)
        self._unocclude(keep)
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

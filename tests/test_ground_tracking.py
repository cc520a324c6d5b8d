"""3D segment tracking: association, life cycle and merging on synthetic observations."""

from __future__ import annotations

import numpy as np
import torch

from meridian_torch.config import GroundTrackingConfig
from meridian_torch.mapping.ground_observations import (
    FrameObservations,
    group_unique,
    voxel_hash,
    voxel_unhash,
)
from meridian_torch.mapping.ground_tracking import (
    SegmentStatus,
    SegmentTracker,
    TrackedSegment,
    association_scores,
    sorted_overlap,
)


def _box_surface(centre, size, step=0.05):
    """Points on the surface of an axis-aligned box."""
    c, s = np.asarray(centre, float), np.asarray(size, float)
    g = [np.arange(-s[k] / 2, s[k] / 2 + 1e-9, step) for k in range(3)]
    pts = []
    for axis in range(3):
        a, b = [k for k in range(3) if k != axis]
        u, v = np.meshgrid(g[a], g[b], indexing="ij")
        for side in (-1, 1):
            p = np.zeros((u.size, 3))
            p[:, a], p[:, b], p[:, axis] = u.ravel(), v.ravel(), side * s[axis] / 2
            pts.append(p)
    return np.concatenate(pts) + c


def _frame(t, camera_xyz, clouds, descriptors, occluded=None):
    pts = np.concatenate(clouds)
    obs = np.concatenate([np.full(len(c), i) for i, c in enumerate(clouds)])
    occ = np.zeros((0, 3)) if occluded is None else occluded[0]
    occ_obs = np.zeros(0, np.int64) if occluded is None else occluded[1]
    T = np.eye(4)
    T[:3, 3] = camera_xyz
    return FrameObservations(float(t), T, pts, obs, occ, occ_obs, torch.stack(descriptors).double(),
                             np.arange(len(clouds)))


def _desc(*v):
    return torch.nn.functional.normalize(torch.tensor(v, dtype=torch.float64), dim=0)


def test_sorted_overlap_matches_set_intersection():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = np.unique(rng.integers(0, 50, 30))
        b = np.unique(rng.integers(0, 50, rng.integers(0, 40)))
        assert sorted_overlap(a, b) == len(set(a) & set(b))


def test_association_scores_gate_and_order():
    cfg = GroundTrackingConfig()
    s = association_scores(np.array([0.1, 0.5, 0.9, 0.9]), np.array([0.99, 0.9, 0.9, 0.7]), cfg)
    assert s[0] < 0 and s[3] < 0 and 0 <= s[1] < s[2] <= 1


def test_static_object_seen_from_many_poses_is_one_segment():
    rng = np.random.default_rng(1)
    box = _box_surface([5.0, 2.0, 0.75], [2.0, 1.0, 1.5])
    tracker = SegmentTracker(GroundTrackingConfig())
    desc = _desc(1.0, 0.2, 0.1, 0.0)
    for k in range(12):
        cam = np.array([k * 0.8, 0.0, 1.2])
        # each frame sees the faces turned to the camera, subsampled and with noise
        visible = box[(box - box.mean(0)) @ (cam - box.mean(0)) > -0.3]
        view = visible[rng.random(len(visible)) < 0.5] + rng.normal(0, 0.01, (1, 3))
        noisy = torch.nn.functional.normalize(desc + 0.03 * torch.randn(4, dtype=torch.float64), dim=0)
        tracker.update(_frame(0.5 * k, cam, [view], [noisy]))
    segs = list(tracker.segments.values())
    assert len(segs) == 1
    assert segs[0].status == SegmentStatus.ACTIVE and segs[0].sightings == 12
    # the union of all views, on the 0.1 m lattice
    assert len(segs[0].points) == len(np.unique(segs[0].keys))
    assert np.abs(segs[0].centroid - [5.0, 2.0, 0.75]).max() < 0.3
    # the incrementally kept coarse keys and box equal a recomputation
    assert np.array_equal(segs[0].iom_keys, np.unique(voxel_hash(segs[0].points, 0.25)))
    assert np.array_equal(segs[0].lo, segs[0].points.min(0)) and np.array_equal(segs[0].hi, segs[0].points.max(0))


def test_two_distinct_objects_never_merge():
    rng = np.random.default_rng(2)
    a = _box_surface([4.0, 0.0, 0.5], [1.0, 1.0, 1.0])
    b_near = _box_surface([5.6, 0.0, 0.5], [1.0, 1.0, 1.0])  # 0.6 m gap, same look
    c_overlap = _box_surface([4.2, 0.2, 0.6], [1.0, 1.0, 1.0])  # overlaps a, other look
    d_a, d_c = _desc(1.0, 0.0, 0.0, 0.0), _desc(0.0, 1.0, 0.3, 0.0)
    tracker = SegmentTracker(GroundTrackingConfig())
    for k in range(10):
        cam = np.array([0.3 * k, -4.0, 1.2])
        views = [p[rng.random(len(p)) < 0.6] for p in (a, b_near, c_overlap)]
        tracker.update(_frame(0.5 * k, cam, views, [d_a, d_a, d_c]))
    segs = sorted(tracker.segments.values(), key=lambda s: s.id)
    assert len(segs) == 3
    assert [s.sightings for s in segs] == [10, 10, 10]


def test_life_cycle_nursery_active_inactive_retired():
    cfg = GroundTrackingConfig()
    tracker = SegmentTracker(cfg)
    box = _box_surface([2.0, 0.0, 0.5], [1.0, 1.0, 1.0])
    d = _desc(1.0, 0.0, 0.0, 0.0)
    other = _box_surface([30.0, 0.0, 0.5], [1.0, 1.0, 1.0])
    tracker.update(_frame(0.0, [0, 0, 1], [box, other], [d, d]))
    assert {s.status for s in tracker.segments.values()} == {SegmentStatus.NURSERY}
    tracker.update(_frame(0.3, [0, 0, 1], [box], [d]))  # `other` unseen 0.3 s: still nursery
    statuses = {s.id: s.status for s in tracker.segments.values()}
    assert statuses == {0: SegmentStatus.ACTIVE, 1: SegmentStatus.NURSERY}
    tracker.update(_frame(0.6, [0, 0, 1], [box], [d]))  # `other` unseen 0.6 s > 0.4 s: deleted
    assert set(tracker.segments) == {0}
    tracker.update(_frame(1.2, [1, 0, 1], [other], [d]))  # box unseen 0.6 s: inactive
    assert tracker.segments[0].status == SegmentStatus.INACTIVE
    tracker.update(_frame(1.5, [12, 0, 1], [other], [d]))  # camera 11 m from the last sighting
    assert tracker.segments[0].status == SegmentStatus.RETIRED


def test_duplicate_segments_merge_into_smaller_id():
    cfg = GroundTrackingConfig()
    tracker = SegmentTracker(cfg)
    full = _box_surface([3.0, 0.0, 0.5], [2.0, 1.0, 1.0])
    left, right = full[full[:, 0] < 3.2], full[full[:, 0] > 2.6]
    d = _desc(0.0, 0.0, 1.0, 0.0)
    # two observations of one object in one frame cannot both match it: the second starts a
    # new (nursery) segment, which merges into the first once it is active
    tracker.update(_frame(0.0, [0, -3, 1], [left, right], [d, d]))
    assert sorted(tracker.segments) == [0, 1]
    tracker.update(_frame(0.3, [0, -3, 1], [left, right], [d, d]))
    assert sorted(tracker.segments) == [0]  # 1 became active and merged into 0
    seg = tracker.segments[0]
    assert seg.status == SegmentStatus.ACTIVE and seg.sightings == 4
    assert seg.points[:, 0].min() < 2.1 and seg.points[:, 0].max() > 3.9


def test_occluded_voxels_are_cleared_by_later_real_points():
    cfg = GroundTrackingConfig()
    tracker = SegmentTracker(cfg)
    plane = np.stack(np.meshgrid(np.arange(0, 3, 0.05), np.arange(0, 2, 0.05), [0.0]), -1).reshape(-1, 3)
    first = plane[plane[:, 0] < 1.5]
    edge = plane[(plane[:, 0] >= 1.5) & (plane[:, 0] < 1.7)]
    d = _desc(1.0, 1.0, 0.0, 0.0)
    tracker.update(_frame(0.0, [0, 0, 1], [first], [d], (edge, np.zeros(len(edge), np.int64))))
    seg = tracker.segments[0]
    assert len(seg.occluded_keys) > 0
    tracker.update(_frame(0.3, [0, 0, 1], [plane], [d]))
    assert len(tracker.segments[0].occluded_keys) == 0
    assert np.array_equal(np.unique(voxel_hash(plane, 0.1)), tracker.segments[0].keys)


# ----------------------------------------------------------- the fast path against a plain one


class PlainTracker(SegmentTracker):
    """The tracker with its fast steps replaced by plain, obviously correct ones: every occluded
    voxel tested against every point after each change, IoM per pair of sorted key sets, centroid
    and extent of every merge candidate read up front. The fast tracker must give the same
    segments, bitwise."""

    def _reached(self, occluded_keys, keys, points):
        """Each occluded voxel's 27 neighbours looked up in the cloud (`all_pairs_reached` checks
        the neighbourhood against all distances)."""
        reached = np.zeros(len(occluded_keys), dtype=bool)
        centres = voxel_unhash(occluded_keys, self.cfg.segment_voxel_m)
        index = {k: i for i, k in enumerate(keys.tolist())}
        offsets = [(dx << 42) + (dy << 21) + dz for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)]
        for q, key in enumerate(occluded_keys.tolist()):
            near = [index[key + o] for o in offsets if key + o in index]
            if near:
                reached[q] = (np.linalg.norm(points[near] - centres[q], axis=1) <= self.cfg.unocclude_dist_m).any()
        return reached

    def _grow(self, seg, keys, points, coarse, occluded_keys):
        seg.occluded_keys = np.union1d(seg.occluded_keys, occluded_keys)
        self._add_points(seg, keys, points, coarse)
        seg.occluded_keys = seg.occluded_keys[~self._reached(seg.occluded_keys, seg.keys, seg.points)]

    def _scores(self, obs, iom_keys, iom_obs, descriptors, candidates):
        cfg = self.cfg
        cosine = (descriptors @ torch.stack([c.descriptor for c in candidates]).T).numpy()
        iom = np.zeros(cosine.shape)
        for i in range(len(descriptors)):
            own = obs.points[obs.point_obs == i]
            lo, hi = own.min(axis=0) - cfg.iom_voxel_m, own.max(axis=0) + cfg.iom_voxel_m
            keys_i = np.unique(voxel_hash(own, cfg.iom_voxel_m))
            for j, c in enumerate(candidates):
                if np.all(lo <= c.hi) and np.all(hi >= c.lo) and cosine[i, j] >= cfg.min_cosine:
                    iom[i, j] = len(np.intersect1d(keys_i, c.iom_keys)) / max(1, min(len(keys_i), len(c.iom_keys)))
        return association_scores(iom, cosine, cfg)

    def _merge(self):
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
            near &= np.arange(len(active))[:, None] < np.arange(len(pool))[None]
            desc = torch.stack([s.descriptor for s in pool])
            cosine = (desc[: len(active)] @ desc.T).numpy()
            merged_any, used = False, set()
            for i, j in zip(*np.nonzero(near)):
                a, b = pool[i], pool[j]
                if a.id in used or b.id in used:
                    continue
                inter = len(np.intersect1d(a.iom_keys, b.iom_keys))
                iom = inter / max(1, min(len(a.iom_keys), len(b.iom_keys)))
                if association_scores(np.array(iom), cosine[i, j], cfg) >= 0:
                    self._merge_pair(a, b)
                    used.update((a.id, b.id))
                    merged_any = True
            if not merged_any:
                return


def assert_same_segments(fast: dict[int, TrackedSegment], plain: dict[int, TrackedSegment]) -> None:
    assert fast.keys() == plain.keys()
    for sid, a in fast.items():
        b = plain[sid]
        assert (a.status, a.descriptor_count, a.first_seen, a.last_seen, a.sightings) == (
            b.status, b.descriptor_count, b.first_seen, b.last_seen, b.sightings)
        for name in ("points", "keys", "iom_keys", "occluded_keys", "last_camera_xyz", "lo", "hi", "centroid"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"segment {sid} {name}")
        assert a.max_extent == b.max_extent
        assert torch.equal(a.descriptor_sum, b.descriptor_sum)


def _drive(tracker: SegmentTracker, seed: int) -> list[dict[int, TrackedSegment]]:
    """A camera passing boxes and a wall: partial noisy views with occluded edge points, a look
    that drifts, duplicates in one frame (merges), an object left behind (inactive, retired)."""
    rng, gen = np.random.default_rng(seed), torch.Generator().manual_seed(seed)
    objects = [
        (_box_surface([4.0, 2.0, 0.5], [1.2, 0.8, 1.0]), _desc(1.0, 0.1, 0.0, 0.0)),
        (_box_surface([7.0, -2.0, 0.7], [2.0, 1.0, 1.4]), _desc(0.0, 1.0, 0.2, 0.0)),
        (_box_surface([12.0, 2.5, 1.0], [6.0, 0.3, 2.0]), _desc(0.0, 0.0, 1.0, 0.3)),
    ]
    states = []
    for k in range(16):
        cam = np.array([0.7 * k, 0.0, 1.2])
        clouds, descs, occ, occ_obs = [], [], [], []
        for cloud, desc in objects:
            if np.linalg.norm(cloud.mean(0)[:2] - cam[:2]) > 9.0:
                continue
            view = cloud[rng.random(len(cloud)) < 0.4] + rng.normal(0, 0.01, 3)
            parts = [view[view[:, 0] < view[:, 0].mean()], view[view[:, 0] >= view[:, 0].mean()]] if k % 5 == 2 else [view]
            for part in parts:
                edge = part[part[:, 0] > np.quantile(part[:, 0], 0.85)] + [0.05, 0.0, 0.0]
                occ.append(edge[rng.random(len(edge)) < 0.5])
                occ_obs.append(np.full(len(occ[-1]), len(clouds)))
                clouds.append(part)
                descs.append(torch.nn.functional.normalize(desc + 0.02 * torch.randn(4, generator=gen, dtype=torch.float64), dim=0))
        if clouds:
            tracker.update(_frame(0.3 * k, cam, clouds, descs, (np.concatenate(occ), np.concatenate(occ_obs))))
        states.append({sid: TrackedSegment(**{**vars(s), "_shape": None}) for sid, s in tracker.segments.items()})
    tracker.finish()
    states.append(dict(tracker.segments))
    return states


def test_fast_tracker_gives_the_plain_trackers_segments():
    for seed in (0, 1):
        fast = _drive(SegmentTracker(GroundTrackingConfig()), seed)
        plain = _drive(PlainTracker(GroundTrackingConfig()), seed)
        for a, b in zip(fast, plain):
            assert_same_segments(a, b)
        statuses = {s.status for state in fast for s in state.values()}
        assert {SegmentStatus.NURSERY, SegmentStatus.ACTIVE, SegmentStatus.INACTIVE} <= statuses
        assert any(len(s.occluded_keys) for state in fast for s in state.values())


def test_group_unique_equals_unique_per_group():
    rng = np.random.default_rng(3)
    keys = rng.integers(0, 40, 300)
    groups = np.sort(rng.integers(0, 6, 300))
    out_keys, out_groups, first = group_unique(keys, groups)
    for g in range(6):
        expect_keys, expect_first = np.unique(keys[groups == g], return_index=True)
        np.testing.assert_array_equal(out_keys[out_groups == g], expect_keys)
        np.testing.assert_array_equal(first[out_groups == g], np.flatnonzero(groups == g)[expect_first])
    assert [len(a) for a in group_unique(keys[:0], groups[:0])] == [0, 0, 0]


def all_pairs_reached(occluded_keys, points, cfg):
    if len(occluded_keys) == 0 or len(points) == 0:
        return np.zeros(len(occluded_keys), dtype=bool)
    centres = voxel_unhash(occluded_keys, cfg.segment_voxel_m)
    return (np.linalg.norm(points[None] - centres[:, None], axis=2) <= cfg.unocclude_dist_m).any(axis=1)


def test_reached_equals_all_pairs_distances():
    cfg = GroundTrackingConfig()
    fast, plain = SegmentTracker(cfg), PlainTracker(cfg)
    rng = np.random.default_rng(4)
    for n_points, n_occluded in ((2000, 50), (30, 400), (0, 10), (10, 0)):
        points = rng.uniform(-1.0, 1.0, (n_points, 3))
        keys, first = np.unique(voxel_hash(points, cfg.segment_voxel_m), return_index=True)
        occluded = np.unique(voxel_hash(rng.uniform(-1.2, 1.2, (n_occluded, 3)), cfg.segment_voxel_m))
        got = fast._reached(occluded, keys, points[first])
        np.testing.assert_array_equal(got, all_pairs_reached(occluded, points[first], cfg))
        np.testing.assert_array_equal(got, plain._reached(occluded, keys, points[first]))
        assert n_points < 100 or 0 < got.sum() < len(got)

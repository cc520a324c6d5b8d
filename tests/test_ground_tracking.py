"""3D segment tracking: association, life cycle and merging on synthetic observations."""

from __future__ import annotations

import numpy as np
import torch

from meridian_torch.config import GroundTrackingConfig
from meridian_torch.mapping.ground_observations import FrameObservations, voxel_hash
from meridian_torch.mapping.ground_tracking import (
    SegmentStatus,
    SegmentTracker,
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

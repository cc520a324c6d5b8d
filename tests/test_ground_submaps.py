"""Ground submaps: trigger counts and gates, radius crop, FOV / range artefact line removal."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meridian_torch.config import GroundMapConfig, GroundTrackingConfig
from meridian_torch.config.mapping import PrimitiveConfig, SubmapSpacingConfig
from meridian_torch.mapping.ground_observations import voxel_hash
from meridian_torch.mapping.ground_submaps import (
    SubmapGeometry,
    SubmapTrigger,
    _shares_cell,
    artifact_line_mask,
    submap_primitives,
    thin_by_distance,
)
from meridian_torch.mapping.ground_tracking import SegmentStatus, SegmentTracker, TrackedSegment
from meridian_torch.types import LineKind


def _segment(sid, points, occluded=None, status=SegmentStatus.INACTIVE, last_seen=0.0, desc=None):
    occluded = np.zeros((0, 3)) if occluded is None else occluded
    tracker = SegmentTracker(GroundTrackingConfig())
    d = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64) if desc is None else desc
    seg = TrackedSegment(sid, status, np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64),
                         np.unique(voxel_hash(occluded, 0.1)) if len(occluded) else np.zeros(0, np.int64),
                         d, 1, last_seen, last_seen, 2, np.zeros(3))
    points = np.asarray(points, dtype=np.float64)
    keys, first = np.unique(voxel_hash(points, 0.1), return_index=True)
    tracker._set_points(seg, keys, points[first], voxel_hash(points[first], 0.25))
    return seg


class _FakeTracker:
    def __init__(self):
        self.segments = {}

    def add(self, seg):
        self.segments[seg.id] = seg


def _tiny_segment(sid, last_seen=0.0, status=SegmentStatus.INACTIVE):
    return _segment(sid, np.array([[sid * 1.0, 0.0, 0.0], [sid + 0.5, 0.0, 0.0]]), status=status, last_seen=last_seen)


def test_trigger_counts_and_selection():
    cfg = GroundMapConfig(submap_trigger_new_segments=20, submap_max_segments=30, submap_min_path_m=0,
                          submap_min_interval_s=0)
    trigger = SubmapTrigger(cfg)
    tracker = _FakeTracker()
    for sid in range(19):
        tracker.add(_tiny_segment(sid, last_seen=float(sid)))
    tracker.add(_tiny_segment(100, status=SegmentStatus.NURSERY))  # never counted
    trigger.observe(tracker)
    assert len(trigger.pending) == 19 and trigger.select(tracker, 0.0) is None
    tracker.add(_tiny_segment(19, last_seen=19.0))
    trigger.observe(tracker)
    chosen = trigger.select(tracker, 0.0)
    assert [s.id for s in chosen] == list(range(20))
    trigger.commit(chosen, 1.0, 0.0)
    assert trigger.pending == []
    # 20 more: the submap takes all new ones and fills up with the most recently seen others
    for sid in range(20, 40):
        tracker.add(_tiny_segment(sid, last_seen=float(sid)))
    trigger.observe(tracker)
    chosen = trigger.select(tracker, 0.0)
    assert [s.id for s in chosen] == list(range(20, 40)) + list(range(19, 9, -1))
    # a merged-away id leaves the pending list
    del tracker.segments[25]
    trigger.observe(tracker)
    assert 25 not in trigger.pending and len(trigger.pending) == 19


def test_gates_skip_and_clear_and_path_trigger():
    cfg = GroundMapConfig(submap_trigger_new_segments=3, submap_min_path_m=20.0, submap_min_interval_s=5.0,
                          submap_trigger_path_m=50.0)
    trigger = SubmapTrigger(cfg)
    tracker = _FakeTracker()
    for sid in range(3):
        tracker.add(_tiny_segment(sid))
    trigger.observe(tracker)
    assert trigger.gate(10.0, 100.0)
    trigger.commit(trigger.select(tracker, 100.0), 10.0, 100.0)
    for sid in range(3, 6):
        tracker.add(_tiny_segment(sid))
    trigger.observe(tracker)
    assert trigger.select(tracker, 110.0) is not None
    assert not trigger.gate(20.0, 110.0) and trigger.pending == []  # 10 m < 20 m: skipped, cleared
    tracker.add(_tiny_segment(6))
    trigger.observe(tracker)
    assert trigger.select(tracker, 140.0) is None  # one new id, 40 m travelled
    assert [s.id for s in trigger.select(tracker, 150.0)][:1] == [6]  # 50 m: the path trigger
    assert trigger.select(tracker, 150.0, force=True) is not None


def test_spacing_after_fix_replaces_the_gates_and_the_path_trigger():
    cfg = GroundMapConfig(submap_trigger_new_segments=3, submap_min_path_m=20.0, submap_min_interval_s=5.0,
                          submap_trigger_path_m=50.0)
    trigger = SubmapTrigger(cfg)
    tracker = _FakeTracker()
    tracker.add(_tiny_segment(0))
    trigger.observe(tracker)
    trigger.commit(trigger.select(tracker, 100.0, force=True), 10.0, 100.0)
    tracker.add(_tiny_segment(1))
    trigger.observe(tracker)
    assert trigger.select(tracker, 120.0) is None  # one new id after 20 m: not yet (50 m)
    assert not trigger.gate(12.0, 112.0)  # 2 s and 12 m: skipped
    tracker.add(_tiny_segment(2))
    trigger.observe(tracker)
    trigger.use_spacing(SubmapSpacingConfig(trigger_path_m=20.0, min_interval_s=1.0, min_path_m=10.0))
    assert [s.id for s in trigger.select(tracker, 120.0)][:1] == [2]  # 20 m now triggers
    assert trigger.gate(12.0, 112.0)  # 2 s and 12 m now pass
    assert not trigger.gate(10.5, 105.0) and trigger.pending == [2]  # 0.5 s: postponed, the new id stays


def test_prune_keeps_what_can_still_be_selected():
    cfg = GroundMapConfig(submap_max_segments=5)
    trigger = SubmapTrigger(cfg)
    tracker = _FakeTracker()
    for sid in range(10):
        tracker.add(_tiny_segment(sid, last_seen=float(sid), status=SegmentStatus.RETIRED))
    trigger.observe(tracker)
    trigger.commit([tracker.segments[i] for i in range(8)], 0.0, 0.0)
    trigger.prune(tracker)
    # in a submap and older than the 5 most recent: gone; 8, 9 were never in a submap
    assert sorted(tracker.segments) == [5, 6, 7, 8, 9]


def _rectangle(x0, x1, y0, y1, step=0.1):
    # at voxel centres: exactly one point per 0.1 m voxel
    x, y = np.meshgrid(np.arange(x0 + step / 2, x1, step), np.arange(y0 + step / 2, y1, step))
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)


def test_artifact_lines_along_fov_edge_and_max_range_removed_real_border_kept():
    # a ground segment 10 m x 6 m; its left side was at the image edge and its far side at the
    # depth cutoff (occluded points along both), its right and near sides are real borders
    region = _rectangle(0, 10, 0, 6)
    left_edge = _rectangle(-0.3, 0.1, 0, 6, 0.1)
    far_edge = _rectangle(0, 10, 5.9, 6.3, 0.1)
    occluded = np.concatenate([left_edge, far_edge])
    seg = _segment(7, region, occluded)
    prims, geometry = submap_primitives([seg], np.array([5.0, 3.0, 1.0]), GroundMapConfig(), PrimitiveConfig(), 0.1)
    ends = prims.line_endpoints.double().numpy()
    assert len(ends) >= 2 and (prims.line_segment_ids == 7).all()
    mid = ends.mean(axis=1)
    horizontal = np.abs(ends[:, 1, 1] - ends[:, 0, 1]) < np.abs(ends[:, 1, 0] - ends[:, 0, 0])
    # kept: the right side (x ~ 10) and the near side (y ~ 0); removed: x ~ 0 and y ~ 6
    assert np.any(~horizontal & (np.abs(mid[:, 0] - 10) < 0.5))
    assert np.any(horizontal & (np.abs(mid[:, 1]) < 0.5))
    assert not np.any(~horizontal & (np.abs(mid[:, 0]) < 0.5))
    assert not np.any(horizontal & (np.abs(mid[:, 1] - 6) < 0.5))
    assert len(geometry.occluded_xy) > 0


def test_radius_crop_marks_the_outer_ring_occluded():
    region = _rectangle(0, 60, 0, 4)
    seg = _segment(3, region)
    cfg = GroundMapConfig(submap_radius_m=20.0)
    prims, geometry = submap_primitives([seg], np.array([10.0, 2.0, 0.0]), cfg, PrimitiveConfig(), 0.1)
    assert np.linalg.norm(geometry.points_xy - [10.0, 2.0], axis=1).max() <= 20.0 + 1e-9
    ring = np.linalg.norm(geometry.occluded_xy - [10.0, 2.0], axis=1)
    assert len(ring) and ring.min() > 19.5 - 1e-9
    # the long sides stay, the cut at x ~ 30 is removed
    ends = prims.line_endpoints.double().numpy()
    vertical = np.abs(ends[:, 1, 0] - ends[:, 0, 0]) < np.abs(ends[:, 1, 1] - ends[:, 0, 1])
    assert not np.any(vertical & (np.abs(ends.mean(1)[:, 0] - 29.9) < 0.6))
    assert np.any(~vertical & (np.abs(ends.mean(1)[:, 1]) < 0.5))


def test_artifact_line_mask_matches_per_line_loop():
    rng = np.random.default_rng(4)
    pts = rng.uniform(0, 10, (400, 2))
    pseg = rng.integers(0, 3, 400)
    occ = rng.uniform(0, 10, (60, 2))
    oseg = rng.integers(0, 3, 60)
    geometry = SubmapGeometry(pts, pseg, occ, oseg, np.array([10, 11, 12]))
    lines = rng.uniform(0, 10, (40, 2, 2))
    parent = rng.integers(0, 3, 40)
    kinds = np.where(rng.random(40) < 0.2, int(LineKind.INFINITE), int(LineKind.SEGMENT))
    cfg = GroundMapConfig(artifact_min_near_fraction=0.3, artifact_min_clear_fraction=0.3)
    keep = artifact_line_mask(lines, kinds, parent, geometry, cfg)
    for i in range(40):
        if kinds[i] != int(LineKind.SEGMENT):
            assert keep[i]
            continue
        s = lines[i, 0] + np.linspace(0, 1, 10)[:, None] * (lines[i, 1] - lines[i, 0])
        near = [np.linalg.norm(pts[pseg == parent[i]] - p, axis=1).min() <= 0.5 for p in s]
        own = occ[oseg == parent[i]]
        clear = [len(own) == 0 or np.linalg.norm(own - p, axis=1).min() > 0.5 for p in s]
        assert keep[i] == (np.mean(near) >= 0.3 and np.mean(clear) >= 0.3)
    assert 0 < keep.sum() < 40


def test_thin_by_distance():
    pos = np.array([[0.0, 0], [1, 0], [5, 0], [6, 0], [11, 0], [11, 5]])
    assert thin_by_distance(pos, 5.0).tolist() == [0, 2, 4, 5]


def test_flat_compact_segments_give_no_points_tall_ones_do():
    rng = np.random.default_rng(5)
    flat = _rectangle(0, 1.5, 0, 1.5)  # 2.25 m^2 of ground
    bush = _rectangle(5, 6.5, 0, 1.5)
    bush = np.concatenate([bush + [0, 0, h] for h in np.arange(0.05, 1.0, 0.1)])  # 1 m tall
    segs = [_segment(1, flat + rng.normal(0, 0.003, flat.shape)), _segment(2, bush)]
    prims, _ = submap_primitives(segs, np.array([3.0, 0.0, 0.0]), GroundMapConfig(), PrimitiveConfig(), 0.1)
    assert prims.point_segment_ids.tolist() == [2]
    np.testing.assert_allclose(prims.points_xy[0].numpy(), [5.75, 0.75], atol=0.05)
    off = GroundMapConfig(point_min_height_m=0.0)  # the reference: both are points
    prims, _ = submap_primitives(segs, np.array([3.0, 0.0, 0.0]), off, PrimitiveConfig(), 0.1)
    assert sorted(prims.point_segment_ids.tolist()) == [1, 2]


def test_box_shortcuts_of_the_radius_crop_give_the_per_point_crop():
    # segments wholly inside the radius, wholly outside and cut by it; with unknown boxes
    # (infinite) every point's distance is tested, which must give the same submap bitwise
    rng = np.random.default_rng(6)
    segs = []
    for sid, (x, y) in enumerate([(2, 1), (-6, 3), (17, 0), (19.8, -1), (26, 4), (0, -19.6)]):
        block = _rectangle(x, x + 1.5, y, y + 1.2) + rng.normal(0, 0.01, (1, 3))
        tall = np.concatenate([block + [0, 0, h] for h in np.arange(0.05, 0.9, 0.1)])
        occluded = _rectangle(x + 1.5, x + 1.9, y, y + 1.2, 0.1) + [0, 0, 0.3]
        segs.append(_segment(sid, tall, occluded))
    centre = np.array([0.0, 0.0, 0.5])
    cfg = GroundMapConfig(submap_radius_m=20.0)
    unknown = []
    for seg in segs:
        copy = TrackedSegment(**{**vars(seg), "_shape": None})
        copy.lo, copy.hi = np.full(3, -np.inf), np.full(3, np.inf)
        unknown.append(copy)
    prims, geometry = submap_primitives(segs, centre, cfg, PrimitiveConfig(), 0.1)
    plain_prims, plain_geometry = submap_primitives(unknown, centre, cfg, PrimitiveConfig(), 0.1)
    assert 2 <= len(geometry.segment_ids) < len(segs)
    for name in ("points_xy", "point_segment", "occluded_xy", "occluded_segment", "segment_ids"):
        np.testing.assert_array_equal(getattr(geometry, name), getattr(plain_geometry, name))
    for name in ("points_xy", "point_segment_ids", "line_endpoints", "line_kinds", "line_segment_ids"):
        assert torch.equal(getattr(prims, name), getattr(plain_prims, name))


def test_shares_cell_equals_a_set_of_group_cells():
    rng = np.random.default_rng(7)
    xy, groups = rng.uniform(0, 3, (200, 2)), rng.integers(0, 3, 200)
    others, others_groups = rng.uniform(1, 5, (150, 2)), rng.integers(0, 3, 150)
    got = _shares_cell(xy, groups, others, others_groups, 0.25)
    cells = {(g, c) for g, c in zip(others_groups.tolist(), voxel_hash(others, 0.25).tolist())}
    expected = [(g, c) in cells for g, c in zip(groups.tolist(), voxel_hash(xy, 0.25).tolist())]
    assert got.tolist() == expected
    # a cell shared only with other groups' points is not shared
    ungrouped = set(voxel_hash(others, 0.25).tolist())
    assert any(c in ungrouped and not e for c, e in zip(voxel_hash(xy, 0.25).tolist(), expected))
    assert 0 < got.sum() < len(got)
    with pytest.raises(ValueError, match="groups"):  # the key's z field holds fewer
        _shares_cell(xy, groups + (1 << 20), others, others_groups, 0.25)

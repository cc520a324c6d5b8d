"""End to end with the real matcher: synthetic ground submaps cut from the aerial map's own world.

The world is a set of point and line primitives with random descriptors; aerial patches hold
them in world metres. Each ground submap holds those within 30 m of the robot, moved into the
drifting odometry frame, with position noise, descriptor noise and a few wrong primitives.
Patch global descriptors are random; a submap's frame descriptors are noisy copies of the
descriptors of the patches it lies in, so place recognition works as it would on good data.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.backend.localizer import Localizer
from meridian_torch.config import MeridianConfig
from meridian_torch.geometry.se3 import pose_from_xyz_yaw, se3_inverse
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.types import (
    AerialMap,
    GroundSubmap,
    LineKind,
    PatchGrid,
    PrimitiveSet,
    stack_primitive_sets,
)

D, DG, SIZE = 16, 8, 150.0


pytestmark = pytest.mark.usefixtures("single_thread")


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _set(pts, pdesc, lines, ldesc) -> PrimitiveSet:
    def f(a):
        return torch.as_tensor(np.asarray(a), dtype=torch.float32)

    return PrimitiveSet(
        points_xy=f(pts).reshape(-1, 2),
        point_descriptors=f(pdesc).reshape(-1, D),
        point_segment_ids=torch.arange(len(pts)),
        line_endpoints=f(lines).reshape(-1, 2, 2),
        line_kinds=torch.full((len(lines),), int(LineKind.SEGMENT)),
        line_descriptors=f(ldesc).reshape(-1, D),
        line_segment_ids=torch.arange(len(lines)),
    )


def make_world(n_frames: int, spacing_m: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0, SIZE, (260, 2))
    pdesc = _unit(rng.normal(size=(260, D)))
    mid, ang, half = rng.uniform(0, SIZE, (120, 2)), rng.uniform(0, math.pi, 120), rng.uniform(2, 8, 120)
    direction = np.stack([np.cos(ang), np.sin(ang)], 1)
    lines = np.stack([mid - half[:, None] * direction, mid + half[:, None] * direction], 1)
    ldesc = _unit(rng.normal(size=(120, D)))

    starts = np.arange(0.0, SIZE - 60 + 1e-9, 30.0)
    bounds = np.array([[x, x + 60, y, y + 60] for y in starts for x in starts])

    def within(xy, b):
        return (xy[:, 0] >= b[0]) & (xy[:, 0] <= b[1]) & (xy[:, 1] >= b[2]) & (xy[:, 1] <= b[3])

    sets = [
        _set(pts[within(pts, b)], pdesc[within(pts, b)], lines[within(mid, b)], ldesc[within(mid, b)])
        for b in bounds
    ]
    patch_desc = _unit(rng.normal(size=(len(bounds), DG)))
    grid = PatchGrid(
        np.zeros((len(bounds), 4), np.int64),
        np.zeros((len(bounds), 2), np.int64),
        bounds,
        np.stack([bounds[:, :2].mean(1), bounds[:, 2:].mean(1)], 1),
    )
    aerial = AerialMap(
        grid,
        stack_primitive_sets(sets),
        torch.as_tensor(patch_desc, dtype=torch.float32),
        0.5,
        (0.0, SIZE),
        (300, 300),
    )

    s = np.arange(n_frames, dtype=float)
    a = s / 45.0
    gt = Trajectory(
        s * 0.5,
        pose_from_xyz_yaw(
            np.c_[75 + 45 * np.cos(a), 75 + 45 * np.sin(a), np.zeros(n_frames)], a + math.pi / 2
        ),
    )
    odom = [pose_from_xyz_yaw(np.array([5.0, -40.0, 0.0]), np.array(0.5)) @ gt.poses[0]]
    for step in se3_inverse(gt.poses[:-1]) @ gt.poses[1:]:
        odom.append(odom[-1] @ step @ pose_from_xyz_yaw(np.zeros(3), np.array(math.radians(0.01))))
    odometry = Trajectory(gt.timestamps, np.stack(odom))
    path = odometry.path_lengths()
    submaps = []
    for i, k in enumerate(np.searchsorted(path, np.arange(15.0, path[-1], spacing_m))):
        centre = gt.poses[k][:2, 3]
        T = odometry.poses[k] @ se3_inverse(gt.poses[k])  # T_odom_world
        R, t = T[:2, :2], T[:2, 3]
        pi = np.linalg.norm(pts - centre, axis=1) < 30
        li = np.linalg.norm(mid - centre, axis=1) < 30
        wrong = rng.uniform(-30, 30, (5, 2)) + centre
        g_pts = np.r_[pts[pi], wrong] @ R.T + t + rng.normal(0, 0.3, (pi.sum() + 5, 2))
        g_lines = lines[li] @ R.T + t + rng.normal(0, 0.3, (li.sum(), 2, 2))
        g_pdesc = _unit(np.r_[pdesc[pi] + rng.normal(0, 0.3, (pi.sum(), D)), rng.normal(size=(5, D))])
        g_ldesc = _unit(ldesc[li] + rng.normal(0, 0.3, (li.sum(), D)))
        inside = [p for p, b in enumerate(bounds) if within(centre[None], b)[0]]
        frames = _unit(patch_desc[inside] + rng.normal(0, 0.2, (len(inside), DG)))
        submaps.append(
            GroundSubmap(
                index=i,
                time=float(gt.timestamps[k]),
                T_odom_base=odometry.poses[k],
                path_length_m=float(path[k]),
                primitives=_set(g_pts, g_pdesc, g_lines, g_ldesc),
                frame_descriptors=torch.as_tensor(frames, dtype=torch.float32),
            )
        )
    return aerial, gt, odometry, submaps


def _config(solver: str) -> MeridianConfig:
    cfg = MeridianConfig()
    m = cfg.matching
    return cfg.model_copy(
        update={
            "matching": m.model_copy(
                update={
                    "solver": solver,
                    "place_recognition": m.place_recognition.model_copy(update={"k_global": 3}),
                    "particles": m.particles.model_copy(update={"n_particles": 16, "n_iterations": 100}),
                }
            )
        }
    )


def _run(n_frames: int, spacing_m: float, solver: str):
    aerial, gt, odometry, submaps = make_world(n_frames, spacing_m)
    loc = Localizer(aerial, _config(solver), odometry, gt.timestamps, seed=0)
    events = [loc.add_submap(s) for s in submaps]
    return gt, submaps, events, loc.finalize()


def _check(gt, submaps, events, result) -> None:
    assert result.localized and result.fix_submap_index is not None
    err = np.linalg.norm(result.T_world_base[:, :2, 3] - gt.poses[:, :2, 3], axis=1)
    assert np.sqrt(np.mean(err**2)) < 1.0
    inc = result.T_world_base_incremental
    ok = np.isfinite(inc[:, 0, 0])
    assert ok.any() and np.linalg.norm(inc[ok, :2, 3] - gt.poses[ok, :2, 3], axis=1).max() < 3.0
    assert len(result.inliers) >= 0.8 * len(submaps)


def test_localizes_with_the_real_matcher() -> None:
    # 8 submaps, 16 particles x 100 iterations: small enough for every test run.
    _check(*_run(n_frames=140, spacing_m=16.0, solver="particles"))


@pytest.mark.slow
def test_localizes_with_clipper_matching_on_a_full_loop() -> None:
    _check(*_run(n_frames=300, spacing_m=20.0, solver="clipper"))


def test_a_trajectory_off_the_map_is_reported_as_not_localized() -> None:
    """The same solution, judged against a map moved 10 km away: the sanity gate refuses it."""
    from meridian_torch.backend.sanity import off_map_fraction

    aerial, gt, odometry, submaps = make_world(n_frames=140, spacing_m=16.0)
    loc = Localizer(aerial, _config("particles"), odometry, gt.timestamps, seed=0)
    for s in submaps:
        loc.add_submap(s)
    moved = dataclasses.replace(aerial.patches, bounds_xy=aerial.patches.bounds_xy + 10_000.0)
    loc.aerial_map = dataclasses.replace(aerial, patches=moved)
    result = loc.finalize()
    assert not result.localized and np.isnan(result.T_world_base).all() and len(result.inliers) == 0
    assert "100 % of the final trajectory lies more than 50 m outside the aerial map" in result.rejected_because
    # On the real map the same run is localized: the gate refused the place, not the run.
    assert off_map_fraction(gt.poses[:, :2, 3], aerial.patches.bounds_xy, 50.0) == 0.0


def test_off_map_fraction_counts_positions_outside_every_grown_patch() -> None:
    from meridian_torch.backend.sanity import off_map_fraction

    bounds = np.array([[0.0, 60.0, 0.0, 60.0], [30.0, 90.0, 0.0, 60.0]])
    xy = np.array([[10.0, 10.0], [89.0, 59.0], [95.0, 30.0], [-4.0, 30.0], [200.0, 0.0]])
    assert off_map_fraction(xy, bounds, 0.0) == pytest.approx(3 / 5)
    assert off_map_fraction(xy, bounds, 5.0) == pytest.approx(1 / 5)


def _se2_path(x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    T = np.zeros((len(x), 3, 3))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = np.cos(yaw), -np.sin(yaw), x
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = np.sin(yaw), np.cos(yaw), y
    T[:, 2, 2] = 1.0
    return T


@settings(max_examples=20, deadline=None)
@given(yaw=st.floats(-3.1, 3.1), tx=st.floats(-1e4, 1e4), drift_deg_per_100m=st.floats(0.0, 20.0))
def test_heading_bend_is_what_the_solution_turns_beyond_the_odometry(yaw: float, tx: float,
                                                                     drift_deg_per_100m: float) -> None:
    """A rigid correction of the odometry bends nothing; a correction growing along the path
    bends by its growth within the window, whatever the rigid part."""
    from meridian_torch.backend.sanity import heading_bend_deg

    s = np.arange(0.0, 400.0, 1.0)  # 1 m steps along a winding path
    odom = _se2_path(*np.cumsum([np.cos(0.01 * s), np.sin(0.01 * s)], axis=1), 0.01 * s)
    rigid = _se2_path(np.array([tx]), np.array([0.0]), np.array([yaw]))[0]
    assert heading_bend_deg(rigid @ odom, odom, 100.0) == pytest.approx(0.0, abs=1e-6)
    turn = np.radians(drift_deg_per_100m) * s / 100.0
    bent = rigid @ odom @ _se2_path(0 * s, 0 * s, turn)
    assert heading_bend_deg(bent, odom, 100.0) == pytest.approx(drift_deg_per_100m, rel=0.02, abs=1e-6)


def test_inlier_disagreement_counts_loop_closures_the_solution_misses() -> None:
    from meridian_torch.backend.sanity import inlier_disagreement

    T = _se2_path(np.arange(6.0) * 10, np.zeros(6), np.zeros(6))
    assert inlier_disagreement(T, T, 10.0, 25.0) == 0.0
    moved = T.copy()
    moved[:2, 0, 2] += 11.0  # two missed by 11 m
    turned = moved @ _se2_path(np.zeros(6), np.zeros(6), np.radians([0, 0, 30, 0, 0, 0]))  # one by 30 deg
    assert inlier_disagreement(T, turned, 10.0, 25.0) == pytest.approx(3 / 6)


def test_a_trajectory_that_turns_away_from_the_odometry_is_reported_as_not_localized(monkeypatch) -> None:
    """The same run with its final solution bent by 90 deg a third of the way: the sanity gate
    refuses it, naming the heading and the missed loop closures (those of the last two thirds)."""
    from meridian_torch.backend import localizer as localizer_module

    aerial, gt, odometry, submaps = make_world(n_frames=140, spacing_m=16.0)
    loc = Localizer(aerial, _config("particles"), odometry, gt.timestamps, seed=0)
    for s in submaps:
        loc.add_submap(s)
    real = localizer_module.optimize_pose_graph

    def bent(*args, **kwargs):
        sol = real(*args, **kwargs)
        T = sol.T_world_base.copy()
        third = len(T) // 3
        pivot = T[third].copy()
        turn = _se2_path(np.zeros(1), np.zeros(1), np.array([np.pi / 2]))[0]
        T[third:] = pivot @ turn @ np.linalg.inv(pivot) @ T[third:]
        return dataclasses.replace(sol, T_world_base=T)

    monkeypatch.setattr(localizer_module, "optimize_pose_graph", bent)
    result = loc.finalize()
    assert not result.localized and np.isnan(result.T_world_base).all()
    assert "turns the odometry's heading by 90 deg" in result.rejected_because
    assert "misses" in result.rejected_because and "of its own loop closures" in result.rejected_because

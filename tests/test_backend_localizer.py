"""The localizer's state machine on a synthetic world with a scripted matcher.

The matcher is replaced by one that knows the truth: for every patch containing the submap's
true position it returns the true T_world_odom (plus small noise) among random wrong hypotheses,
so these tests exercise candidates, consistency, CLIPPER, the gate, commits and the pose graph,
not matching (tested in the matching suite; an end-to-end run with the real matcher is below).
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from meridian_torch.backend.frames import OnlineUpdate
from meridian_torch.backend.localizer import Localizer, localize_offline
from meridian_torch.backend.pose_graph import propagate_covariance
from meridian_torch.config import MeridianConfig
from meridian_torch.errors import ConfigError
from meridian_torch.geometry.planar import se2_from_se3, yaw_of
from meridian_torch.geometry.se2 import se2_matrix
from meridian_torch.geometry.se3 import pose_from_xyz_yaw, se3_inverse
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.matching.hypotheses import Hypotheses
from meridian_torch.types import AerialMap, GroundSubmap, PatchGrid, PrimitiveSet, stack_primitive_sets

D = 4
MAP_SIZE_M = 150.0


pytestmark = pytest.mark.usefixtures("single_thread")


def make_map(seed: int = 0) -> AerialMap:
    rng = np.random.default_rng(seed)
    starts = np.arange(0.0, MAP_SIZE_M - 60.0 + 1e-9, 30.0)
    bounds = np.array([[x, x + 60.0, y, y + 60.0] for y in starts for x in starts])
    sets = []
    for x0, x1, y0, y1 in bounds:
        pts = rng.uniform([x0, y0], [x1, y1], size=(20, 2))
        desc = torch.nn.functional.normalize(torch.randn(20, D, dtype=torch.float64), dim=-1)
        sets.append(
            PrimitiveSet(
                points_xy=torch.as_tensor(pts, dtype=torch.float32),
                point_descriptors=desc.float(),
                point_segment_ids=torch.arange(20),
                line_endpoints=torch.zeros(0, 2, 2),
                line_kinds=torch.zeros(0, dtype=torch.int64),
                line_descriptors=torch.zeros(0, D),
                line_segment_ids=torch.zeros(0, dtype=torch.int64),
            )
        )
    n = len(bounds)
    grid = PatchGrid(
        pixel_boxes=np.zeros((n, 4), dtype=np.int64),
        grid_index=np.zeros((n, 2), dtype=np.int64),
        bounds_xy=bounds,
        centres_xy=np.stack([bounds[:, :2].mean(1), bounds[:, 2:].mean(1)], 1),
    )
    return AerialMap(
        patches=grid,
        primitives=stack_primitive_sets(sets),
        global_descriptors=torch.randn(n, D),
        meters_per_pixel=0.5,
        origin_xy=(0.0, MAP_SIZE_M),
        image_size=(360, 360),
        crs="EPSG:32632",
    )


class World:
    """Ground truth, drifting odometry, submaps every `spacing_m` and a matcher that knows the truth."""

    def __init__(self, seed: int = 0, n_frames: int = 260, spacing_m: float = 20.0) -> None:
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.times = np.arange(n_frames) * 0.5
        # A loop around the map centre, 1 m per frame.
        s = np.arange(n_frames, dtype=np.float64)
        radius = 45.0
        ang = s / radius
        xy = np.stack([75 + radius * np.cos(ang), 75 + radius * np.sin(ang)], 1)
        yaw = ang + math.pi / 2
        z = 0.3 * np.sin(s / 20.0)
        self.gt = Trajectory(self.times, pose_from_xyz_yaw(np.c_[xy, z], yaw))
        # Odometry: T_odom_world (30 deg, offset) times ground truth, plus a slow yaw drift.
        T_odom_world = pose_from_xyz_yaw(np.array([5.0, -40.0, 0.0]), np.array(math.radians(30.0)))
        steps = se3_inverse(self.gt.poses[:-1]) @ self.gt.poses[1:]
        drift = pose_from_xyz_yaw(np.zeros((n_frames - 1, 3)), np.full(n_frames - 1, math.radians(0.01)))
        odom = [T_odom_world @ self.gt.poses[0]]
        for step, d in zip(steps, drift):
            odom.append(odom[-1] @ step @ d)
        self.odometry = Trajectory(self.times, np.stack(odom))
        path = self.odometry.path_lengths()
        self.submap_frames = [int(k) for k in np.searchsorted(path, np.arange(10.0, path[-1], spacing_m))]
        self.bad_submaps: set[int] = set()  # no correct hypothesis at all
        self.corrupt_submaps: set[int] = set()  # the correct hypothesis is shifted 25 m
        self.shift_m: dict[int, float] = {}  # the correct hypothesis is shifted this far along x
        self.probability_scale = 1.0  # of every hypothesis probability (0.4, 0.3, 0.2 by rank)
        self.calls: list[tuple[int, bool]] = []  # (submap, with rotation prior)
        self.priors: list[object] = []  # the rotation prior of each call

    def submaps(self) -> list[GroundSubmap]:
        out = []
        path = self.odometry.path_lengths()
        for i, k in enumerate(self.submap_frames):
            prims = PrimitiveSet.empty(D)
            # The scripted matcher identifies the submap by this id.
            prims = PrimitiveSet(
                points_xy=torch.zeros(1, 2),
                point_descriptors=torch.ones(1, D) / 2,
                point_segment_ids=torch.tensor([i]),
                line_endpoints=prims.line_endpoints,
                line_kinds=prims.line_kinds,
                line_descriptors=prims.line_descriptors,
                line_segment_ids=prims.line_segment_ids,
            )
            out.append(
                GroundSubmap(
                    index=i,
                    time=float(self.times[k]),
                    T_odom_base=self.odometry.poses[k],
                    path_length_m=float(path[k]),
                    primitives=prims,
                    frame_descriptors=torch.randn(2, D),
                )
            )
        return out

    def true_T_world_odom(self, i: int) -> np.ndarray:
        k = self.submap_frames[i]
        T = self.gt.poses[k] @ se3_inverse(self.odometry.poses[k])
        return np.array([[T[0, 0], T[0, 1], T[0, 3]], [T[1, 0], T[1, 1], T[1, 3]], [0, 0, 1.0]])

    def matcher(self, ground, aerial, *, rotation_prior, config, generator) -> Hypotheses:
        i = int(ground.point_segment_ids[0])
        self.calls.append((i, rotation_prior is not None))
        self.priors.append(rotation_prior)
        P, L, m = len(aerial), 3, 5
        k = self.submap_frames[i]
        true_xy = self.gt.poses[k][:2, 3]
        T_true = self.true_T_world_odom(i)
        theta = torch.empty(P, L, dtype=torch.float64)
        t = torch.empty(P, L, 2, dtype=torch.float64)
        prob = (torch.tensor([0.4, 0.3, 0.2], dtype=torch.float64) * self.probability_scale).expand(P, L).clone()
        for p in range(P):
            pts = aerial.points_xy[p][aerial.point_valid[p]].double().numpy()
            lo, hi = pts.min(0) - 2, pts.max(0) + 2
            # Wrong hypotheses: anywhere in the patch but >= 20 m from the truth, any yaw (near the
            # prior's when given), so that they are never consistent by chance.
            centre = self.rng.uniform(lo, hi, size=(64, 2))
            centre = centre[np.linalg.norm(centre - true_xy, axis=1) >= 20.0][:L]
            yaw = (
                self.rng.uniform(-math.pi, math.pi, size=L)
                if rotation_prior is None  # one yaw for all patches or one per patch
                else float(torch.as_tensor(rotation_prior).reshape(-1).expand(P)[p]) + self.rng.normal(0, 0.2, size=L)
            )
            T_wb_odom = se2_matrix(torch.as_tensor(yaw), torch.zeros(L, 2)).numpy()
            # choose t so that the submap centre maps to `centre`
            odom_xy = self.odometry.poses[k][:2, 3]
            theta[p] = torch.as_tensor(yaw)
            t[p] = torch.as_tensor(centre - np.einsum("lij,j->li", T_wb_odom[:, :2, :2], odom_xy))
            inside = np.all(true_xy >= lo) and np.all(true_xy <= hi)
            if inside and i not in self.bad_submaps:
                rank = int(self.rng.integers(0, 2))
                noise = self.rng.normal(0, [0.3, 0.3, math.radians(0.5)])
                shift = np.array([25.0 if i in self.corrupt_submaps else self.shift_m.get(i, 0.0), 0.0])
                theta[p, rank] = math.atan2(T_true[1, 0], T_true[0, 0]) + noise[2]
                t[p, rank] = torch.as_tensor(T_true[:2, 2] + noise[:2] + shift)
        valid = torch.ones(P, L, dtype=torch.bool)
        return Hypotheses(
            T_world_odom=se2_matrix(theta, t).float(),
            theta=theta.float(),
            t=t.float(),
            probability=prob.float(),
            association_mask=torch.ones(P, L, m, dtype=torch.bool),
            objective=torch.ones(P, L),
            valid=valid,
            pairs=torch.zeros(P, m, 2, dtype=torch.int64),
        )


def _cfg(**backend) -> MeridianConfig:
    cfg = MeridianConfig()
    return cfg.model_copy(
        update={
            "matching": cfg.matching.model_copy(
                update={
                    "place_recognition": cfg.matching.place_recognition.model_copy(
                        update={"mode": "exhaustive"}
                    )
                }
            ),
            "backend": cfg.backend.model_copy(update=backend),
        }
    )


def _xy_error(T: np.ndarray, gt: Trajectory) -> np.ndarray:
    return np.linalg.norm(T[:, :2, 3] - gt.poses[:, :2, 3], axis=1)


@pytest.fixture(scope="module")
def run():
    world = World(seed=1)
    world.bad_submaps = {0, 1, 2, 3}
    world.corrupt_submaps = {6}
    # online update covariances on, as the pipeline does with `backend.covariance`
    loc = Localizer(make_map(), _cfg(), world.odometry, world.times, matcher=world.matcher, online_covariance=True)
    events = [loc.add_submap(s) for s in world.submaps()]
    return world, loc, events, loc.finalize()


def test_fix_is_committed_exactly_when_the_gate_holds(run) -> None:
    world, _loc, events, result = run
    # Submaps 0-3 carry no correct hypothesis, 6 a corrupted one: after submap n there are
    # n - 4 correct submaps; the gate needs >= 6 of them and >= 50 % of n + 1 submaps: n = 10.
    fixed = [e.submap_index for e in events if e.fix_committed]
    assert fixed == [10]
    assert all(e.state == "pre" for e in events[:10]) and all(e.state == "post" for e in events[10:])
    assert result.fix_submap_index == 10 and result.fix_time == pytest.approx(events[10].time)
    # After the fix every new submap is matched once, with the rotation prior, near its pose.
    after = [c for c in world.calls if c[0] > 10]
    assert after and all(prior for _, prior in after)


def test_trajectory_is_recovered_and_corrupted_closure_rejected(run) -> None:
    world, _loc, _events, result = run
    assert result.localized
    err = _xy_error(result.T_world_base, world.gt)
    # Before the first and after the last inlier the drifting odometry extrapolates.
    span = (world.times >= result.inliers.time.min().item()) & (
        world.times <= result.inliers.time.max().item()
    )
    assert np.sqrt(np.mean(err[span] ** 2)) < 0.5 and np.sqrt(np.mean(err**2)) < 1.5
    yaw_err = np.abs(np.angle(np.exp(1j * (yaw_of(result.T_world_base) - world.gt.yaws))))
    assert np.degrees(yaw_err).max() < 2.0
    # z (and roll/pitch) come from the odometry.
    assert np.allclose(result.T_world_base[:, 2, 3], world.odometry.poses[:, 2, 3])
    inlier_submaps = set(result.inliers.submap_index.tolist())
    assert 6 not in inlier_submaps and not (inlier_submaps & world.bad_submaps)
    assert len(inlier_submaps) == len(result.inliers)  # one per submap
    assert len(inlier_submaps) >= len(world.submap_frames) - 6
    assert result.covariance is not None and result.covariance.shape == (len(world.times), 3, 3)
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0)


def test_online_estimate_is_causal_and_close(run) -> None:
    world, _loc, _events, result = run
    inc = result.T_world_base_incremental
    fix_time = result.fix_time
    before = world.times < fix_time
    assert np.all(np.isnan(inc[before])) and np.all(np.isfinite(inc[~before]))
    assert _xy_error(inc[~before], Trajectory(world.times[~before], world.gt.poses[~before])).max() < 3.0
    # The estimate of a frame depends only on updates available at its time: replaying the
    # localizer up to submap 10 gives identical estimates for frames before submap 11's time.
    world2 = World(seed=1)
    world2.bad_submaps, world2.corrupt_submaps = {0, 1, 2, 3}, {6}
    loc2 = Localizer(make_map(), _cfg(), world2.odometry, world2.times, matcher=world2.matcher)
    for s in world2.submaps()[:11]:
        loc2.add_submap(s)
    cut = world.times < world.times[world.submap_frames[11]]
    assert np.allclose(loc2.online_estimate()[cut], inc[cut], equal_nan=True)


def test_online_covariances_carry_the_update_of_the_online_estimate(run) -> None:
    """Per frame: the marginal of the update whose anchor gives the online estimate there, carried
    from that update's anchor frame along the odometry; NaN before the fix."""
    world, loc, _events, result = run
    cov = loc.online_covariances()
    np.testing.assert_array_equal(cov, result.covariance_incremental)
    online = result.incremental_frames
    assert online.any() and not online.all()
    assert np.isnan(cov[~online]).all() and np.isfinite(cov[online]).all()
    updates = loc._updates
    assert len(updates) > 1 and all(u.covariance is not None for u in updates)
    odom_se2 = se2_from_se3(world.odometry.poses)
    used = set()
    for k in np.flatnonzero(online):
        i = max(i for i, u in enumerate(updates) if u.available_time <= world.times[k])
        u = updates[i]
        used.add(i)
        # the update whose anchor the online estimate uses at this frame
        np.testing.assert_allclose((u.T_world_odom @ odom_se2[k])[:2, 2], result.T_world_base_incremental[k, :2, 3],
                                   atol=1e-9)
        assert u.node <= k
        expected = propagate_covariance(u.covariance, u.T_world_odom @ odom_se2[u.node : k + 1], loc.cfg.backend)
        np.testing.assert_allclose(cov[k], expected, rtol=1e-12, atol=0)
        if k == u.node:
            np.testing.assert_array_equal(cov[k], u.covariance)
    assert len(used) == len(updates)
    np.testing.assert_allclose(cov[-1], loc.latest_estimate()[1], rtol=1e-12)


def test_a_frame_before_its_updates_anchor_frame_is_carried_back(run) -> None:
    """Updates out of time order (not made by the localizer itself) can anchor after a frame that
    uses them: the anchor's marginal is then carried back along the odometry."""
    world, full, _events, _result = run
    loc = Localizer(make_map(), _cfg(), world.odometry, world.times, matcher=world.matcher)
    anchor_cov = np.diag([0.2, 0.3, 1e-4])
    T_world_odom = full._updates[0].T_world_odom
    loc._updates.append(OnlineUpdate(float(world.times[100]), T_world_odom, 120, anchor_cov))
    cov = loc.online_covariances()
    assert np.isnan(cov[:100]).all() and np.isfinite(cov[100:]).all()
    np.testing.assert_array_equal(cov[120], anchor_cov)
    back = (T_world_odom @ se2_from_se3(world.odometry.poses[105:121]))[::-1]
    np.testing.assert_allclose(cov[105], propagate_covariance(anchor_cov, back, loc.cfg.backend), rtol=1e-12)
    # away from the anchor frame, backwards or forwards, the position uncertainty grows
    for k in (100, 110, 130, 200):
        assert np.all(np.linalg.eigvalsh(cov[k][:2, :2] - anchor_cov[:2, :2]) > 0)


def test_without_online_covariance_the_result_has_none() -> None:
    _world, loc, _oldest, result = _windowed_run(4)
    assert not loc.online_covariance and result.covariance_incremental is None
    assert result.incremental_frames.any() and np.isnan(loc.online_covariances()).all()


def _windowed_run(window: int):
    world = World(seed=1)
    world.bad_submaps, world.corrupt_submaps = {0, 1, 2, 3}, {6}
    loc = Localizer(make_map(), _cfg(online_window_submaps=window), world.odometry, world.times,
                    matcher=world.matcher)
    oldest_in_pool = []
    for s in world.submaps():
        loc.add_submap(s)
        if loc.state == "post" and len(loc.pool):
            oldest_in_pool.append((s.index, int(loc.pool.submap_index.min())))
    return world, loc, oldest_in_pool, loc.finalize()


def test_a_window_longer_than_the_drive_changes_nothing(run) -> None:
    world, _loc, _events, result = run
    _, loc, _, windowed = _windowed_run(len(world.submap_frames) + 1)
    assert len(loc.archive) == 0
    np.testing.assert_array_equal(windowed.T_world_base, result.T_world_base)
    np.testing.assert_array_equal(windowed.T_world_base_incremental, result.T_world_base_incremental)


def test_online_window_bounds_the_pool_and_keeps_the_accepted_closures(run) -> None:
    """With a short window the online consistency graph only holds recent submaps, while the
    archived loop closures stay in the pose graph: the fix and the trajectory stay right."""
    world, _loc, _events, full = run
    window = 4
    _, loc, oldest_in_pool, result = _windowed_run(window)
    assert oldest_in_pool and all(latest - oldest < window for latest, oldest in oldest_in_pool)
    archived = loc.archive.submap_index.tolist()
    assert len(archived) == len(set(archived)) > 0  # at most one accepted closure per submap
    assert not set(archived) & (world.bad_submaps | world.corrupt_submaps)
    assert result.localized and result.fix_submap_index == full.fix_submap_index
    err = _xy_error(result.T_world_base, world.gt)
    assert np.sqrt(np.mean(err**2)) < 1.5
    online = np.isfinite(result.T_world_base_incremental[:, 0, 0])
    assert _xy_error(result.T_world_base_incremental[online], Trajectory(world.times[online], world.gt.poses[online])).max() < 3.0


def test_gate_fraction_blocks_the_fix() -> None:
    world = World(seed=2, n_frames=200)
    world.bad_submaps = set(range(6))  # 6 of 10 submaps are hopeless: never >= 50 % + 6
    loc = Localizer(make_map(), _cfg(final_rematch=False), world.odometry, world.times, matcher=world.matcher)
    events = [loc.add_submap(s) for s in world.submaps()]
    assert len(events) == 10 and not any(e.fix_committed for e in events)
    assert any(e.attempted for e in events)
    result = loc.finalize()
    assert not result.localized and result.incremental_trajectory is None
    assert np.all(np.isnan(result.T_world_base))
    assert len(result.final_hypotheses) == 0  # no final pass


@pytest.mark.parametrize("min_mean", [0.15, None])
def test_improbable_inliers_give_no_fix(min_mean: float | None) -> None:
    # The same consistent closures as the module's run, but every hypothesis 6x less probable: the
    # true ones at 0.05-0.067, below the mean the gate asks for, so no fix (and no final result)
    # unless the test is off; then the fix comes where the count and fraction allow it.
    world = World(seed=1)
    world.bad_submaps = {0, 1, 2, 3}
    world.corrupt_submaps = {6}
    world.probability_scale = 1 / 6
    loc = Localizer(make_map(), _cfg(fix_min_mean_probability=min_mean), world.odometry, world.times,
                    matcher=world.matcher)
    events = [loc.add_submap(s) for s in world.submaps()]
    attempts = [e for e in events if e.attempted]
    result = loc.finalize()
    if min_mean is None:
        assert [e.submap_index for e in events if e.fix_committed] == [10] and result.localized
    else:
        assert attempts and not any(e.fix_committed for e in events)
        assert not result.localized and np.all(np.isnan(result.T_world_base))


@pytest.mark.parametrize("after_refutations", [1, 2])
def test_a_fix_the_following_submaps_refute_is_revoked_and_the_estimate_withheld(after_refutations: int) -> None:
    world = World(seed=3, n_frames=360)
    world.corrupt_submaps = set(range(6))  # 0-5 agree with each other on a pose 25 m off: a wrong fix
    loc = Localizer(make_map(), _cfg(fix_revoke_after_refutations=after_refutations), world.odometry, world.times,
                    matcher=world.matcher, online_covariance=True)
    events = []
    for submap in world.submaps():
        events.append(loc.add_submap(submap))
        if events[-1].fix_revoked:
            assert loc.latest_estimate() == (None, None) and loc.state == "pre"
        if events[-1].fix_doubted:
            assert loc.latest_estimate() == (None, None) and loc.state == "post"
    fixes = [e.submap_index for e in events if e.fix_committed]
    revoked = [e.submap_index for e in events if e.fix_revoked]
    doubted = [e.submap_index for e in events if e.fix_doubted]
    b = loc.cfg.backend
    # the submaps after the wrong fix match the truth, not its prediction: none of them agrees
    first_refuted = fixes[0] + b.fix_min_inliers
    if after_refutations == 1:
        assert revoked == [first_refuted] and not doubted and len(fixes) == 2 and fixes[1] > revoked[0]
        # the new fix is again judged by 0-5's wrong agreement, the submap after it outvotes them
        recovered = fixes[1] + 1
    else:
        # nothing was committed at the doubting submap, so at the next one the alternatives of the
        # submaps since the fix outvote 0-5: the accepted set turns to the truth without a new search
        assert doubted == [first_refuted] and not revoked and len(fixes) == 1
        recovered = first_refuted + 1
    result = loc.finalize()
    t = world.times
    withheld = (t >= events[first_refuted].time) & (t < events[first_refuted + 1].time)
    assert withheld.any() and np.isnan(result.T_world_base_incremental[withheld]).all()
    assert np.isnan(result.covariance_incremental[withheld]).all()
    late = t >= events[recovered].time
    assert _xy_error(result.T_world_base_incremental[late], Trajectory(t[late], world.gt.poses[late])).max() < 3.0
    assert result.localized and _xy_error(result.T_world_base, world.gt).max() < 3.0


@pytest.mark.parametrize("after_refutations", [1, 2, 3])
def test_a_fix_refuted_by_that_many_submaps_in_a_row_is_revoked(after_refutations: int) -> None:
    # the wrong fix of the test above, and no submap after it finds a match (so the truth cannot
    # outvote it): every check refutes it; the first after_refutations - 1 only withhold
    world = World(seed=3, n_frames=360)
    world.corrupt_submaps = set(range(6))
    world.bad_submaps = set(range(6, len(world.submap_frames)))
    loc = Localizer(make_map(), _cfg(fix_revoke_after_refutations=after_refutations), world.odometry, world.times,
                    matcher=world.matcher)
    events = [loc.add_submap(s) for s in world.submaps()]
    fix = next(e.submap_index for e in events if e.fix_committed)
    first_refuted = fix + loc.cfg.backend.fix_min_inliers
    assert first_refuted + after_refutations <= len(events)
    assert [e.submap_index for e in events if e.fix_doubted] == list(
        range(first_refuted, first_refuted + after_refutations - 1))
    revoked = [e.submap_index for e in events if e.fix_revoked][0]
    assert revoked == first_refuted + after_refutations - 1
    # withheld from the first refuting submap until a new fix, if one comes
    refix = next((e.time for e in events[revoked:] if e.fix_committed), np.inf)
    withheld = (world.times >= events[first_refuted].time) & (world.times < refix)
    assert withheld.any() and np.isnan(loc.online_estimate()[withheld]).all()


def _sparse_world() -> tuple[World, int]:
    """A world whose right fix comes without failures at submap `fix`, after which 5 of the 9
    submaps find no match (4 of 9 agree, 44 %; fix + 10 agrees again); and that fix."""
    clean = World(seed=3, n_frames=360)
    first = Localizer(make_map(), _cfg(), clean.odometry, clean.times, matcher=clean.matcher)
    fix = next(e.submap_index for e in map(first.add_submap, clean.submaps()) if e.fix_committed)
    world = World(seed=3, n_frames=360)
    world.bad_submaps = {fix + k for k in (2, 4, 7, 8, 9)}
    assert fix + 10 < len(world.submap_frames)
    return world, fix


@pytest.mark.parametrize("revoke_below", [0.4, 0.5])
def test_a_right_fix_with_sparse_agreement_is_kept_above_the_revocation_fraction(revoke_below: float) -> None:
    # a right fix on the sparse KITTI 09 world was revoked like this under a 50 % rule
    world, fix = _sparse_world()
    # one refuting submap revokes: this tests the fraction (the second look has its own test below)
    loc = Localizer(make_map(), _cfg(fix_revoke_below_fraction=revoke_below, fix_revoke_after_refutations=1),
                    world.odometry, world.times, matcher=world.matcher)
    events = [loc.add_submap(s) for s in world.submaps()]
    assert [e.submap_index for e in events if e.fix_committed][0] == fix
    revoked = [e.submap_index for e in events if e.fix_revoked]
    b = loc.cfg.backend
    assert b.fix_min_inliers == 6
    if revoke_below <= 4 / 9:
        assert revoked == []
        late = world.times >= events[fix].time
        assert np.isfinite(loc.online_estimate()[late]).all()
    else:  # 4 of 8 still holds at 50 %, 4 of 9 does not
        assert revoked == [fix + 9]


def test_one_refuting_submap_only_withholds_the_estimate_when_two_in_a_row_revoke() -> None:
    # under the 50 % rule: fix + 9 refutes the right fix (4 of 9 agree), fix + 10 does not (5 of 10)
    world, fix = _sparse_world()
    loc = Localizer(make_map(), _cfg(fix_revoke_below_fraction=0.5, fix_revoke_after_refutations=2),
                    world.odometry, world.times, matcher=world.matcher, online_covariance=True)
    events = []
    for submap in world.submaps():
        events.append(loc.add_submap(submap))
        if events[-1].fix_doubted:
            assert loc.latest_estimate() == (None, None) and loc.state == "post"
        elif events[-1].submap_index > fix:
            assert loc.latest_estimate()[0] is not None
    assert [e.submap_index for e in events if e.fix_committed] == [fix]
    assert [e.submap_index for e in events if e.fix_doubted] == [fix + 9]
    assert not any(e.fix_revoked for e in events)
    t = world.times
    online, covariances = loc.online_estimate(), loc.online_covariances()
    withheld = (t >= events[fix + 9].time) & (t < events[fix + 10].time)
    assert withheld.any() and np.isnan(online[withheld]).all() and np.isnan(covariances[withheld]).all()
    resumed = t >= events[fix + 10].time
    assert np.isfinite(online[resumed]).all() and np.isfinite(covariances[resumed]).all()
    assert _xy_error(online[resumed], Trajectory(t[resumed], world.gt.poses[resumed])).max() < 3.0


def test_offline_mode_localizes() -> None:
    world = World(seed=3, n_frames=200)
    world.corrupt_submaps = {2}
    result = localize_offline(
        make_map(), _cfg(), world.odometry, world.times, world.submaps(), matcher=world.matcher
    )
    assert result.localized and result.fix_submap_index is None
    assert np.sqrt(np.mean(_xy_error(result.T_world_base, world.gt) ** 2)) < 1.0
    assert 2 not in result.inliers.submap_index.tolist()
    # pass 1 matched every submap without prior, pass 2 every submap with it
    assert sum(1 for _, prior in world.calls if not prior) == len(world.submap_frames)
    assert sum(1 for _, prior in world.calls if prior) == len(world.submap_frames)


def test_rewriting_a_folder_drops_the_previous_runs_optional_outputs(run, tmp_path) -> None:
    from meridian_torch.config import EvaluationConfig
    from meridian_torch.evaluation.trajectory_metrics import evaluate_run
    from meridian_torch.pipeline.outputs import write_outputs

    world, _loc, _events, result = run
    write_outputs(tmp_path, result, crs="EPSG:32632")
    evaluate_run(tmp_path, world.gt, EvaluationConfig())
    stale = ("trajectory.tum", "trajectory_incremental.tum", "covariance.csv", "covariance_incremental.csv",
             "trajectory_latlon.csv", "trajectory.geojson", "metrics.json")
    assert all((tmp_path / name).is_file() for name in stale)
    nan = np.full_like(result.T_world_base, np.nan)
    lost = dataclasses.replace(result, localized=False, T_world_base=nan, T_world_base_incremental=nan, covariance=None,
                               covariance_incremental=None)
    written = write_outputs(tmp_path, lost, crs="EPSG:32632")
    # A later evaluation must not find the earlier run's trajectories (it would report their ATE).
    assert not any((tmp_path / name).exists() for name in stale)
    assert set(written) == {p.name for p in tmp_path.iterdir()}


def test_outputs_follow_the_format_and_evaluate(run, tmp_path) -> None:
    from meridian_torch.config import EvaluationConfig
    from meridian_torch.evaluation.trajectory_metrics import evaluate_run
    from meridian_torch.io.poses import parse_tum
    from meridian_torch.io.results import read_covariances, read_outputs
    from meridian_torch.pipeline.outputs import write_outputs

    world, _loc, events, result = run
    written = write_outputs(tmp_path, result, crs="EPSG:32632")
    for name in (
        "trajectory.tum",
        "trajectory_incremental.tum",
        "covariance.csv",
        "covariance_incremental.csv",
        "loop_closures.csv",
        "hypotheses.csv",
        "submaps.csv",
        "localization.json",
        "trajectory_latlon.csv",
        "trajectory.geojson",
    ):
        assert name in written and (tmp_path / name).is_file()
    final, problems = parse_tum(tmp_path / "trajectory.tum")
    assert not problems and np.allclose(final.timestamps, world.times, atol=1e-9)  # every frame
    assert np.allclose(final.poses, result.T_world_base, atol=1e-9)
    inc, problems = parse_tum(tmp_path / "trajectory_incremental.tum")
    assert not problems and inc.timestamps[0] >= result.fix_time  # only from the fix on
    # One covariance row per frame of trajectory_incremental.tum (read_covariances checks the times).
    online_cov = read_covariances(tmp_path / "covariance_incremental.csv", inc)
    np.testing.assert_allclose(online_cov, result.covariance_incremental[result.incremental_frames], rtol=1e-12)
    # Every data line is `timestamp tx ty tz qx qy qz qw`.
    lines = [ln for ln in (tmp_path / "trajectory.tum").read_text().splitlines() if not ln.startswith("#")]
    assert all(len(ln.split()) == 8 for ln in lines)
    latlon = np.loadtxt(tmp_path / "trajectory_latlon.csv", delimiter=",", skiprows=1)
    # EPSG:32632 = UTM 32N: northing ~ 0-150 m is just north of the equator, easting ~ 0 lies far
    # west of the central meridian (9 E); mapped back, the points return to the trajectory.
    from rasterio.warp import transform

    assert np.all((latlon[:, 1] > 0) & (latlon[:, 1] < 0.01)) and np.all(
        (latlon[:, 2] > 3) & (latlon[:, 2] < 6)
    )
    x, y = transform("EPSG:4326", "EPSG:32632", latlon[:, 2].tolist(), latlon[:, 1].tolist())
    assert np.allclose(np.c_[x, y], final.poses[:, :2, 3], atol=1e-3)
    run_out = read_outputs(tmp_path)
    assert len(run_out.loop_closures) == len(result.inliers)
    metrics = evaluate_run(tmp_path, world.gt, EvaluationConfig())
    assert (tmp_path / "metrics.json").is_file()
    err = np.linalg.norm(result.T_world_base[:, :2, 3] - world.gt.poses[:, :2, 3], axis=1)
    assert metrics["final"]["ate_rmse_m"] == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-6)
    assert metrics["fraction_localized"] == pytest.approx(np.mean(world.times >= result.fix_time))
    assert metrics["time_to_first_fix_s"] == pytest.approx(result.fix_time - world.times[0])
    # ground truth runs 1 m per frame
    assert metrics["distance_to_first_fix_m"] == pytest.approx(result.fix_time / 0.5, rel=1e-3)
    online = metrics["incremental_covariance_consistency"]
    assert online["n"] == len(inc) and online["n_invalid_covariance"] == 0
    reg = metrics["registration_success"]["place_recognition"]["5m_5deg"]
    # Submaps 0-3 have no correct hypothesis and 6 a corrupted one; the others before the fix have
    # one at rank 1 or 2 of their patch (probabilities 0.4 / 0.3, a tie across patches).
    n_pre = len([e for e in events if e.submap_index <= result.fix_submap_index])
    assert reg["n_submaps"] == n_pre and reg["top25"] == pytest.approx((n_pre - 5) / n_pre)
    assert reg["top1"] < reg["top25"]
    # The final pass re-matched every submap; its hypotheses are written and evaluated as a mode.
    rows = run_out.hypotheses[run_out.hypotheses["mode"] == "final_rematch"]
    assert len(rows) == len(result.final_hypotheses) > 0
    assert set(rows["submap_index"].tolist()) == {e.submap_index for e in events}
    final = metrics["registration_success"]["final_rematch"]["5m_5deg"]
    assert final["n_submaps"] == len(events) and final["top25"] >= final["top1"] > 0


@settings(max_examples=15, deadline=None)
@given(fix_fraction=st.floats(0.0, 1.0, exclude_max=True), seed=st.integers(0, 2**32 - 1))
def test_covariance_incremental_csv_round_trips(run, fix_fraction: float, seed: int) -> None:
    """Whatever frame the fix comes at and whatever the values, covariance_incremental.csv has one
    row per frame of trajectory_incremental.tum, at its timestamps, with the values exactly."""
    from meridian_torch.io.poses import read_tum
    from meridian_torch.io.results import read_covariances
    from meridian_torch.pipeline.outputs import write_outputs

    _world, _loc, _events, result = run
    n = len(result.frame_times)
    fix_frame = int(fix_fraction * n)
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 3, 3)) * 10.0 ** rng.uniform(-6, 4, (n, 1, 1))  # variances 1e-12 to 1e8
    cov = A @ np.swapaxes(A, 1, 2)
    cov[:fix_frame] = np.nan
    online = result.T_world_base.copy()  # stands in for an online estimate from fix_frame on
    online[:fix_frame] = np.nan
    changed = dataclasses.replace(result, T_world_base_incremental=online, covariance_incremental=cov)
    with tempfile.TemporaryDirectory() as tmp:
        write_outputs(tmp, changed)
        inc = read_tum(Path(tmp) / "trajectory_incremental.tum")
        assert len(inc) == n - fix_frame
        np.testing.assert_allclose(inc.timestamps, result.frame_times[fix_frame:], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(read_covariances(Path(tmp) / "covariance_incremental.csv", inc), cov[fix_frame:])


def test_report_is_written(run, tmp_path) -> None:
    from meridian_torch.evaluation.report import write_report
    from meridian_torch.evaluation.trajectory_metrics import evaluate_run
    from meridian_torch.pipeline.outputs import write_outputs

    world, _loc, _events, result = run
    write_outputs(tmp_path, result)
    metrics = evaluate_run(tmp_path, world.gt)
    report = write_report(tmp_path, metrics=metrics, groundtruth=world.gt)
    text = report.read_text()
    assert f"{metrics['final']['ate_rmse_m']:.3g}" in text and "localized: **True**" in text
    for png in ("trajectory.png", "error_vs_distance.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (tmp_path / "trajectory.geojson").exists()  # no CRS, no geo outputs


def test_failed_attempts_rematch_only_new_submaps_while_the_inliers_stay() -> None:
    world = World(seed=4, n_frames=200)
    world.bad_submaps = set(range(10))  # nothing consistent: the pre-fix inlier set never changes
    cfg = _cfg(final_rematch=False, attempt_min_inliers=1)
    loc = Localizer(make_map(), cfg, world.odometry, world.times, matcher=world.matcher)
    events = [loc.add_submap(s) for s in world.submaps()]
    attempts = [e.submap_index for e in events if e.attempted]
    assert attempts == list(range(5, 10)) and not any(e.fix_committed for e in events)
    # The first attempt re-matches submaps 0-5, every later one only the newest submap.
    assert sum(1 for _, prior in world.calls if prior) == len(events)


def test_no_attempt_without_enough_pre_fix_inliers() -> None:
    world = World(seed=4, n_frames=200)
    world.bad_submaps = set(range(10))
    loc = Localizer(make_map(), _cfg(final_rematch=False, attempt_min_inliers=3), world.odometry, world.times,
                    matcher=world.matcher)
    events = [loc.add_submap(s) for s in world.submaps()]
    assert max(e.n_inliers for e in events) < 3
    assert not any(e.attempted for e in events) and not any(prior for _, prior in world.calls)


def test_cached_pool_graph_matches_a_fresh_one(run) -> None:
    # The pool's consistency graph is carried across submaps (appends, commits that drop
    # candidates); after all of it, it must equal the graph scored from scratch.
    from meridian_torch.backend.consistency import sparse_affinity

    _world, loc, events, _result = run
    n, (i, j, v) = loc._pool_edges
    assert n == len(loc.pool) and any(e.state == "post" for e in events)
    fi, fj, fv = sparse_affinity(loc.pool, loc.cfg.backend)
    assert sorted(zip(i.tolist(), j.tolist())) == sorted(zip(fi.tolist(), fj.tolist()))
    assert torch.allclose(v.sort().values, fv.sort().values)


def test_auto_mode_above_the_exhaustive_limit_matches_the_coarse_search_candidates() -> None:
    from meridian_torch.core.timing import record_stages

    world = World(seed=2, n_frames=120)
    cfg = _cfg(final_rematch=False)
    pr = cfg.matching.place_recognition.model_copy(update={"mode": "auto", "exhaustive_max_patches": 4, "k_coarse": 3})
    cfg = cfg.model_copy(update={"matching": cfg.matching.model_copy(update={"place_recognition": pr})})
    loc = Localizer(make_map(), cfg, world.odometry, world.times, matcher=world.matcher)
    with record_stages() as times:
        events = [loc.add_submap(s) for s in world.submaps()[:3]]
    assert [e.n_patches for e in events] == [3, 3, 3]
    assert times.calls["place recognition/coarse map"] == 1 and times.calls["place recognition/coarse search"] == 3


@pytest.mark.parametrize("fusion", ["always", "never"])
def test_coarse_mode_fuses_the_frames_global_descriptors_when_asked(fusion: str) -> None:
    """The patches a submap gets are the top k of the coarse search, fused with its frames' max
    cosine to the map's global descriptors when fusion is on (computed here from the parts)."""
    from meridian_torch.backend.results import StageSeconds
    from meridian_torch.backend.submap_matching import SubmapMatching
    from meridian_torch.matching.place_recognition import CoarseSearch, rank_fusion, stack_similarity

    world = World(seed=2, n_frames=120)
    cfg = _cfg()
    pr = cfg.matching.place_recognition.model_copy(update={"mode": "coarse", "k_coarse": 5, "global_fusion": fusion})
    cfg = cfg.model_copy(update={"matching": cfg.matching.model_copy(update={"place_recognition": pr})})
    aerial_map = make_map()
    submap = world.submaps()[2]
    # the submap's second frame looks like patch 7
    submap = dataclasses.replace(submap, frame_descriptors=torch.stack([submap.frame_descriptors[0],
                                                                         aerial_map.global_descriptors[7]]))
    patches, _ = SubmapMatching(aerial_map, cfg, world.matcher, 0, StageSeconds()).place_recognition_patches(submap)
    bounds = torch.as_tensor(aerial_map.patches.bounds_xy, dtype=torch.float64)
    coarse = CoarseSearch(aerial_map.primitives, bounds, pr.coarse).add_submap(
        submap.primitives, torch.as_tensor(submap.T_odom_base[:2, 3])).score[None]
    similarity = stack_similarity(submap.frame_descriptors[None], torch.ones(1, 2, dtype=torch.bool),
                                  aerial_map.global_descriptors)
    expected = rank_fusion([coarse, similarity], pr.fusion_rank_constant) if fusion == "always" else coarse
    assert patches.tolist() == expected[0].topk(5).indices.tolist()
    assert (7 in patches.tolist()) == (fusion == "always")  # the coarse search alone ranks it lower
    if fusion == "always":  # descriptors of another describer are refused, not compared
        other = dataclasses.replace(submap, frame_descriptors=torch.randn(2, D + 1))
        with pytest.raises(ConfigError, match="5 dimensions, the aerial map's 4"):
            SubmapMatching(aerial_map, cfg, world.matcher, 0, StageSeconds()).place_recognition_patches(other)


@pytest.mark.parametrize("yaw_prior", [True, False])
def test_coarse_candidates_are_matched_with_the_chains_yaw_when_asked(yaw_prior: bool) -> None:
    from meridian_torch.matching.place_recognition import CoarseSearch

    world = World(seed=2, n_frames=120)
    cfg = _cfg(final_rematch=False)
    pr = cfg.matching.place_recognition.model_copy(
        update={"mode": "coarse", "k_coarse": 4, "coarse_yaw_prior": yaw_prior})
    cfg = cfg.model_copy(update={"matching": cfg.matching.model_copy(update={"place_recognition": pr})})
    aerial_map = make_map()
    loc = Localizer(aerial_map, cfg, world.odometry, world.times, matcher=world.matcher)
    submaps = world.submaps()[:3]
    for s in submaps:
        loc.add_submap(s)
    # the chain computed from its parts: each submap's top 4 patches and the chain's yaw there
    search = CoarseSearch(aerial_map.primitives, torch.as_tensor(aerial_map.patches.bounds_xy, dtype=torch.float64),
                          pr.coarse)
    for k, s in enumerate(submaps):
        priors = search.add_submap(s.primitives, torch.as_tensor(s.T_odom_base[:2, 3]))
        top = priors.score.topk(4).indices
        if yaw_prior:
            assert torch.equal(torch.as_tensor(world.priors[k]), priors.yaw[top].double())
        else:
            assert world.priors[k] is None


def _gated_run(gate: float | None, shift_m: dict[int, float], last_submap: int, **backend):
    """The localizer after submaps 0..last_submap of a world whose submaps `shift_m` are shifted
    (`backend`: further config overrides)."""
    world = World(seed=1, n_frames=400)
    world.bad_submaps = {0, 1, 2, 3}
    world.shift_m = shift_m
    # loop-closure priors as tight as the scripted matcher's 0.3 m noise
    cfg = _cfg(online_gate_chi2=gate, prior_trans_sigma_m=0.5, **backend)
    loc = Localizer(make_map(), cfg, world.odometry, world.times, matcher=world.matcher, online_covariance=True)
    events = [loc.add_submap(s) for s in world.submaps()[: last_submap + 1]]
    return world, loc, events


def test_online_gate_holds_a_closure_that_disagrees_with_the_prediction() -> None:
    # Submap 14's only correct-looking closure is 2.5 m off: within the consistency tolerance
    # (3 m between neighbours), so CLIPPER accepts it, but outside the prediction's uncertainty.
    world, loc, events = _gated_run(None, {14: 2.5}, 14)
    assert events[9].fix_committed and 14 in loc._anchored
    world, loc, events = _gated_run(chi2.ppf(0.99, 3), {14: 2.5}, 14)
    assert 14 not in loc._anchored and 13 in loc._anchored
    assert 14 in loc.pool.select(loc._pool_inliers().inliers).submap_index.tolist()  # still a CLIPPER inlier
    # without the shift nothing is held
    world, loc, events = _gated_run(chi2.ppf(0.99, 3), {}, 14)
    assert set(range(4, 15)) <= set(loc._anchored)


@pytest.mark.parametrize("release_submaps", [2, 3])
def test_online_gate_takes_closures_of_enough_submaps_that_fail_it_together(release_submaps: int) -> None:
    # Successive submaps agree with each other and not with the prediction: the prediction may be
    # what is wrong, so the gate lets them in once there are `online_gate_release_submaps` of them.
    gate = chi2.ppf(0.99, 3)
    world, loc, events = _gated_run(gate, {14: 2.5, 15: 2.5}, 15, online_gate_release_submaps=release_submaps)
    if release_submaps <= 2:
        assert {14, 15} <= set(loc._anchored)
    else:  # two are not enough: both held
        assert not {14, 15} & set(loc._anchored) and 13 in loc._anchored
    world, loc, events = _gated_run(gate, {14: 2.5, 15: 2.5, 16: 2.5}, 16, online_gate_release_submaps=release_submaps)
    assert {14, 15, 16} <= set(loc._anchored)

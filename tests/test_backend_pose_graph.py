"""The GTSAM pose graph: alignment, optimization, covariance, and robustness through CLIPPER."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.backend.candidates import LoopClosureCandidates
from meridian_torch.backend.consistency import select_inliers
from meridian_torch.backend.pose_graph import (
    IncrementalPoseGraph,
    align_odometry,
    closure_sigma_scales,
    optimize_pose_graph,
    propagate_covariance,
)
from meridian_torch.config import BackendConfig


def se2(x, y, yaw) -> np.ndarray:
    x, y, yaw = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(yaw, float))
    T = np.zeros(yaw.shape + (3, 3))
    T[..., 0, 0], T[..., 0, 1], T[..., 0, 2] = np.cos(yaw), -np.sin(yaw), x
    T[..., 1, 0], T[..., 1, 1], T[..., 1, 2] = np.sin(yaw), np.cos(yaw), y
    T[..., 2, 2] = 1
    return T


def path(n: int = 120, drift_deg: float = 0.0):
    """Ground truth along an S-curve (1 m steps), and odometry in another frame with a per-step yaw drift."""
    yaw = 0.6 * np.sin(np.arange(n) / 25.0)
    truth, odom = [se2(10.0, 20.0, yaw[0])], [se2(-3.0, 7.0, 1.2)]
    for k in range(n - 1):
        step = se2(1.0, 0.0, yaw[k + 1] - yaw[k])
        truth.append(truth[-1] @ step)
        odom.append(odom[-1] @ step @ se2(0, 0, math.radians(drift_deg)))
    return np.stack(truth), np.stack(odom)


def test_align_odometry_recovers_the_frame() -> None:
    truth, odom = path()
    T_world_odom = truth[0] @ np.linalg.inv(odom[0])
    nodes = np.array([5, 40, 90])
    assert np.allclose(align_odometry(truth[nodes], odom[nodes]), T_world_odom, atol=1e-9)


def test_optimization_follows_priors_and_reports_covariance() -> None:
    truth, odom = path(drift_deg=0.05)  # 6 deg of heading drift over the path
    nodes = np.arange(0, 120, 15)
    cfg = BackendConfig(odom_rot_sigma_deg=0.5)  # the reference's older, softer odometry: lets the graph bend
    sol = optimize_pose_graph(odom, nodes, truth[nodes], cfg, covariance=True)
    err = np.linalg.norm(sol.T_world_base[:, :2, 2] - truth[:, :2, 2], axis=1)
    rigid = align_odometry(truth[nodes], odom[nodes]) @ odom
    err_rigid = np.linalg.norm(rigid[:, :2, 2] - truth[:, :2, 2], axis=1)
    assert err.max() < 0.5 * err_rigid.max()  # the graph bends the drifting odometry onto the priors
    assert sol.final_error < sol.initial_error
    cov = sol.covariance
    assert cov.shape == (120, 3, 3) and np.allclose(cov, np.swapaxes(cov, 1, 2))
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_covariance_is_in_world_axes() -> None:
    # A straight chain heading north with one prior at its start: far away the position is
    # uncertain across the heading (world x), not along it (world y).
    n = 60
    odom = se2(np.zeros(n), np.arange(n, dtype=float), np.full(n, math.pi / 2))
    sol = optimize_pose_graph(odom, np.array([0]), odom[:1], BackendConfig(), covariance=True)
    far = sol.covariance[-1]
    assert far[0, 0] > 5 * far[1, 1]
    assert sol.covariance[0, 0, 0] == pytest.approx(4.0, rel=1e-3)  # the prior's 2 m sigma


@settings(max_examples=10, deadline=None)
@given(turn_deg=st.floats(-3.0, 3.0), start=st.integers(0, 30), lengths_seed=st.integers(0, 2**16),
       per_metre=st.booleans())
def test_propagated_covariance_is_the_marginal_of_a_chain(turn_deg: float, start: int, lengths_seed: int,
                                                          per_metre: bool) -> None:
    """On a chain with one prior (a tree: linear-Gaussian propagation is exact to first order),
    carrying node `start`'s marginal along the odometry gives the marginal at the end, also when
    the steps differ in length and their noise grows with it."""
    n = 60
    lengths = np.random.default_rng(lengths_seed).uniform(0.2, 4.0, n)
    yaw = np.radians(turn_deg) * np.arange(n)
    steps = se2(lengths, np.zeros(n), np.radians(turn_deg) * np.ones(n))
    odom = np.stack(list(itertools.accumulate(steps[:-1], lambda T, s: T @ s, initial=np.eye(3))))
    assert np.allclose(np.arctan2(odom[:, 1, 0], odom[:, 0, 0]), np.angle(np.exp(1j * yaw)))
    cfg = BackendConfig(odom_rot_sigma_deg=0.5, odom_trans_sigma_m_per_sqrt_m=0.05 * per_metre,
                        odom_rot_sigma_deg_per_sqrt_m=0.1 * per_metre)
    sol = optimize_pose_graph(odom, np.array([0]), odom[:1], cfg, covariance=True)
    got = propagate_covariance(sol.covariance[start], sol.T_world_base[start:], cfg)
    np.testing.assert_allclose(got, sol.covariance[-1], rtol=1e-3, atol=1e-6)
    assert optimize_pose_graph(odom, np.array([0]), odom[:1], cfg, covariance="last").covariance.shape == (1, 3, 3)
    np.testing.assert_allclose(
        optimize_pose_graph(odom, np.array([0]), odom[:1], cfg, covariance="last").covariance[0], sol.covariance[-1]
    )


@pytest.mark.parametrize("length", [0.5, 3.0, 12.0])
def test_odometry_noise_grows_with_the_step_length(length: float) -> None:
    """One step of `length` m along x after a prior: the marginal of its end is the prior's plus the
    step's noise (per-step and per-metre variances added), its yaw swinging the lever arm."""
    cfg = BackendConfig(odom_trans_sigma_m_per_sqrt_m=0.07, odom_rot_sigma_deg_per_sqrt_m=0.2)
    odom = se2([0.0, length], [0.0, 0.0], [0.0, 0.0])
    cov = optimize_pose_graph(odom, np.array([0]), odom[:1], cfg, covariance=True).covariance[-1]
    var_t = cfg.odom_trans_sigma_m**2 + cfg.odom_trans_sigma_m_per_sqrt_m**2 * length
    var_yaw = (math.radians(cfg.odom_rot_sigma_deg) ** 2
               + math.radians(cfg.odom_rot_sigma_deg_per_sqrt_m) ** 2 * length)
    prior_t, prior_yaw = cfg.prior_trans_sigma_m**2, math.radians(cfg.prior_rot_sigma_deg) ** 2
    assert cov[0, 0] == pytest.approx(prior_t + var_t, rel=1e-6)
    assert cov[1, 1] == pytest.approx(prior_t + var_t + length**2 * prior_yaw, rel=1e-6)
    assert cov[2, 2] == pytest.approx(prior_yaw + var_yaw, rel=1e-6)


def test_corrupted_loop_closure_is_rejected() -> None:
    truth, odom = path(drift_deg=0.02)
    nodes = np.arange(5, 120, 10)
    meas = truth[nodes].copy()
    meas[4, :2, 2] += [12.0, -6.0]  # one corrupted loop closure
    n = len(nodes)
    cands = LoopClosureCandidates(
        submap_index=torch.arange(n),
        patch_index=torch.zeros(n, dtype=torch.int64),
        time=torch.as_tensor(nodes, dtype=torch.float64),
        path_length_m=torch.as_tensor(nodes, dtype=torch.float64),
        T_odom_base=torch.as_tensor(odom[nodes]),
        T_world_base=torch.as_tensor(meas),
        probability=torch.ones(n, dtype=torch.float64),
        quality=torch.ones(n, dtype=torch.float64),
        n_associations=torch.full((n,), 10),
    )
    sel = select_inliers(cands, BackendConfig(), torch.Generator().manual_seed(0))
    assert sel.inliers.tolist() == [k != 4 for k in range(n)]
    good = optimize_pose_graph(odom, nodes[sel.inliers.numpy()], meas[sel.inliers.numpy()], BackendConfig())
    bad = optimize_pose_graph(odom, nodes, meas, BackendConfig())
    err_good = np.linalg.norm(good.T_world_base[:, :2, 2] - truth[:, :2, 2], axis=1).max()
    err_bad = np.linalg.norm(bad.T_world_base[:, :2, 2] - truth[:, :2, 2], axis=1).max()
    assert err_good < 0.6 and err_bad > 2 * err_good


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**16), drift_deg=st.floats(-0.05, 0.05), drop_every=st.integers(2, 6))
def test_incremental_graph_follows_the_batch_solution(seed: int, drift_deg: float, drop_every: int) -> None:
    """The online graph, grown frame batch by frame batch with priors added and withdrawn, ends
    every update where the batch solve of the same factors ends (last pose and its covariance)."""
    rng = np.random.default_rng(seed)
    truth, odom = path(n=300, drift_deg=drift_deg)
    nodes = np.arange(7, 300, 23)
    meas = truth[nodes] @ se2(rng.normal(0, 1.5, len(nodes)), rng.normal(0, 1.5, len(nodes)),
                              rng.normal(0, 0.06, len(nodes)))
    scales = rng.uniform(1.0, 3.0, len(nodes))  # each closure its own weight, as from its probability
    cfg = BackendConfig()
    graph = IncrementalPoseGraph(cfg)
    for j in range(2, len(nodes)):
        n = min(int(nodes[j]) + 1 + int(rng.integers(0, 10)), len(odom))
        given_ = np.arange(j + 1)
        given_ = given_[(given_ % drop_every != j % drop_every) | (given_ == j)]  # some earlier priors withdrawn
        T_last, cov = graph.update(odom[:n], nodes[given_], meas[given_], covariance=True, prior_scales=scales[given_])
        batch = optimize_pose_graph(odom[:n], nodes[given_], meas[given_], cfg, covariance="last",
                                    prior_scales=scales[given_])
        assert graph.n_nodes == n
        assert np.linalg.norm(T_last[:2, 2] - batch.T_world_base[-1, :2, 2]) < 0.01
        assert abs(math.atan2(T_last[1, 0], T_last[0, 0]) - math.atan2(*batch.T_world_base[-1, 1::-1, 0])) < 1e-3
        assert np.abs(cov - batch.covariance[0]).max() < 1e-2 * np.abs(batch.covariance[0]).max()


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(1e-6, 1.0), min_size=1, max_size=20), st.floats(0.01, 1.0), st.floats(1.0, 10.0))
def test_closure_sigma_scales(probability: list[float], reference: float, max_scale: float) -> None:
    p = np.array(probability)
    scales = closure_sigma_scales(p, BackendConfig(prior_sigma_probability=reference, prior_sigma_max_scale=max_scale))
    assert ((scales >= 1.0) & (scales <= max_scale)).all()
    assert (scales[p >= reference] == 1.0).all()  # a probable closure keeps the configured sigmas
    inside = (p < reference) & (np.sqrt(reference / p) <= max_scale)
    np.testing.assert_allclose(scales[inside], np.sqrt(reference / p[inside]))  # variance ~ 1 / p
    order = np.argsort(p)
    assert (np.diff(scales[order]) <= 0).all()  # less probable: never more trusted
    assert (closure_sigma_scales(p, BackendConfig(prior_sigma_probability=None)) == 1.0).all()


def test_a_scaled_closure_pulls_less() -> None:
    # Two closures on the same frame, 4 m apart: the solution lies between them, nearer the one
    # with the smaller sigmas, at the ratio of their weights (1 / scale^2).
    truth, odom = path(60)
    left, right = truth[30] @ se2(0.0, -2.0, 0.0), truth[30] @ se2(0.0, 2.0, 0.0)
    nodes, meas = np.array([30, 30]), np.stack([left, right])
    cfg = BackendConfig()
    for scales in ([1.0, 1.0], [1.0, 3.0], [2.0, 1.0]):
        sol = optimize_pose_graph(odom, nodes, meas, cfg, prior_scales=np.array(scales))
        lateral = (np.linalg.inv(truth[30]) @ sol.T_world_base[30])[1, 2]
        w = 1.0 / np.array(scales) ** 2
        assert lateral == pytest.approx((w[0] * -2.0 + w[1] * 2.0) / w.sum(), abs=0.05)
    with pytest.raises(ValueError, match="prior scales"):
        optimize_pose_graph(odom, nodes, meas, cfg, prior_scales=np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match="prior scales"):
        optimize_pose_graph(odom, nodes, meas, cfg, prior_scales=np.array([1.0]))


def test_incremental_graph_refuses_to_drop_frames() -> None:
    truth, odom = path(50)
    graph = IncrementalPoseGraph(BackendConfig())
    graph.update(odom[:40], np.array([10]), truth[10:11])
    with pytest.raises(ValueError, match="cannot drop frames"):
        graph.update(odom[:30], np.array([10]), truth[10:11])


def test_bad_inputs() -> None:
    _, odom = path(10)
    with pytest.raises(ValueError):
        optimize_pose_graph(odom, np.array([], dtype=int), np.zeros((0, 3, 3)), BackendConfig())
    with pytest.raises(ValueError):
        optimize_pose_graph(odom, np.array([10]), odom[:1], BackendConfig())

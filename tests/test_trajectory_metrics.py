"""Trajectory metrics: ATE / heading against a direct computation and against evo on the same TUM files;
covariance consistency against Gaussian errors drawn from the covariances."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.evaluation.trajectory_metrics import (
    CONSISTENT_NEES,
    CONSISTENT_POSITION_NEES,
    CONSISTENT_WITHIN_2SIGMA,
    associate,
    covariance_consistency,
    registration_success,
    trajectory_errors,
)
from meridian_torch.geometry.se3 import pose_from_xyz_yaw
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.poses import read_tum, write_tum


def _pair(seed: int = 0, planar: bool = True):
    rng = np.random.default_rng(seed)
    t_gt = np.arange(200) * 0.1
    yaw = np.cumsum(rng.normal(0, 0.05, 200))
    xyz = np.c_[
        np.cumsum(np.cos(yaw)), np.cumsum(np.sin(yaw)), np.zeros(200) if planar else rng.normal(0, 1, 200)
    ]
    gt = Trajectory(t_gt, pose_from_xyz_yaw(xyz, yaw))
    # Estimates at a different rate, slightly shifted times (within 5 ms), with errors; some have no GT.
    t_est = np.r_[np.arange(0, 200, 2) * 0.1 + rng.uniform(-0.005, 0.005, 100), [25.0, 26.0]]
    base = gt.interpolate(np.clip(t_est, 0, t_gt[-1]))
    noise_xy = rng.normal(0, 0.8, (len(t_est), 2))
    noise_yaw = rng.normal(0, 0.05, len(t_est))
    est_xyz = (
        base[:, :3, 3] + np.c_[noise_xy, np.zeros(len(t_est)) if planar else rng.normal(0, 3, len(t_est))]
    )
    est = Trajectory(t_est, pose_from_xyz_yaw(est_xyz, np.arctan2(base[:, 1, 0], base[:, 0, 0]) + noise_yaw))
    return est, gt


def test_ate_matches_direct_computation() -> None:
    est, gt = _pair(planar=False)  # z differs wildly: ATE is 2D and must ignore it
    e = trajectory_errors(est, gt, 0.01)
    assert len(e.times) == 100  # the two estimates beyond the ground truth are skipped
    i, j = associate(est.timestamps, gt.timestamps, 0.01)
    assert np.all(np.abs(est.timestamps[i] - gt.timestamps[j]) <= 0.005 + 1e-12)
    direct = np.sqrt(np.mean(np.sum((est.positions[:100, :2] - gt.positions[::2, :2]) ** 2, axis=1)))
    assert e.summary()["ate_rmse_m"] == pytest.approx(direct, rel=1e-12)
    yaw_err = np.angle(np.exp(1j * (est.yaws[:100] - gt.yaws[::2])))
    assert e.summary()["heading_rmse_deg"] == pytest.approx(
        math.degrees(np.sqrt(np.mean(yaw_err**2))), rel=1e-9
    )


def test_ate_agrees_with_evo_on_the_same_files(tmp_path) -> None:
    evo_metrics = pytest.importorskip("evo.core.metrics")
    from evo.core import sync
    from evo.tools import file_interface

    est, gt = _pair(seed=3)
    write_tum(tmp_path / "est.tum", est)
    write_tum(tmp_path / "gt.tum", gt)
    ours = trajectory_errors(read_tum(tmp_path / "est.tum"), read_tum(tmp_path / "gt.tum"), 0.01).summary()
    ref, est_evo = sync.associate_trajectories(
        file_interface.read_tum_trajectory_file(str(tmp_path / "gt.tum")),
        file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum")),
        max_diff=0.01,
    )
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)  # unaligned; z is 0 in both files
    ape.process_data((ref, est_evo))
    assert ape.get_statistic(evo_metrics.StatisticsType.rmse) == pytest.approx(ours["ate_rmse_m"], rel=1e-9)
    assert ape.get_statistic(evo_metrics.StatisticsType.max) == pytest.approx(ours["ate_max_m"], rel=1e-9)
    rot = evo_metrics.APE(evo_metrics.PoseRelation.rotation_angle_deg)  # pure yaw: angle = |yaw error|
    rot.process_data((ref, est_evo))
    assert rot.get_statistic(evo_metrics.StatisticsType.rmse) == pytest.approx(
        ours["heading_rmse_deg"], rel=1e-6
    )
    assert ours["n"] == ref.num_poses


def test_registration_success_top_k() -> None:
    gt = Trajectory(
        np.array([0.0, 10.0]), pose_from_xyz_yaw(np.array([[0.0, 0, 0], [100.0, 0, 0]]), np.zeros(2))
    )
    truth = np.array([50.0, 0.0, 0.0])  # at t = 5
    wrong = np.array([80.0, 30.0, 1.0])
    hyps = [
        np.stack([wrong, truth + [4.0, 0, 0], wrong]),  # correct at rank 2 (4 m off)
        np.stack([truth + [0, 0, math.radians(7)]]),  # 7 deg off: only the loose threshold
        np.zeros((0, 3)),
    ]  # nothing
    scores = [np.array([0.5, 0.3, 0.2]), np.array([1.0]), np.zeros(0)]
    strict = registration_success(
        np.array([5.0, 5.0, 5.0]), hyps, scores, gt, top_k=[1, 2], translation_m=5, rotation_deg=5
    )
    assert strict == {"n_submaps": 3, "top1": 0.0, "top2": pytest.approx(1 / 3)}
    loose = registration_success(
        np.array([5.0, 5.0, 5.0]), hyps, scores, gt, top_k=[1, 2], translation_m=5, rotation_deg=10
    )
    assert loose == {"n_submaps": 3, "top1": pytest.approx(1 / 3), "top2": pytest.approx(2 / 3)}


# Covariance consistency (NEES, 2-sigma fraction) of per-pose (x, y, yaw) covariances, world axes.

N_POSES = 4000  # tolerances below are 5 standard errors of the mean over this many poses


def _random_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3, 3) random covariances of (x, y, yaw): metres to tens of metres, mrad to a tenth of a
    rad, random correlations (A A^T plus a floor that keeps them well conditioned)."""
    scale = np.c_[10.0 ** rng.uniform(-1, 1, (n, 2)), 10.0 ** rng.uniform(-3, -1, n)]
    A = rng.normal(size=(n, 3, 3)) * scale[:, :, None]
    return A @ np.swapaxes(A, 1, 2) + 0.1 * scale[:, :, None] ** 2 * np.eye(3)


def _estimate_with_errors(gt: Trajectory, errors_xy_yaw: np.ndarray) -> Trajectory:
    xyz = gt.positions + np.c_[errors_xy_yaw[:, :2], np.zeros(len(gt))]
    return Trajectory(gt.timestamps, pose_from_xyz_yaw(xyz, gt.yaws + errors_xy_yaw[:, 2]))


def _gaussian_case(seed: int, n: int = N_POSES) -> tuple[Trajectory, Trajectory, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    gt = Trajectory(
        np.arange(n) * 0.1,
        pose_from_xyz_yaw(
            np.c_[rng.uniform(-500, 500, (n, 2)), np.zeros(n)], rng.uniform(-math.pi, math.pi, n)
        ),
    )
    cov = _random_spd(rng, n)
    errors = (np.linalg.cholesky(cov) @ rng.normal(size=(n, 3, 1)))[:, :, 0]
    return gt, _estimate_with_errors(gt, errors), cov, errors


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_gaussian_errors_are_consistent(seed: int) -> None:
    gt, est, cov, _ = _gaussian_case(seed)
    c = covariance_consistency(est, cov, gt)
    assert c["n"] == N_POSES and c["n_without_groundtruth"] == c["n_invalid_covariance"] == 0
    # chi2(k): mean k, variance 2k; a Bernoulli(p) fraction: variance p (1 - p)
    assert c["nees_mean"] == pytest.approx(CONSISTENT_NEES, abs=5 * math.sqrt(6 / N_POSES))
    assert c["position_nees_mean"] == pytest.approx(CONSISTENT_POSITION_NEES, abs=5 * math.sqrt(4 / N_POSES))
    p = CONSISTENT_WITHIN_2SIGMA
    assert p == pytest.approx(0.8647, abs=1e-4)
    assert c["position_within_2sigma"] == pytest.approx(p, abs=5 * math.sqrt(p * (1 - p) / N_POSES))


@settings(max_examples=5, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_errors_three_times_too_large_give_nine_times_the_nees(seed: int) -> None:
    gt, est, cov, errors = _gaussian_case(seed)  # yaw sigma <= 0.2 rad: 3x errors stay inside (-pi, pi)
    c1 = covariance_consistency(est, cov, gt)
    c3 = covariance_consistency(_estimate_with_errors(gt, 3 * errors), cov, gt)
    assert c3["nees_mean"] == pytest.approx(9 * c1["nees_mean"], rel=1e-6)
    assert c3["nees_mean"] == pytest.approx(9 * CONSISTENT_NEES, abs=9 * 5 * math.sqrt(6 / N_POSES))
    assert c3["position_nees_mean"] == pytest.approx(
        9 * CONSISTENT_POSITION_NEES, abs=9 * 5 * math.sqrt(4 / N_POSES)
    )
    p = 1 - math.exp(-2 / 9)  # P(chi2_2 <= 4 / 9)
    assert c3["position_within_2sigma"] == pytest.approx(p, abs=5 * math.sqrt(p * (1 - p) / N_POSES))


def test_yaw_error_across_pi_is_wrapped() -> None:
    gt = Trajectory(
        np.array([0.0]), pose_from_xyz_yaw(np.array([[5.0, 5.0, 0.0]]), np.array([math.pi - 0.01]))
    )
    est = Trajectory(
        np.array([0.0]), pose_from_xyz_yaw(np.array([[5.0, 5.0, 0.0]]), np.array([-math.pi + 0.01]))
    )
    c = covariance_consistency(est, np.diag([1.0, 1.0, 0.01**2])[None], gt)
    assert c["n"] == 1 and c["nees_mean"] == pytest.approx((0.02 / 0.01) ** 2, rel=1e-6)
    assert c["position_nees_mean"] == pytest.approx(0.0, abs=1e-12) and c["position_within_2sigma"] == 1.0


def test_poses_without_groundtruth_or_valid_covariance_are_skipped_and_counted() -> None:
    gt, est, cov, errors = _gaussian_case(7, n=50)
    late = Trajectory(np.r_[est.timestamps, 100.0, 101.0], np.concatenate([est.poses, est.poses[:2]]))
    cov = np.concatenate([cov, cov[:2]])
    cov[3] = np.diag([1.0, 1.0, 0.0])  # singular
    cov[4, 0, 1] = np.nan
    cov[5] = np.diag([1.0, -1.0, 1.0])  # indefinite
    c = covariance_consistency(late, cov, gt)
    assert (c["n"], c["n_without_groundtruth"], c["n_invalid_covariance"]) == (47, 2, 3)
    keep = np.r_[0:3, 6:50]
    direct = [e @ np.linalg.inv(S) @ e for e, S in zip(errors[keep], cov[keep])]
    position = [e[:2] @ np.linalg.inv(S[:2, :2]) @ e[:2] for e, S in zip(errors[keep], cov[keep])]
    assert c["nees_mean"] == pytest.approx(np.mean(direct), rel=1e-6)
    assert c["position_nees_mean"] == pytest.approx(np.mean(position), rel=1e-6)
    assert c["position_within_2sigma"] == pytest.approx(np.mean(np.array(position) <= 4), abs=1e-12)
    none = covariance_consistency(late, np.full_like(cov, np.nan), gt)
    assert none["n"] == 0 and none["nees_mean"] is None and none["n_invalid_covariance"] == 50


def _write_run(
    out_dir, gt: Trajectory, est: Trajectory, cov: np.ndarray | None, cov_incremental: np.ndarray | None = None
) -> None:
    """A run folder as `pipeline.outputs.write_outputs` writes it, localized, without loop closures;
    the online estimate is `est` from half-way on, its covariances `cov_incremental` (N, 3, 3)."""
    from meridian_torch.backend.candidates import LoopClosureCandidates
    from meridian_torch.backend.results import LocalizationResult
    from meridian_torch.pipeline.outputs import write_outputs

    incremental = est.poses.copy()
    incremental[: len(est) // 2] = np.nan  # the fix comes half-way
    result = LocalizationResult(
        frame_times=est.timestamps,
        T_world_base=est.poses,
        covariance=cov,
        T_world_base_incremental=incremental,
        localized=True,
        inliers=LoopClosureCandidates.empty(),
        fix_submap_index=0,
        fix_time=float(est.timestamps[len(est) // 2]),
        submap_hypotheses={},
        submap_matching_mode={},
        final_hypotheses=LoopClosureCandidates.empty(),
        events=[],
        timings={},
        covariance_incremental=cov_incremental,
    )
    write_outputs(out_dir, result)


def test_evaluate_run_and_report_carry_the_covariance_consistency(tmp_path) -> None:
    from meridian_torch.evaluation.report import write_report
    from meridian_torch.evaluation.trajectory_metrics import evaluate_run

    gt, est, cov, _ = _gaussian_case(11, n=200)
    _write_run(tmp_path, gt, est, cov)
    metrics = evaluate_run(tmp_path, gt)
    c = metrics["final_covariance_consistency"]
    assert c == pytest.approx(covariance_consistency(est, cov, gt), rel=1e-9)  # the CSV holds exact floats
    assert json.loads((tmp_path / "metrics.json").read_text())[
        "final_covariance_consistency"
    ] == pytest.approx(c)
    assert metrics["incremental"]["ate_max_m"] >= metrics["incremental"]["ate_rmse_m"] > 0
    text = write_report(tmp_path, metrics=metrics).read_text()
    assert f"mean NEES {c['nees_mean']:.3g}" in text and "86.5 %" in text

    _write_run(tmp_path, gt, est, None)  # without covariance.csv: no consistency
    assert evaluate_run(tmp_path, gt)["final_covariance_consistency"] is None
    assert "NEES" not in write_report(tmp_path, metrics=evaluate_run(tmp_path, gt)).read_text()


def test_evaluate_run_and_report_carry_the_incremental_covariance_consistency(tmp_path) -> None:
    from meridian_torch.evaluation.report import write_report
    from meridian_torch.evaluation.trajectory_metrics import evaluate_run

    gt, est, cov, _ = _gaussian_case(12, n=200)
    online_cov = cov.copy()
    online_cov[:100] = np.nan  # before the fix (frames 0-99 have no online estimate)
    online_cov[100:] *= 4.0  # differs from the final covariance: the metric reads the right file
    _write_run(tmp_path, gt, est, cov, online_cov)
    metrics = evaluate_run(tmp_path, gt)
    online = Trajectory(est.timestamps[100:], est.poses[100:])
    c = metrics["incremental_covariance_consistency"]
    assert c == pytest.approx(covariance_consistency(online, online_cov[100:], gt), rel=1e-9)
    assert c["n"] == 100 and c["n_invalid_covariance"] == 0
    assert metrics["final_covariance_consistency"] == pytest.approx(covariance_consistency(est, cov, gt), rel=1e-9)
    assert json.loads((tmp_path / "metrics.json").read_text())[
        "incremental_covariance_consistency"
    ] == pytest.approx(c)
    text = write_report(tmp_path, metrics=metrics).read_text()
    assert f"incremental covariance consistency over 100 poses: mean NEES {c['nees_mean']:.3g}" in text
    assert "final covariance consistency over 200 poses" in text

    _write_run(tmp_path, gt, est, cov)  # without covariance_incremental.csv: no online consistency
    metrics = evaluate_run(tmp_path, gt)
    assert metrics["incremental_covariance_consistency"] is None
    assert metrics["final_covariance_consistency"] is not None
    assert "incremental covariance consistency" not in write_report(tmp_path, metrics=metrics).read_text()

"""Trajectory metrics: ATE / heading against a direct computation and against evo on the same TUM files."""

from __future__ import annotations

import math

import numpy as np
import pytest

from meridian_torch.evaluation.trajectory_metrics import associate, registration_success, trajectory_errors
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

"""Trajectory and registration metrics (paper section IV).

- ATE: unaligned 2D RMSE of |xy_est - xy_gt| at the same timestamps (no alignment: both are in
  the world frame), also mean and max; heading error |wrap(yaw_est - yaw_gt)| RMSE, mean, max.
  Computed for the final trajectory and for the incremental (online) one over its frames.
- fraction of frames localized (frames with an online estimate / all frames), distance (ground
  truth path length) and time from the first frame to the first online estimate.
- covariance consistency of the final trajectory (`covariance.csv`, world axes) and of the
  incremental one (`covariance_incremental.csv`): mean NEES e^T S^-1 e of e = (dx, dy,
  wrap(dyaw)) over the poses (a consistent estimator gives 3), of the position alone (2), and the
  fraction of position errors inside the 2-sigma ellipse (1 - e^-2 = 86.5 %). The errors are
  the unaligned world-frame ones, as the covariance is in world axes.
- registration success top-k: per submap, its hypotheses ranked by probability (over all patches it
  was matched against); success@k if any of the first k lies within the translation and rotation
  thresholds of the ground-truth T_world_base at the submap time (strict <).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from meridian_torch.config import EvaluationConfig
from meridian_torch.geometry.planar import scalar_yaw_of, wrap_angle
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.atomic import write_text_atomic
from meridian_torch.io.results import (
    COVARIANCE_CSV,
    COVARIANCE_INCREMENTAL_CSV,
    METRICS_JSON,
    RunOutputs,
    read_covariances,
    read_outputs,
)

__all__ = [
    "CONSISTENT_NEES",
    "CONSISTENT_POSITION_NEES",
    "CONSISTENT_WITHIN_2SIGMA",
    "METRICS_JSON",
    "TrajectoryErrors",
    "associate",
    "covariance_consistency",
    "evaluate_run",
    "localization_metrics",
    "registration_success",
    "trajectory_errors",
]


def associate(
    est_times: np.ndarray, gt_times: np.ndarray, max_difference_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i_est, i_gt): each estimate with the nearest ground-truth time within the bound."""
    est_times, gt_times = np.asarray(est_times, np.float64), np.asarray(gt_times, np.float64)
    if len(gt_times) == 0 or len(est_times) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    j = np.clip(np.searchsorted(gt_times, est_times), 1, max(len(gt_times) - 1, 1))
    j = np.where(
        np.abs(gt_times[j - 1] - est_times) <= np.abs(gt_times[np.minimum(j, len(gt_times) - 1)] - est_times),
        j - 1,
        np.minimum(j, len(gt_times) - 1),
    )
    ok = np.abs(gt_times[j] - est_times) <= max_difference_s
    return np.flatnonzero(ok), j[ok]


@dataclass(frozen=True)
class TrajectoryErrors:
    times: np.ndarray  # (M,) estimate timestamps that have ground truth
    translation_m: np.ndarray  # (M,) 2D position error
    heading_rad: np.ndarray  # (M,) |wrap(yaw_est - yaw_gt)|
    distance_m: np.ndarray  # (M,) ground-truth path length from the ground truth's start

    def summary(self) -> dict[str, float | int | None]:
        n = len(self.times)
        if n == 0:
            return {
                "n": 0,
                "ate_rmse_m": None,
                "ate_mean_m": None,
                "ate_max_m": None,
                "heading_rmse_deg": None,
                "heading_mean_deg": None,
                "heading_max_deg": None,
            }
        h = np.degrees(self.heading_rad)
        return {
            "n": n,
            "ate_rmse_m": float(np.sqrt(np.mean(self.translation_m**2))),
            "ate_mean_m": float(self.translation_m.mean()),
            "ate_max_m": float(self.translation_m.max()),
            "heading_rmse_deg": float(np.sqrt(np.mean(h**2))),
            "heading_mean_deg": float(h.mean()),
            "heading_max_deg": float(h.max()),
        }


def _world_errors(
    est: Trajectory, gt: Trajectory, max_difference_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(i_est, i_gt, (M, 3) signed errors (dx, dy, wrap(dyaw)) in world axes, unaligned)."""
    i, j = associate(est.timestamps, gt.timestamps, max_difference_s)
    dxy = est.positions[i, :2] - gt.positions[j, :2]
    return i, j, np.c_[dxy, wrap_angle(est.yaws[i] - gt.yaws[j])]


def trajectory_errors(est: Trajectory, gt: Trajectory, max_difference_s: float = 0.01) -> TrajectoryErrors:
    """Per-pose errors of `est` against `gt` at the same timestamps (unaligned, 2D)."""
    i, j, e = _world_errors(est, gt, max_difference_s)
    return TrajectoryErrors(
        times=est.timestamps[i],
        translation_m=np.linalg.norm(e[:, :2], axis=1),
        heading_rad=np.abs(e[:, 2]),
        distance_m=gt.path_lengths()[j],
    )


CONSISTENT_NEES = 3.0  # E[e^T S^-1 e] for e ~ N(0, S) in 3 dimensions
CONSISTENT_POSITION_NEES = 2.0
CONSISTENT_WITHIN_2SIGMA = 1.0 - math.exp(-2.0)  # P(chi2 with 2 dof <= 2^2)


def covariance_consistency(
    est: Trajectory, covariance_xy_yaw: np.ndarray, gt: Trajectory, max_difference_s: float = 0.01
) -> dict[str, float | int | None]:
    """How well the per-pose covariances (N, 3, 3) of (x, y, yaw), world axes, of `est` describe its
    errors against `gt`: mean NEES (3 DoF, consistent: `CONSISTENT_NEES`), mean position NEES (x, y;
    `CONSISTENT_POSITION_NEES`) and the fraction of positions within Mahalanobis distance 2
    (`CONSISTENT_WITHIN_2SIGMA`), over `n` poses. Poses without ground truth within
    `max_difference_s` and poses whose covariance is non-finite or not positive definite are
    skipped and counted (`n_without_groundtruth`, `n_invalid_covariance`)."""
    cov = np.asarray(covariance_xy_yaw, dtype=np.float64)
    if cov.shape != (len(est), 3, 3):
        raise ValueError(f"covariance_xy_yaw: shape {cov.shape}, expected ({len(est)}, 3, 3) (one per pose)")
    i, _, e = _world_errors(est, gt, max_difference_s)
    cov = cov[i]
    valid = np.isfinite(cov).all(axis=(1, 2))
    sym = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    eig = np.zeros((len(cov), 3))
    eig[valid] = np.linalg.eigvalsh(sym[valid])
    # numerically singular as in numpy's matrix_rank: smallest eigenvalue within 3 eps of the largest
    valid &= eig[:, 0] > 3 * np.finfo(np.float64).eps * np.abs(eig[:, 2])
    counts = {
        "n": int(valid.sum()),
        "n_without_groundtruth": len(est) - len(i),
        "n_invalid_covariance": int((~valid).sum()),
    }
    if not valid.any():
        return counts | {"nees_mean": None, "position_nees_mean": None, "position_within_2sigma": None}
    e, sym = e[valid], sym[valid]
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(sym, e[:, :, None])[:, :, 0])
    position_nees = np.einsum("ni,ni->n", e[:, :2], np.linalg.solve(sym[:, :2, :2], e[:, :2, None])[:, :, 0])
    return counts | {
        "nees_mean": float(nees.mean()),
        "position_nees_mean": float(position_nees.mean()),
        "position_within_2sigma": float(np.mean(position_nees <= 4.0)),
    }


def registration_success(
    submap_times: np.ndarray,
    hypotheses_xy_yaw: list[np.ndarray],
    scores: list[np.ndarray],
    gt: Trajectory,
    *,
    top_k: list[int],
    translation_m: float,
    rotation_deg: float,
) -> dict[str, float | int]:
    """Fraction of submaps whose top-k hypotheses (by score) contain one within the thresholds.

    `hypotheses_xy_yaw[s]` (K_s, 3) are T_world_base (x, y, yaw) of submap s at `submap_times[s]`;
    submaps whose time the ground truth does not cover are skipped; a submap without hypotheses fails.
    """
    times = np.asarray(submap_times, np.float64)
    covered = (
        (times >= gt.timestamps[0]) & (times <= gt.timestamps[-1]) if len(gt) else np.zeros(len(times), bool)
    )
    out: dict[str, float | int] = {"n_submaps": int(covered.sum())}
    if not covered.any():
        return out | {f"top{k}": float("nan") for k in top_k}
    gt_poses = gt.interpolate(times[covered])
    hits = {k: 0 for k in top_k}
    for T_gt, hyp, score in zip(
        gt_poses,
        [h for h, c in zip(hypotheses_xy_yaw, covered) if c],
        [s for s, c in zip(scores, covered) if c],
    ):
        if len(hyp) == 0:
            continue
        order = np.argsort(-np.asarray(score), kind="stable")
        hyp = np.asarray(hyp)[order]
        ok = (np.linalg.norm(hyp[:, :2] - T_gt[:2, 3], axis=1) < translation_m) & (
            np.degrees(np.abs(wrap_angle(hyp[:, 2] - scalar_yaw_of(T_gt)))) < rotation_deg
        )
        for k in top_k:
            hits[k] += bool(ok[:k].any())
    return out | {f"top{k}": hits[k] / int(covered.sum()) for k in top_k}


def _gt_distance(gt: Trajectory, t0: float, t1: float) -> float | None:
    """Ground-truth path length between two times (None when the ground truth does not cover them)."""
    if not gt.covers(np.array([t0, t1])):
        return None
    inner = gt.timestamps[(gt.timestamps > t0) & (gt.timestamps < t1)]
    times = np.unique(np.concatenate([[t0], inner, [t1]]))
    return float(Trajectory(times, gt.interpolate(times)).path_lengths()[-1])


def localization_metrics(
    run: RunOutputs,
    gt: Trajectory,
    cfg: EvaluationConfig,
    final_covariance_xy_yaw: np.ndarray | None = None,
    incremental_covariance_xy_yaw: np.ndarray | None = None,
) -> dict[str, Any]:
    """Every metric of one run's outputs against the ground truth (T_world_base); with the final
    or incremental trajectory's (N, 3, 3) covariances also their consistency (`covariance_consistency`)."""
    s = run.summary
    metrics: dict[str, Any] = {
        "localized": bool(s["localized"]),
        "n_frames": int(s["n_frames"]),
        "n_submaps": int(s["n_submaps"]),
        "n_inliers": int(s["n_inliers"]),
    }
    metrics["final"] = (
        trajectory_errors(run.final, gt, cfg.max_time_difference_s).summary() if run.final else None
    )
    metrics["final_covariance_consistency"] = (
        covariance_consistency(run.final, final_covariance_xy_yaw, gt, cfg.max_time_difference_s)
        if run.final is not None and final_covariance_xy_yaw is not None
        else None
    )
    inc = run.incremental
    metrics["incremental"] = trajectory_errors(inc, gt, cfg.max_time_difference_s).summary() if inc else None
    metrics["incremental_covariance_consistency"] = (
        covariance_consistency(inc, incremental_covariance_xy_yaw, gt, cfg.max_time_difference_s)
        if inc is not None and incremental_covariance_xy_yaw is not None
        else None
    )
    n_inc = len(inc) if inc is not None else 0
    metrics["fraction_localized"] = n_inc / max(int(s["n_frames"]), 1)
    metrics["time_to_first_fix_s"] = metrics["distance_to_first_fix_m"] = None
    if inc is not None:
        t0, t_fix = float(s["first_frame_time"]), float(inc.timestamps[0])
        metrics["time_to_first_fix_s"] = t_fix - t0
        metrics["distance_to_first_fix_m"] = _gt_distance(gt, t0, t_fix)
    hyp = run.hypotheses
    registration: dict[str, Any] = {}
    for mode in sorted(set(hyp["mode"].tolist())) if len(hyp) else []:
        rows = hyp[hyp["mode"] == mode]
        submaps = np.unique(rows["submap_index"])
        times = np.array([rows["time"][rows["submap_index"] == i][0] for i in submaps])
        xyyaw = [
            np.stack([r["x"], r["y"], r["yaw"]], 1)
            for r in (rows[rows["submap_index"] == i] for i in submaps)
        ]
        prob = [rows["probability"][rows["submap_index"] == i] for i in submaps]
        registration[mode] = {
            f"{cfg.success_translation_m:g}m_{deg:g}deg": registration_success(
                times,
                xyyaw,
                prob,
                gt,
                top_k=cfg.success_top_k,
                translation_m=cfg.success_translation_m,
                rotation_deg=deg,
            )
            for deg in (cfg.success_rotation_deg, cfg.success_rotation_deg_loose)
        }
    metrics["registration_success"] = registration
    metrics["timings_s"] = s.get("timings_s", {})
    return metrics


def evaluate_run(
    out_dir: str | Path, groundtruth: Trajectory, cfg: EvaluationConfig | None = None
) -> dict[str, Any]:
    """Metrics of the run in `out_dir` against `groundtruth`; also written to `out_dir/metrics.json`."""
    cfg = cfg or EvaluationConfig()
    run = read_outputs(out_dir)

    def covariances(name: str, est: Trajectory | None) -> np.ndarray | None:
        path = Path(out_dir) / name
        return read_covariances(path, est) if est is not None and path.is_file() else None

    metrics = localization_metrics(
        run,
        groundtruth,
        cfg,
        covariances(COVARIANCE_CSV, run.final),
        covariances(COVARIANCE_INCREMENTAL_CSV, run.incremental),
    )
    write_text_atomic(Path(out_dir) / METRICS_JSON, json.dumps(metrics, indent=2) + "\n")
    return metrics

"""Trajectory and registration metrics (paper section IV).

- ATE: unaligned 2D RMSE of |xy_est - xy_gt| at the same timestamps (no alignment: both are in
  the world frame), also mean and max; heading error |wrap(yaw_est - yaw_gt)| RMSE, mean, max.
  Computed for the final trajectory and for the incremental (online) one over its frames.
- fraction of frames localized (frames with an online estimate / all frames), distance (ground
  truth path length) and time from the first frame to the first online estimate.
- registration success top-k: per submap, its hypotheses ranked by probability (over all patches it
  was matched against); success@k if any of the first k lies within the translation and rotation
  thresholds of the ground-truth T_world_base at the submap time (strict <).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from meridian_torch.config import EvaluationConfig
from meridian_torch.geometry.planar import scalar_yaw_of, wrap_angle
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.atomic import write_text_atomic
from meridian_torch.io.results import METRICS_JSON, RunOutputs, read_outputs

__all__ = [
    "METRICS_JSON",
    "TrajectoryErrors",
    "associate",
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


def trajectory_errors(est: Trajectory, gt: Trajectory, max_difference_s: float = 0.01) -> TrajectoryErrors:
    """Per-pose errors of `est` against `gt` at the same timestamps (unaligned, 2D)."""
    i, j = associate(est.timestamps, gt.timestamps, max_difference_s)
    dxy = est.positions[i, :2] - gt.positions[j, :2]
    return TrajectoryErrors(
        times=est.timestamps[i],
        translation_m=np.linalg.norm(dxy, axis=1),
        heading_rad=np.abs(wrap_angle(est.yaws[i] - gt.yaws[j])),
        distance_m=gt.path_lengths()[j],
    )


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


def localization_metrics(run: RunOutputs, gt: Trajectory, cfg: EvaluationConfig) -> dict[str, Any]:
    """Every metric of one run's outputs against the ground truth (T_world_base)."""
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
    inc = run.incremental
    metrics["incremental"] = trajectory_errors(inc, gt, cfg.max_time_difference_s).summary() if inc else None
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
    metrics = localization_metrics(read_outputs(out_dir), groundtruth, cfg)
    write_text_atomic(Path(out_dir) / METRICS_JSON, json.dumps(metrics, indent=2) + "\n")
    return metrics

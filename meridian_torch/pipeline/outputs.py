"""Writing a localization run's output folder (the files and their format: `io.results`),
atomically: every file through a temporary file and a rename, and optional outputs of an earlier
run in the same folder removed so that nothing stale survives."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from meridian_torch.backend.candidates import LoopClosureCandidates
from meridian_torch.backend.results import LocalizationResult
from meridian_torch.config import EvaluationConfig
from meridian_torch.geometry.planar import yaw_of
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.atomic import write_text_atomic
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.io.poses import write_tum
from meridian_torch.io.results import (
    COVARIANCE_COLUMNS,
    COVARIANCE_CSV,
    COVARIANCE_INCREMENTAL_CSV,
    FINAL_TUM,
    GEOJSON,
    HYPOTHESES_CSV,
    INCREMENTAL_TUM,
    LATLON_CSV,
    LOOP_CLOSURES_CSV,
    METRICS_JSON,
    SUBMAPS_CSV,
    SUMMARY_JSON,
    to_latlon,
)
from meridian_torch.pipeline.run import SequenceRun

__all__ = ["write_outputs", "write_run_folder"]


# Files a run writes only sometimes (when localized, with a CRS, with ground truth): a folder
# reused for another run must not keep the previous run's copies.
_OPTIONAL_OUTPUTS = (
    FINAL_TUM, INCREMENTAL_TUM, COVARIANCE_CSV, COVARIANCE_INCREMENTAL_CSV, LATLON_CSV, GEOJSON, METRICS_JSON
)


_CANDIDATE_COLUMNS = [
    "submap_index",
    "time",
    "patch_index",
    "x",
    "y",
    "yaw",
    "probability",
    "quality",
    "n_associations",
]


_POSE_NOTE = "x, y, yaw: SE(2) pose graph; z, roll, pitch: odometry"


def _csv(header: list[str], rows: list[list[object]]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buf.getvalue()


def _num(v: float) -> str:
    return repr(float(v))


def _covariance_csv(times: np.ndarray, covariance: np.ndarray) -> str:
    """(M,) times and (M, 3, 3) covariances of (x, y, yaw) as `covariance.csv` (io.results)."""
    c = covariance
    rows = [
        [f"{t:.9f}", *(_num(c[k, i, j]) for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))]
        for k, t in enumerate(times)
    ]
    return _csv(COVARIANCE_COLUMNS, rows)


def _candidate_rows(c: LoopClosureCandidates) -> list[list[object]]:
    T = c.T_world_base.numpy()
    yaw = yaw_of(T)
    return [
        [
            int(c.submap_index[k]),
            f"{float(c.time[k]):.9f}",
            int(c.patch_index[k]),
            _num(T[k, 0, 2]),
            _num(T[k, 1, 2]),
            _num(yaw[k]),
            _num(c.probability[k]),
            _num(c.quality[k]),
            int(c.n_associations[k]),
        ]
        for k in range(len(c))
    ]


def _geojson(
    final: Trajectory | None, incremental: Trajectory | None, inliers: LoopClosureCandidates, crs: str
) -> str:
    features = []
    for name, traj in (("final", final), ("incremental", incremental)):
        if traj is not None:
            latlon = to_latlon(traj.positions[:, :2], crs)
            features.append(
                {
                    "type": "Feature",
                    "properties": {
                        "name": f"{name} trajectory",
                        "t_start": float(traj.timestamps[0]),
                        "t_end": float(traj.timestamps[-1]),
                    },
                    "geometry": {"type": "LineString", "coordinates": latlon[:, ::-1].tolist()},
                }
            )
    if len(inliers):
        latlon = to_latlon(inliers.T_world_base[:, :2, 2].numpy(), crs)
        for k in range(len(inliers)):
            features.append(
                {
                    "type": "Feature",
                    "properties": {
                        "name": "loop closure",
                        "submap_index": int(inliers.submap_index[k]),
                        "time": float(inliers.time[k]),
                        "patch_index": int(inliers.patch_index[k]),
                    },
                    "geometry": {"type": "Point", "coordinates": latlon[k, ::-1].tolist()},
                }
            )
    return json.dumps({"type": "FeatureCollection", "features": features}) + "\n"


def write_outputs(
    out_dir: str | Path, result: LocalizationResult, *, crs: str | None = None
) -> dict[str, Path]:
    """Write every output of `result` into `out_dir`; returns {file name: path} of what was written.

    `crs` (the orthophoto's projected CRS, e.g. "EPSG:32632") adds the latitude/longitude outputs.
    Optional outputs of an earlier run in the same folder that this run does not write (e.g. its
    trajectory when this run is not localized, its metrics.json) are removed.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in _OPTIONAL_OUTPUTS:
        (out / name).unlink(missing_ok=True)
    written: dict[str, Path] = {}

    def text(name: str, content: str) -> None:
        write_text_atomic(out / name, content)
        written[name] = out / name

    final = result.final_trajectory
    incremental = result.incremental_trajectory
    if final is not None:
        write_tum(out / FINAL_TUM, final, comment=f"meridian-torch final T_world_base ({_POSE_NOTE})")
        written[FINAL_TUM] = out / FINAL_TUM
        if result.covariance is not None:
            text(COVARIANCE_CSV, _covariance_csv(result.frame_times, result.covariance))
    if incremental is not None:
        write_tum(
            out / INCREMENTAL_TUM,
            incremental,
            comment=f"meridian-torch online T_world_base from the global fix on ({_POSE_NOTE})",
        )
        written[INCREMENTAL_TUM] = out / INCREMENTAL_TUM
        if result.covariance_incremental is not None:
            online_cov = result.covariance_incremental[result.incremental_frames]
            text(COVARIANCE_INCREMENTAL_CSV, _covariance_csv(incremental.timestamps, online_cov))
    text(LOOP_CLOSURES_CSV, _csv(_CANDIDATE_COLUMNS, _candidate_rows(result.inliers)))
    hyp_rows = []
    for index in sorted(result.submap_hypotheses):
        mode = result.submap_matching_mode.get(index, "")
        hyp_rows += [[*row, mode] for row in _candidate_rows(result.submap_hypotheses[index])]
    hyp_rows += [[*row, "final_rematch"] for row in _candidate_rows(result.final_hypotheses)]
    text(HYPOTHESES_CSV, _csv(_CANDIDATE_COLUMNS + ["mode"], hyp_rows))
    text(
        SUBMAPS_CSV,
        _csv(
            [
                "submap_index",
                "time",
                "state",
                "n_patches",
                "n_hypotheses",
                "n_candidates",
                "n_inliers",
                "attempted",
                "fix_committed",
                "seconds",
                "fix_revoked",
                "fix_doubted",
            ],
            [
                [
                    e.submap_index,
                    f"{e.time:.9f}",
                    e.state,
                    e.n_patches,
                    e.n_hypotheses,
                    e.n_candidates,
                    e.n_inliers,
                    int(e.attempted),
                    int(e.fix_committed),
                    f"{e.seconds:.4f}",
                    int(e.fix_revoked),
                    int(e.fix_doubted),
                ]
                for e in result.events
            ],
        ),
    )
    summary = {
        "localized": result.localized,
        "rejected_because": result.rejected_because,
        "n_frames": len(result.frame_times),
        "first_frame_time": float(result.frame_times[0]),
        "last_frame_time": float(result.frame_times[-1]),
        "n_submaps": len(result.events),
        "n_inliers": len(result.inliers),
        "fix_submap_index": result.fix_submap_index,
        "fix_time": result.fix_time,
        "timings_s": result.timings,
        "crs": crs,
        "pose_note": _POSE_NOTE,
    }
    text(SUMMARY_JSON, json.dumps(summary, indent=2) + "\n")
    if crs is not None and final is not None:
        latlon = to_latlon(final.positions[:, :2], crs)
        text(
            LATLON_CSV,
            _csv(
                ["timestamp", "latitude", "longitude"],
                [[f"{t:.9f}", f"{la:.9f}", f"{lo:.9f}"] for t, (la, lo) in zip(final.timestamps, latlon)],
            ),
        )
    if crs is not None and (final is not None or incremental is not None):
        text(GEOJSON, _geojson(final, incremental, result.inliers, crs))
    return written


def write_run_folder(
    out_dir: str | Path,
    run: SequenceRun,
    *,
    crs: str | None,
    ortho: Orthophoto | None = None,
    groundtruth: Trajectory | None,
    evaluation: EvaluationConfig,
) -> tuple[dict | None, Path]:
    """Everything `localize` leaves in its output folder: the outputs, `metrics.json` when there
    is ground truth (`evaluation` settings), and the report. Returns (metrics or None, report path)."""
    from meridian_torch.evaluation.report import write_report
    from meridian_torch.evaluation.trajectory_metrics import evaluate_run

    write_outputs(out_dir, run.result, crs=crs)
    metrics = None
    if groundtruth is not None:
        metrics = evaluate_run(out_dir, groundtruth, evaluation)
    report = write_report(out_dir, stage_seconds=run.seconds, real_time_factor=run.real_time_factor,
                          peak_memory_mib=run.peak_memory_mib, metrics=metrics, ortho=ortho,
                          groundtruth=groundtruth, max_difference_s=evaluation.max_time_difference_s)
    return metrics, report

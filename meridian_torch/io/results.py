"""The output folder of a localization run: file names, format, and reading it back
(`pipeline.outputs` writes it).

Files in the output folder:
- `trajectory.tum`: final optimized T_world_base at every frame time (only when localized);
- `trajectory_incremental.tum`: the online estimate at each frame time from the fix on;
- `covariance.csv`: per frame of trajectory.tum, the marginal covariance of (x, y, yaw) in
  world-aligned axes (m^2, m rad, rad^2): `timestamp,xx,xy,xyaw,yy,yyaw,yawyaw`;
- `covariance_incremental.csv`: the same per frame of trajectory_incremental.tum (when the online
  updates computed covariances, `backend.covariance`): the online update's marginal at its last
  frame carried along the odometry to the frame;
- `loop_closures.csv`: the final inlier loop closures (measured T_world_base at the submap time);
- `hypotheses.csv`: every submap's candidates from its first matching (mode `place_recognition`
  before the fix, `rotation_prior` after it) and from the final pass's re-matching near the final
  trajectory (mode `final_rematch`), for registration metrics;
- `submaps.csv`: one row per processed submap (the localizer's events);
- `localization.json`: summary (localized, fix, counts, per-stage seconds, frame count);
- with a CRS: `trajectory_latlon.csv` (`timestamp,latitude,longitude`, WGS84) and
  `trajectory.geojson` (final and incremental LineStrings, loop closures as Points).
Poses: x, y, yaw from the SE(2) pose graph, z / roll / pitch from the odometry.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meridian_torch.errors import SequenceFormatError
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.poses import read_tum

__all__ = [
    "COVARIANCE_COLUMNS",
    "COVARIANCE_CSV",
    "COVARIANCE_INCREMENTAL_CSV",
    "FINAL_TUM",
    "GEOJSON",
    "HYPOTHESES_CSV",
    "INCREMENTAL_TUM",
    "LATLON_CSV",
    "LOOP_CLOSURES_CSV",
    "METRICS_JSON",
    "SUBMAPS_CSV",
    "SUMMARY_JSON",
    "RunOutputs",
    "read_covariances",
    "read_outputs",
    "to_latlon",
]

FINAL_TUM = "trajectory.tum"
INCREMENTAL_TUM = "trajectory_incremental.tum"
COVARIANCE_CSV = "covariance.csv"
COVARIANCE_INCREMENTAL_CSV = "covariance_incremental.csv"
COVARIANCE_COLUMNS = ["timestamp", "xx", "xy", "xyaw", "yy", "yyaw", "yawyaw"]  # both covariance files
LOOP_CLOSURES_CSV = "loop_closures.csv"
HYPOTHESES_CSV = "hypotheses.csv"
SUBMAPS_CSV = "submaps.csv"
SUMMARY_JSON = "localization.json"
LATLON_CSV = "trajectory_latlon.csv"
GEOJSON = "trajectory.geojson"
METRICS_JSON = "metrics.json"  # written by meridian_torch.evaluation from these outputs


def to_latlon(xy: np.ndarray, crs: str) -> np.ndarray:
    """(N, 2) world x, y in the projected `crs` -> (N, 2) WGS84 latitude, longitude (degrees)."""
    from rasterio.warp import transform

    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    lon, lat = transform(crs, "EPSG:4326", xy[:, 0].tolist(), xy[:, 1].tolist())
    return np.stack([np.asarray(lat), np.asarray(lon)], axis=1)


@dataclass(frozen=True)
class RunOutputs:
    """What `evaluate` needs from an output folder."""

    summary: dict
    final: Trajectory | None
    incremental: Trajectory | None
    loop_closures: np.ndarray  # structured rows of loop_closures.csv
    hypotheses: np.ndarray  # structured rows of hypotheses.csv


def _read_table(path: Path) -> np.ndarray:
    if not path.is_file():
        raise SequenceFormatError(f"{path}: missing (not a localization output folder?)")
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    names = rows[0]
    dtypes = [
        ("submap_index", "i8"),
        ("time", "f8"),
        ("patch_index", "i8"),
        ("x", "f8"),
        ("y", "f8"),
        ("yaw", "f8"),
        ("probability", "f8"),
        ("quality", "f8"),
        ("n_associations", "i8"),
        ("mode", "U32"),
    ]
    dtype = [d for d in dtypes if d[0] in names]
    order = [names.index(n) for n, _ in dtype]
    return np.array([tuple(r[i] for i in order) for r in rows[1:]], dtype=dtype)


def read_outputs(out_dir: str | Path) -> RunOutputs:
    """Read the folder written by `pipeline.outputs.write_outputs` (missing trajectories are None)."""
    out = Path(out_dir)
    if not (out / SUMMARY_JSON).is_file():
        raise SequenceFormatError(f"{out / SUMMARY_JSON}: missing (not a localization output folder?)")
    summary = json.loads((out / SUMMARY_JSON).read_text())
    final = read_tum(out / FINAL_TUM) if (out / FINAL_TUM).is_file() else None
    incremental = read_tum(out / INCREMENTAL_TUM) if (out / INCREMENTAL_TUM).is_file() else None
    return RunOutputs(
        summary, final, incremental, _read_table(out / LOOP_CLOSURES_CSV), _read_table(out / HYPOTHESES_CSV)
    )


def read_covariances(path: str | Path, est: Trajectory) -> np.ndarray:
    """(N, 3, 3) covariances of `est`'s poses from a `covariance.csv` or `covariance_incremental.csv`
    (one row per pose; `COVARIANCE_COLUMNS`)."""
    path = Path(path)
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows or rows[0] != COVARIANCE_COLUMNS:
        raise SequenceFormatError(f"{path}: header {rows[:1]}, expected {COVARIANCE_COLUMNS}")
    try:
        values = np.array([[float(v) for v in r] for r in rows[1:]], dtype=np.float64).reshape(-1, 7)
    except ValueError as exc:
        raise SequenceFormatError(f"{path}: a row is not 7 numbers ({exc})") from exc
    if len(values) != len(est) or not np.allclose(values[:, 0], est.timestamps, rtol=0, atol=1e-6):
        raise SequenceFormatError(
            f"{path}: {len(values)} rows whose timestamps do not match the {len(est)} poses of the trajectory"
        )
    xx, xy, xyaw, yy, yyaw, yawyaw = values[:, 1:].T
    return np.stack([np.c_[xx, xy, xyaw], np.c_[xy, yy, yyaw], np.c_[xyaw, yyaw, yawyaw]], axis=1)

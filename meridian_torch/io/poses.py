"""Pose files: TUM (`timestamp tx ty tz qx qy qz qw`) and KITTI (row-major 3x4 per line).

Readers are strict: every problem is reported as a SequenceFormatError naming the file,
the line number and what is wrong. `parse_tum` returns all problems instead of raising,
for `check_sequence`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from meridian_torch.errors import SequenceFormatError
from meridian_torch.geometry.se3 import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.atomic import write_text_atomic

__all__ = ["parse_tum", "read_tum", "write_tum", "read_kitti", "write_kitti"]

QUAT_NORM_TOL = 1e-3  # larger deviations mean a broken file, smaller ones are rounding
ROTATION_TOL = 1e-3  # max |R^T R - I| accepted (and then re-orthonormalised) in KITTI files
KITTI_DEFAULT_DT = 0.1  # KITTI odometry runs at 10 Hz

PathLike = str | os.PathLike[str]


def _numeric_rows(path: Path, ncols: int, what: str, problems: list[str]) -> tuple[list[int], np.ndarray]:
    """Line numbers and (M, ncols) values of the well-formed data lines; problems appended."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        problems.append(f"{path}: file not found")
        return [], np.zeros((0, ncols))
    except (OSError, UnicodeDecodeError) as e:
        problems.append(f"{path}: cannot read as text ({e})")
        return [], np.zeros((0, ncols))
    line_numbers: list[int] = []
    rows: list[list[float]] = []
    n_data = 0
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        n_data += 1
        parts = line.split()
        if len(parts) != ncols:
            problems.append(f"{path}: line {n}: expected {ncols} columns ({what}), got {len(parts)}")
            continue
        try:
            values = [float(p) for p in parts]
        except ValueError:
            bad = next(p for p in parts if not _is_float(p))
            problems.append(f"{path}: line {n}: not a number: {bad!r}")
            continue
        if not all(math.isfinite(v) for v in values):
            problems.append(f"{path}: line {n}: NaN or infinite value")
            continue
        line_numbers.append(n)
        rows.append(values)
    if n_data == 0:
        problems.append(f"{path}: empty file (no data lines)")
    return line_numbers, np.array(rows, dtype=np.float64).reshape(-1, ncols)


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _check_increasing(path: Path, times: np.ndarray, line_numbers: list[int], problems: list[str]) -> None:
    for k in np.flatnonzero(np.diff(times) <= 0):
        problems.append(
            f"{path}: line {line_numbers[k + 1]}: timestamp {times[k + 1]:.9f} not greater than "
            f"the previous one {times[k]:.9f} (line {line_numbers[k]}); timestamps must strictly increase"
        )


def parse_tum(path: PathLike) -> tuple[Trajectory | None, list[str]]:
    """Read a TUM file, collecting every problem; the trajectory is None if there is any.

    Quaternions whose norm deviates from 1 by at most 1e-3 are renormalised.
    """
    path = Path(path)
    problems: list[str] = []
    lines, rows = _numeric_rows(path, 8, "timestamp tx ty tz qx qy qz qw", problems)
    norms = np.linalg.norm(rows[:, 4:8], axis=1)
    for k in np.flatnonzero(np.abs(norms - 1.0) > QUAT_NORM_TOL):
        problems.append(
            f"{path}: line {lines[k]}: quaternion norm {norms[k]:.6g} is not 1 (tolerance {QUAT_NORM_TOL})"
        )
    _check_increasing(path, rows[:, 0], lines, problems)
    if problems:
        return None, problems
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = quat_xyzw_to_matrix(rows[:, 4:8])  # normalises the quaternion
    poses[:, :3, 3] = rows[:, 1:4]
    return Trajectory(rows[:, 0], poses), []


def read_tum(path: PathLike) -> Trajectory:
    """Read a TUM trajectory; raises SequenceFormatError on the first problem."""
    traj, problems = parse_tum(path)
    if problems:
        raise SequenceFormatError(problems[0])
    assert traj is not None
    return traj


def write_tum(path: PathLike, traj: Trajectory, comment: str | None = None) -> None:
    """Write `traj` as TUM atomically: `%.9f` timestamps, shortest exact repr for the rest."""
    lines = [f"# {c}" for c in comment.splitlines()] if comment else []
    lines.append("# timestamp tx ty tz qx qy qz qw")
    quats = matrix_to_quat_xyzw(traj.poses[:, :3, :3])
    for t, T, q in zip(traj.timestamps, traj.poses, quats):
        # repr() is the shortest text that reads back to the identical float64.
        values = " ".join(repr(float(v)) for v in (*T[:3, 3], *q))
        lines.append(f"{t:.9f} {values}")
    write_text_atomic(path, "\n".join(lines) + "\n")


def _read_times(path: Path) -> np.ndarray:
    problems: list[str] = []
    lines, rows = _numeric_rows(path, 1, "timestamp", problems)
    _check_increasing(path, rows[:, 0], lines, problems)
    if problems:
        raise SequenceFormatError(problems[0])
    return rows[:, 0]


def read_kitti(path: PathLike, timestamps: np.ndarray | PathLike | None = None) -> Trajectory:
    """Read a KITTI pose file (12 numbers per line: the row-major top 3x4 of T_frame_body).

    `timestamps` is either an array with one time per pose or the path of a KITTI times file
    (one number per line). Without it the poses are timed index * 0.1 s (KITTI's 10 Hz).
    Rotations off orthonormal by more than 1e-3 (or reflections) are errors; smaller
    deviations are projected back onto SO(3).
    """
    path = Path(path)
    problems: list[str] = []
    lines, rows = _numeric_rows(path, 12, "row-major 3x4 pose", problems)
    mats = rows.reshape(-1, 3, 4)
    R = mats[:, :, :3]
    err = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2), initial=0.0)
    det = np.linalg.det(R) if len(R) else np.zeros(0)
    for k in np.flatnonzero((err > ROTATION_TOL) | (det <= 0)):
        problems.append(
            f"{path}: line {lines[k]}: rotation is not orthonormal with det +1 "
            f"(max |R^T R - I| = {err[k]:.3g}, det = {det[k]:.6g}, tolerance {ROTATION_TOL})"
        )
    if problems:
        raise SequenceFormatError(problems[0])

    if timestamps is None:
        times = np.arange(len(mats)) * KITTI_DEFAULT_DT
    elif isinstance(timestamps, (str, os.PathLike)):
        times = _read_times(Path(timestamps))
        if len(times) != len(mats):
            raise SequenceFormatError(
                f"{timestamps}: {len(times)} timestamps but {path} has {len(mats)} poses"
            )
    else:
        times = np.asarray(timestamps, dtype=np.float64)
        if times.shape != (len(mats),):
            raise SequenceFormatError(f"{path}: {len(mats)} poses but {times.shape} timestamps given")
        if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
            raise SequenceFormatError(f"{path}: given timestamps must be finite and strictly increasing")

    U, _, Vt = np.linalg.svd(R)
    poses = np.tile(np.eye(4), (len(mats), 1, 1))
    poses[:, :3, :3] = U @ Vt  # nearest rotation; det > 0 was checked above
    poses[:, :3, 3] = mats[:, :, 3]
    return Trajectory(times, poses)


def write_kitti(path: PathLike, traj: Trajectory, times_path: PathLike | None = None) -> None:
    """Write `traj` as a KITTI pose file (and its times file if `times_path` is given), atomically."""
    rows = traj.poses[:, :3, :].reshape(len(traj), 12)
    write_text_atomic(path, "".join(" ".join(repr(float(v)) for v in r) + "\n" for r in rows))
    if times_path is not None:
        write_text_atomic(times_path, "".join(f"{t:.9f}\n" for t in traj.timestamps))

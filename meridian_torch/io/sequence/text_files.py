"""The sequence folder's text files besides camera.json: ground/frames.csv (the frames and their
images), whether ground/odometry.tum covers the frames without long gaps, and meta.json."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from meridian_torch.geometry.trajectory import Trajectory

__all__ = ["FRAMES_HEADER", "FrameTable", "check_covers", "odometry_gap_problems", "parse_frames", "parse_meta"]

FRAMES_HEADER = ("timestamp", "rgb", "depth")


class FrameTable(NamedTuple):
    times: np.ndarray  # (N,) seconds
    rgb: list[Path]
    depth: list[Path]
    lines: list[int]  # line of each frame in frames.csv, for messages


def parse_frames(path: Path, problems: list[str]) -> FrameTable | None:
    """The frames of frames.csv; None only if the file or its header is unusable."""
    n_before = len(problems)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        problems.append(f"{path}: file not found")
        return None
    except (OSError, UnicodeDecodeError) as e:
        problems.append(f"{path}: cannot read as text ({e})")
        return None
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or tuple(c.strip() for c in rows[0]) != FRAMES_HEADER:
        got = ",".join(rows[0]) if rows else "nothing (empty file)"
        problems.append(f"{path}: line 1: header must be `{','.join(FRAMES_HEADER)}`, got `{got}`")
        return None
    times: list[float] = []
    rgb: list[Path] = []
    depth: list[Path] = []
    lines: list[int] = []
    for n, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != 3:
            problems.append(f"{path}: line {n}: expected 3 columns (timestamp,rgb,depth), got {len(row)}")
            continue
        t_text, rgb_rel, depth_rel = (c.strip() for c in row)
        try:
            t = float(t_text)
        except ValueError:
            problems.append(f"{path}: line {n}: timestamp is not a number: {t_text!r}")
            continue
        if not math.isfinite(t):
            problems.append(f"{path}: line {n}: timestamp is NaN or infinite")
            continue
        bad = [p for p in (rgb_rel, depth_rel) if not p or Path(p).is_absolute()]
        if bad:
            problems.append(f"{path}: line {n}: image paths must be non-empty and relative to ground/")
            continue
        if times and t <= times[-1]:
            problems.append(
                f"{path}: line {n}: timestamp {t:.9f} not greater than the previous one {times[-1]:.9f} "
                f"(line {lines[-1]}); timestamps must strictly increase"
            )
        times.append(t)
        rgb.append(path.parent / rgb_rel)
        depth.append(path.parent / depth_rel)
        lines.append(n)
    if not times and len(problems) == n_before:
        problems.append(f"{path}: no frames (only the header)")
    # The well-formed rows are returned even if others are bad, so that check_sequence can
    # still check their images.
    return FrameTable(np.array(times), rgb, depth, lines)


def check_covers(odometry: Trajectory, times: np.ndarray, odom_path: Path, problems: list[str]) -> None:
    if not odometry.covers(times):
        problems.append(
            f"{odom_path}: odometry covers [{odometry.timestamps[0]:.9f}, {odometry.timestamps[-1]:.9f}] s "
            f"but the frames in frames.csv span [{times[0]:.9f}, {times[-1]:.9f}] s; it must cover them all"
        )


def odometry_gap_problems(odometry: Trajectory, times: np.ndarray, odom_path: Path, max_gap_s: float) -> list[str]:
    """One problem per gap longer than `max_gap_s` between odometry poses with frames inside it."""
    problems = []
    for t0, t1 in odometry.gaps_bridged(times, max_gap_s):
        n = int(((times > t0) & (times < t1)).sum())
        problems.append(
            f"{odom_path}: no pose between {t0:.9f} and {t1:.9f} s ({t1 - t0:.3f} s, longer than "
            f"ground_map.max_odometry_gap_s = {max_gap_s} s) but {n} frame(s) fall inside; their poses would be "
            "guessed: split the sequence there, fill the odometry, or raise the limit"
        )
    return problems


def parse_meta(path: Path, problems: list[str]) -> dict[str, Any]:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        problems.append(f"{path}: not valid JSON ({e})")
        return {}
    if not isinstance(meta, dict):
        problems.append(f"{path}: expected a JSON object")
        return {}
    return meta

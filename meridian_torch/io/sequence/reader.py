"""SequenceReader: a sequence folder validated on opening, its frames loaded when indexed."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from meridian_torch.errors import SequenceFormatError
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.ortho import Orthophoto, find_orthophoto, read_orthophoto
from meridian_torch.io.poses import PathLike, parse_tum
from meridian_torch.io.sequence.camera_json import parse_camera
from meridian_torch.io.sequence.images import load_frame_images
from meridian_torch.io.sequence.problems import raise_first
from meridian_torch.io.sequence.text_files import (
    check_covers,
    odometry_gap_problems,
    parse_frames,
    parse_meta,
)

__all__ = ["Frame", "SequenceReader"]


@dataclass(frozen=True)
class Frame:
    index: int
    timestamp: float
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres along the optical axis, 0 = no depth
    T_odom_base: np.ndarray  # (4, 4) float64, odometry interpolated at `timestamp`


class SequenceReader:
    """A validated sequence folder; frames (images) are loaded only when indexed.

    Opening checks camera.json, frames.csv, odometry.tum (and that it covers the frames),
    groundtruth.tum and meta.json if present, and that aerial/ holds an orthophoto; the first
    problem raises SequenceFormatError. Image problems raise when that frame is loaded.
    """

    def __init__(self, path: PathLike) -> None:
        self._root = Path(path)
        if not self._root.is_dir():
            raise SequenceFormatError(f"{self._root}: not a folder")
        ground = self._root / "ground"
        problems: list[str] = []
        camera = parse_camera(ground / "camera.json", problems)
        raise_first(problems)
        table = parse_frames(ground / "frames.csv", problems)
        raise_first(problems)
        odometry, problems = parse_tum(ground / "odometry.tum")
        raise_first(problems)
        assert camera is not None and table is not None and odometry is not None
        check_covers(odometry, table.times, ground / "odometry.tum", problems)
        raise_first(problems)
        groundtruth = None
        if (self._root / "groundtruth.tum").exists():
            groundtruth, problems = parse_tum(self._root / "groundtruth.tum")
            raise_first(problems)
        meta = parse_meta(self._root / "meta.json", problems) if (self._root / "meta.json").exists() else {}
        raise_first(problems)
        self._ortho_path = find_orthophoto(self._root / "aerial")
        self._camera = camera
        self._table = table
        self._odometry = odometry
        self._groundtruth = groundtruth
        self._meta = meta
        self._T_odom_base = odometry.interpolate(table.times)
        self._ortho: Orthophoto | None = None
        for a in (self._table.times, self._T_odom_base):
            a.setflags(write=False)  # shared with callers

    @property
    def path(self) -> Path:
        return self._root

    @property
    def camera(self) -> CameraModel:
        return self._camera

    @property
    def frame_times(self) -> np.ndarray:
        """(N,) frame timestamps in seconds (read-only)."""
        return self._table.times

    @property
    def T_odom_base(self) -> np.ndarray:
        """(N, 4, 4) odometry interpolated at every frame time (read-only)."""
        return self._T_odom_base

    @property
    def odometry(self) -> Trajectory:
        """T_odom_base as recorded in ground/odometry.tum."""
        return self._odometry

    def require_odometry_without_gaps(self, max_gap_s: float, n_frames: int | None = None) -> None:
        """Raise SequenceFormatError if the pose of any of the first `n_frames` frames (default all)
        would be interpolated across a gap longer than `max_gap_s` between odometry poses."""
        problems = odometry_gap_problems(self._odometry, self._table.times[:n_frames],
                                         self._root / "ground" / "odometry.tum", max_gap_s)
        if problems:
            more = f" (and {len(problems) - 1} more such gaps)" if len(problems) > 1 else ""
            raise SequenceFormatError(problems[0] + more)

    @property
    def groundtruth(self) -> Trajectory | None:
        """T_world_base from groundtruth.tum, or None if the sequence has none."""
        return self._groundtruth

    @property
    def meta(self) -> dict[str, Any]:
        """Contents of meta.json ({} if absent)."""
        return self._meta

    def ortho(self) -> Orthophoto:
        """The aerial orthophoto, read on first call and then cached."""
        if self._ortho is None:
            self._ortho = read_orthophoto(self._ortho_path)
        return self._ortho

    def __len__(self) -> int:
        return len(self._table.times)

    def __getitem__(self, index: int) -> Frame:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for a sequence of {n} frames")
        i = index % n
        table = self._table
        rgb, depth = load_frame_images(table.rgb[i], table.depth[i], table.lines[i], self._camera)
        return Frame(i, float(self._table.times[i]), rgb, depth, self._T_odom_base[i].copy())

    def __iter__(self) -> Iterator[Frame]:
        return (self[i] for i in range(len(self)))

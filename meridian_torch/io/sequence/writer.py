"""SequenceWriter: a sequence folder written frame by frame into a temporary folder that replaces
the destination only when complete."""

from __future__ import annotations

import json
import math
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from meridian_torch.errors import SequenceFormatError
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.atomic import atomic_directory, write_text_atomic
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.ortho import Orthophoto, write_orthophoto
from meridian_torch.io.poses import PathLike, write_tum
from meridian_torch.io.sequence.camera_json import validated_camera_dict
from meridian_torch.io.sequence.problems import raise_first
from meridian_torch.io.sequence.text_files import FRAMES_HEADER, check_covers

__all__ = ["SequenceWriter"]

_TIME_DECIMALS = 9  # timestamps are stored to the nanosecond


class SequenceWriter:
    """Write a sequence folder atomically: everything goes to a hidden temporary sibling that
    is renamed to `path` by close() (or on leaving a `with` block without an exception).

    On an exception inside the `with` block, or if close() finds the sequence incomplete,
    the temporary folder is deleted and `path` is left as it was.
    """

    def __init__(self, path: PathLike, camera: CameraModel, overwrite: bool = False) -> None:
        self._path = Path(path)
        self._camera_json = validated_camera_dict(camera)
        self._camera = camera
        self.check_target(self._path, overwrite)
        self._stack = ExitStack()
        self._tmp = self._stack.enter_context(atomic_directory(self._path, overwrite=overwrite))
        for sub in ("ground/rgb", "ground/depth", "aerial"):
            (self._tmp / sub).mkdir(parents=True)
        self._times: list[float] = []
        self._odometry: Trajectory | None = None
        self._groundtruth: Trajectory | None = None
        self._ortho: Orthophoto | None = None
        self._meta: dict[str, Any] | None = None
        self._closed = False

    @staticmethod
    def check_target(path: PathLike, overwrite: bool) -> None:
        """Refuse an existing `path` unless `overwrite`: callers check before rendering or
        converting, so that the refusal does not come after the work."""
        if Path(path).exists() and not overwrite:
            raise SequenceFormatError(f"{path}: already exists; pass --overwrite (overwrite=True in Python) to replace it")

    @property
    def path(self) -> Path:
        """Final location of the sequence."""
        return self._path

    @property
    def extra_dir(self) -> Path:
        """Root of the temporary sequence folder: files written below it (e.g. extra_dir / "sim")
        before close() are committed together with the sequence."""
        self._require_open()
        return self._tmp

    def __len__(self) -> int:
        return len(self._times)

    def _require_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"SequenceWriter for {self._path} is already closed")

    def add_frame(self, timestamp: float, rgb: np.ndarray, depth: np.ndarray) -> int:
        """Write frame `len(self)`: rgb (H, W, 3) uint8, depth (H, W) metres (<= 0 or non-finite = none).

        Timestamps are stored to the nanosecond and must strictly increase. Depth is saved as
        round(depth * depth_scale) in a 16-bit PNG; values beyond 65535 become 0 (no depth).
        Returns the frame index.
        """
        self._require_open()
        t = round(float(timestamp), _TIME_DECIMALS)
        if not math.isfinite(t):
            raise SequenceFormatError(f"frame {len(self)}: timestamp {timestamp} is not finite")
        if self._times and t <= self._times[-1]:
            raise SequenceFormatError(
                f"frame {len(self)}: timestamp {t:.9f} not greater than the previous one "
                f"{self._times[-1]:.9f}"
            )
        h, w = self._camera.height, self._camera.width
        rgb = np.asarray(rgb)
        depth = np.asarray(depth)
        if rgb.shape != (h, w, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be ({h}, {w}, 3) uint8 per camera.json, got {rgb.shape} {rgb.dtype}")
        if depth.shape != (h, w) or not np.issubdtype(depth.dtype, np.floating):
            raise ValueError(
                f"depth must be ({h}, {w}) float metres per camera.json, got {depth.shape} {depth.dtype}"
            )
        scaled = depth.astype(np.float64) * self._camera.depth_scale
        units = np.rint(np.where(np.isfinite(scaled) & (scaled > 0), scaled, 0.0))
        units[units > np.iinfo(np.uint16).max] = 0  # unrepresentable: "no depth" beats a wrong value
        index = len(self._times)
        name = f"{index:06d}.png"
        for sub, image in (("rgb", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)), ("depth", units.astype(np.uint16))):
            if not cv2.imwrite(str(self._tmp / "ground" / sub / name), image):
                raise OSError(f"cannot write {self._tmp / 'ground' / sub / name}")
        self._times.append(t)
        return index

    def set_odometry(self, traj: Trajectory) -> None:
        """T_odom_base at any rate; must cover the frame timestamps by close()."""
        self._require_open()
        self._odometry = traj

    def set_groundtruth(self, traj: Trajectory) -> None:
        """T_world_base, for evaluation only."""
        self._require_open()
        self._groundtruth = traj

    def set_orthophoto(self, ortho: Orthophoto) -> None:
        self._require_open()
        self._ortho = ortho

    def set_meta(self, meta: dict[str, Any]) -> None:
        """Free-form JSON-serialisable metadata, e.g. {"name": ..., "source": ..., "notes": ...}."""
        self._require_open()
        json.dumps(meta)  # fail now, not at close(), if it is not serialisable
        self._meta = dict(meta)

    def _write_all(self) -> None:
        if not self._times:
            raise SequenceFormatError(f"{self._path}: no frames added")
        if self._odometry is None:
            raise SequenceFormatError(f"{self._path}: odometry missing (call set_odometry)")
        if self._ortho is None:
            raise SequenceFormatError(f"{self._path}: orthophoto missing (call set_orthophoto)")
        times = np.array(self._times)
        # Compare at the stored (nanosecond) precision, as a reader will.
        odom_stored = Trajectory(np.round(self._odometry.timestamps, _TIME_DECIMALS), self._odometry.poses)
        problems: list[str] = []
        check_covers(odom_stored, times, self._path / "ground" / "odometry.tum", problems)
        raise_first(problems)
        ground = self._tmp / "ground"
        write_text_atomic(ground / "camera.json", json.dumps(self._camera_json, indent=1) + "\n")
        rows = [",".join(FRAMES_HEADER)]
        rows += [f"{t:.9f},rgb/{i:06d}.png,depth/{i:06d}.png" for i, t in enumerate(self._times)]
        write_text_atomic(ground / "frames.csv", "\n".join(rows) + "\n")
        write_tum(ground / "odometry.tum", self._odometry, comment="T_odom_base")
        if self._groundtruth is not None:
            write_tum(self._tmp / "groundtruth.tum", self._groundtruth, comment="T_world_base")
        if self._meta is not None:
            write_text_atomic(self._tmp / "meta.json", json.dumps(self._meta, indent=1) + "\n")
        write_orthophoto(self._tmp / "aerial", self._ortho)

    def close(self) -> None:
        """Write the remaining files and move the sequence into place (no-op if already closed)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._write_all()
        except BaseException:
            self._stack.__exit__(*sys.exc_info())  # deletes the temporary folder
            raise
        self._stack.close()  # renames the temporary folder to `path`

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        elif not self._closed:
            self._closed = True
            self._stack.__exit__(exc_type, exc, tb)

"""Sequence folders (README, Formats): strict reader, whole-folder checker and atomic writer."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import sys
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from meridian_torch.errors import SequenceFormatError
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.atomic import atomic_directory, write_text_atomic
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.ortho import (
    Orthophoto,
    check_orthophoto,
    find_orthophoto,
    read_orthophoto,
    write_orthophoto,
)
from meridian_torch.io.poses import parse_tum, write_tum

__all__ = ["Frame", "read_camera", "SequenceReader", "SequenceWriter", "check_sequence"]

CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "depth_scale", "T_base_camera")
FRAMES_HEADER = ("timestamp", "rgb", "depth")
RIGID_TOL = 1e-3  # max |R^T R - I| of T_base_camera; smaller errors are re-orthonormalised
_RGB_MODES = ("RGB", "RGBA")  # alpha, if any, is dropped
_DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I")  # how Pillow opens 16-bit greyscale PNGs
_TIME_DECIMALS = 9  # timestamps are stored to the nanosecond

PathLike = str | os.PathLike[str]


@dataclass(frozen=True)
class Frame:
    index: int
    timestamp: float
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres along the optical axis, 0 = no depth
    T_odom_base: np.ndarray  # (4, 4) float64, odometry interpolated at `timestamp`


def _raise_first(problems: list[str]) -> None:
    if problems:
        raise SequenceFormatError(problems[0])


def _is_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# ---------------------------------------------------------------------------------- camera


def _camera_from_dict(data: object, where: str, problems: list[str]) -> CameraModel | None:
    n_before = len(problems)
    if not isinstance(data, dict):
        problems.append(f"{where}: expected a JSON object with keys {', '.join(CAMERA_KEYS)}")
        return None
    for key in data:
        if key not in CAMERA_KEYS:
            problems.append(f"{where}: unknown key {key!r} (allowed: {', '.join(CAMERA_KEYS)})")
    for key in CAMERA_KEYS:
        if key not in data:
            problems.append(f"{where}: missing key {key!r}")
    for key in ("width", "height"):
        v = data.get(key)
        if key in data and not (isinstance(v, int) and not isinstance(v, bool) and v > 0):
            problems.append(f"{where}: key {key!r} must be a positive integer, got {v!r}")
    for key in ("fx", "fy", "depth_scale"):
        v = data.get(key)
        if key in data and not (_is_number(v) and v > 0):
            problems.append(f"{where}: key {key!r} must be a finite number > 0, got {v!r}")
    for key in ("cx", "cy"):
        v = data.get(key)
        if key in data and not _is_number(v):
            problems.append(f"{where}: key {key!r} must be a finite number, got {v!r}")
    T = _rigid_from_json(data.get("T_base_camera"), where, problems) if "T_base_camera" in data else None
    if len(problems) > n_before or T is None:
        return None
    return CameraModel(
        width=data["width"], height=data["height"], fx=float(data["fx"]), fy=float(data["fy"]),
        cx=float(data["cx"]), cy=float(data["cy"]), depth_scale=float(data["depth_scale"]), T_base_camera=T,
    )


def _rigid_from_json(value: object, where: str, problems: list[str]) -> np.ndarray | None:
    if not (
        isinstance(value, list) and len(value) == 4
        and all(isinstance(r, list) and len(r) == 4 and all(_is_number(v) for v in r) for r in value)
    ):
        problems.append(f"{where}: key 'T_base_camera' must be a 4x4 list of finite numbers (row-major)")
        return None
    T = np.array(value, dtype=np.float64)
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-9 or err > RIGID_TOL or np.linalg.det(R) <= 0:
        problems.append(
            f"{where}: key 'T_base_camera' is not a rigid transform (bottom row {T[3].tolist()}, "
            f"max |R^T R - I| = {err:.3g}, tolerance {RIGID_TOL}, det must be +1)"
        )
        return None
    U, _, Vt = np.linalg.svd(R)
    T[:3, :3] = U @ Vt
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return T


def _parse_camera(path: Path, problems: list[str]) -> CameraModel | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        problems.append(f"{path}: file not found")
        return None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        problems.append(f"{path}: not valid JSON ({e})")
        return None
    return _camera_from_dict(data, str(path), problems)


def _camera_to_dict(camera: CameraModel) -> dict[str, Any]:
    return {
        "width": int(camera.width), "height": int(camera.height),
        "fx": float(camera.fx), "fy": float(camera.fy), "cx": float(camera.cx), "cy": float(camera.cy),
        "depth_scale": float(camera.depth_scale),
        "T_base_camera": np.asarray(camera.T_base_camera, dtype=np.float64).tolist(),
    }


def read_camera(path: PathLike) -> CameraModel:
    """Read ground/camera.json; SequenceFormatError for missing/unknown keys or invalid values."""
    problems: list[str] = []
    camera = _parse_camera(Path(path), problems)
    _raise_first(problems)
    assert camera is not None
    return camera


def _validated_camera_dict(camera: CameraModel) -> dict[str, Any]:
    data = _camera_to_dict(camera)
    problems: list[str] = []
    _camera_from_dict(data, "camera", problems)
    if problems:
        raise ValueError(problems[0])
    return data


# ---------------------------------------------------------------------------------- frames.csv


class _FrameTable(NamedTuple):
    times: np.ndarray  # (N,) seconds
    rgb: list[Path]
    depth: list[Path]
    lines: list[int]  # line of each frame in frames.csv, for messages


def _parse_frames(path: Path, problems: list[str]) -> _FrameTable | None:
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
    return _FrameTable(np.array(times), rgb, depth, lines)


def _check_covers(odometry: Trajectory, times: np.ndarray, odom_path: Path, problems: list[str]) -> None:
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


def _parse_meta(path: Path, problems: list[str]) -> dict[str, Any]:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        problems.append(f"{path}: not valid JSON ({e})")
        return {}
    if not isinstance(meta, dict):
        problems.append(f"{path}: expected a JSON object")
        return {}
    return meta


# ---------------------------------------------------------------------------------- images


def _open_image(path: Path, line: int, problems: list[str]) -> Image.Image | None:
    """Open (header only) an image listed on `line` of frames.csv."""
    try:
        return Image.open(path)
    except FileNotFoundError:
        problems.append(f"{path}: file not found (listed in frames.csv line {line})")
    except (UnidentifiedImageError, OSError) as e:
        problems.append(f"{path}: not a readable image ({e})")
    return None


def _decode(img: Image.Image, path: Path, problems: list[str]) -> None:
    """Decode the whole image: truncated or corrupt data shows only here, not in the header."""
    try:
        img.load()
    except (OSError, SyntaxError, ValueError) as e:
        problems.append(f"{path}: image data cannot be decoded ({e})")


def _check_size(img: Image.Image, path: Path, camera: CameraModel | None, problems: list[str]) -> None:
    if camera is not None and img.size != (camera.width, camera.height):
        problems.append(
            f"{path}: image is {img.size[0]}x{img.size[1]} but camera.json says "
            f"{camera.width}x{camera.height}"
        )


def _check_rgb(img: Image.Image, path: Path, camera: CameraModel | None, problems: list[str]) -> None:
    if img.format not in ("PNG", "JPEG"):
        problems.append(f"{path}: {img.format} image; RGB frames must be PNG or JPEG")
    elif img.mode not in _RGB_MODES:
        problems.append(f"{path}: image mode {img.mode}; RGB frames must be 8-bit RGB")
    _check_size(img, path, camera, problems)


def _check_depth(img: Image.Image, path: Path, camera: CameraModel | None, problems: list[str]) -> None:
    if img.format != "PNG":
        problems.append(f"{path}: {img.format} image; depth must be a 16-bit PNG")
    elif img.mode in ("L", "P", "1"):
        problems.append(
            f"{path}: 8-bit depth image; depth must be a 16-bit greyscale PNG (value = metres * depth_scale)"
        )
    elif img.mode not in _DEPTH_MODES:
        problems.append(f"{path}: image mode {img.mode}; depth must be a 16-bit greyscale PNG")
    _check_size(img, path, camera, problems)


def _load_frame_images(
    rgb_path: Path, depth_path: Path, line: int, camera: CameraModel
) -> tuple[np.ndarray, np.ndarray]:
    problems: list[str] = []
    rgb_img = _open_image(rgb_path, line, problems)
    _raise_first(problems)
    assert rgb_img is not None
    with rgb_img:
        _check_rgb(rgb_img, rgb_path, camera, problems)
        _raise_first(problems)
        try:
            rgb = np.array(rgb_img.convert("RGB"))  # a writable copy
        except OSError as e:
            raise SequenceFormatError(f"{rgb_path}: cannot decode image ({e})") from e
    depth_img = _open_image(depth_path, line, problems)
    _raise_first(problems)
    assert depth_img is not None
    with depth_img:
        _check_depth(depth_img, depth_path, camera, problems)
        _raise_first(problems)
        try:
            raw = np.asarray(depth_img)
        except OSError as e:
            raise SequenceFormatError(f"{depth_path}: cannot decode image ({e})") from e
    depth = (raw.astype(np.float64) / camera.depth_scale).astype(np.float32)
    return rgb, depth


# ---------------------------------------------------------------------------------- reader


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
        camera = _parse_camera(ground / "camera.json", problems)
        _raise_first(problems)
        table = _parse_frames(ground / "frames.csv", problems)
        _raise_first(problems)
        odometry, problems = parse_tum(ground / "odometry.tum")
        _raise_first(problems)
        assert camera is not None and table is not None and odometry is not None
        _check_covers(odometry, table.times, ground / "odometry.tum", problems)
        _raise_first(problems)
        groundtruth = None
        if (self._root / "groundtruth.tum").exists():
            groundtruth, problems = parse_tum(self._root / "groundtruth.tum")
            _raise_first(problems)
        meta = _parse_meta(self._root / "meta.json", problems) if (self._root / "meta.json").exists() else {}
        _raise_first(problems)
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
        rgb, depth = _load_frame_images(table.rgb[i], table.depth[i], table.lines[i], self._camera)
        return Frame(i, float(self._table.times[i]), rgb, depth, self._T_odom_base[i].copy())

    def __iter__(self) -> Iterator[Frame]:
        return (self[i] for i in range(len(self)))


# ---------------------------------------------------------------------------------- checker


def check_sequence(path: PathLike, max_odometry_gap_s: float | None = None, *, quick: bool = False) -> list[str]:
    """Every problem of a sequence folder, each naming its file; an empty list means valid.

    `max_odometry_gap_s` (default: the config default) also reports frames inside longer gaps
    between odometry poses. Every image is decoded (a truncated file is found here, not at its
    frame in the middle of a run); `quick` reads the headers only.

    Unlike SequenceReader this also checks every listed image (existence, format, bit depth,
    size vs camera.json, from the headers only) and the orthophoto.
    """
    root = Path(path)
    if not root.is_dir():
        return [f"{root}: not a folder"]
    ground = root / "ground"
    problems: list[str] = []
    if not ground.is_dir():
        problems.append(f"{ground}: folder missing")
    camera = _parse_camera(ground / "camera.json", problems)
    table = _parse_frames(ground / "frames.csv", problems)
    if table is not None:
        for line, rgb_path, depth_path in zip(table.lines, table.rgb, table.depth):
            for img_path, check in ((rgb_path, _check_rgb), (depth_path, _check_depth)):
                img = _open_image(img_path, line, problems)
                if img is not None:
                    with img:
                        check(img, img_path, camera, problems)
                        if not quick:
                            _decode(img, img_path, problems)
    odometry, odom_problems = parse_tum(ground / "odometry.tum")
    problems += odom_problems
    if odometry is not None and table is not None and len(table.times):
        _check_covers(odometry, table.times, ground / "odometry.tum", problems)
        if max_odometry_gap_s is None:
            from meridian_torch.config import GroundMapConfig

            max_odometry_gap_s = GroundMapConfig().max_odometry_gap_s
        problems += odometry_gap_problems(odometry, table.times, ground / "odometry.tum", max_odometry_gap_s)
    if (root / "groundtruth.tum").exists():
        problems += parse_tum(root / "groundtruth.tum")[1]
    if (root / "meta.json").exists():
        _parse_meta(root / "meta.json", problems)
    problems += check_orthophoto(root / "aerial")
    return problems


# ---------------------------------------------------------------------------------- writer


class SequenceWriter:
    """Write a sequence folder atomically: everything goes to a hidden temporary sibling that
    is renamed to `path` by close() (or on leaving a `with` block without an exception).

    On an exception inside the `with` block, or if close() finds the sequence incomplete,
    the temporary folder is deleted and `path` is left as it was.
    """

    def __init__(self, path: PathLike, camera: CameraModel, overwrite: bool = False) -> None:
        self._path = Path(path)
        self._camera_json = _validated_camera_dict(camera)
        self._camera = camera
        if self._path.exists() and not overwrite:
            raise SequenceFormatError(f"{self._path}: already exists (pass overwrite=True to replace it)")
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
        _check_covers(odom_stored, times, self._path / "ground" / "odometry.tum", problems)
        _raise_first(problems)
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

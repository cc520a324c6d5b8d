"""ground/camera.json: the pinhole camera and where it sits on the robot, parsed strictly (every
missing or unknown key and invalid value is a problem) and serialised."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from meridian_torch.io.camera import CameraModel
from meridian_torch.io.poses import PathLike
from meridian_torch.io.sequence.problems import raise_first

__all__ = ["CAMERA_KEYS", "RIGID_TOL", "parse_camera", "read_camera", "validated_camera_dict"]

CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "depth_scale", "T_base_camera")
RIGID_TOL = 1e-3  # max |R^T R - I| of T_base_camera; smaller errors are re-orthonormalised


def _is_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


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


def parse_camera(path: Path, problems: list[str]) -> CameraModel | None:
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
    camera = parse_camera(Path(path), problems)
    raise_first(problems)
    assert camera is not None
    return camera


def validated_camera_dict(camera: CameraModel) -> dict[str, Any]:
    data = _camera_to_dict(camera)
    problems: list[str] = []
    _camera_from_dict(data, "camera", problems)
    if problems:
        raise ValueError(problems[0])
    return data

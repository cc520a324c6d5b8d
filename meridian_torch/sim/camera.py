"""The simulated camera: a pinhole model with square pixels and its mount on the robot base, from the config."""

from __future__ import annotations

import math

import numpy as np

from meridian_torch.config.sim import CameraConfig
from meridian_torch.io.camera import CameraModel

__all__ = ["camera_model_from_config", "R_BASE_OPTICAL"]

# Columns are the optical axes (x right, y down, z forward) expressed in the base frame (x forward, y left, z up).
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_model_from_config(cfg: CameraConfig) -> CameraModel:
    """Pinhole model of `cfg`: square pixels from the horizontal FOV, principal point at the image centre.

    Pixel centres are at integer coordinates (OpenCV), so the centre is ((W-1)/2, (H-1)/2).
    The mount rotation is roll-pitch-yaw about the base axes, R = Rz(yaw) Ry(pitch) Rx(roll);
    a positive rotation about the base's y (left) axis turns the forward axis down, so
    positive pitch looks down as the config documents.
    """
    f = 0.5 * cfg.width / math.tan(math.radians(cfg.hfov_deg) / 2.0)
    roll, pitch, yaw = (math.radians(v) for v in cfg.mount_rpy_deg)
    T = np.eye(4)
    T[:3, :3] = _rot_z(yaw) @ _rot_y(pitch) @ _rot_x(roll) @ R_BASE_OPTICAL
    T[:3, 3] = cfg.mount_xyz
    return CameraModel(
        width=cfg.width,
        height=cfg.height,
        fx=f,
        fy=f,
        cx=(cfg.width - 1) / 2.0,
        cy=(cfg.height - 1) / 2.0,
        depth_scale=cfg.depth_scale,
        T_base_camera=T,
    )

"""Pinhole RGB-D camera model of a sequence folder (ground/camera.json)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CameraModel"]


@dataclass(frozen=True)
class CameraModel:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float  # depth PNG units per metre
    T_base_camera: np.ndarray  # (4, 4) maps camera (optical) frame points into the base frame

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

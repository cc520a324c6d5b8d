"""Planar (x, y, yaw) helpers in numpy float64: angle wrapping, the yaw of a pose, SE(2) matrices.

wrap_angle, yaw_of and se2_from_se3 carry the names of their torch versions in `geometry.se2`;
they are not interchangeable bit for bit: torch's and numpy's cos, sin and atan2 round differently.
Poses are (..., 3, 3) SE(2) or (..., 4, 4) SE(3) matrices `T_a_b`; angles are radians,
counter-clockwise.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["wrap_angle", "yaw_of", "scalar_yaw_of", "se2_from_xy_yaw", "se2_from_se3"]


def wrap_angle(a):
    """Wrap angles (arrays or Python floats) into [-pi, pi); by rounding, an input a hair below
    -pi, -3pi, ... comes out as +pi."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def yaw_of(T: np.ndarray) -> np.ndarray:
    """Heading of the body x axis projected on the x-y plane, (..., 4, 4) -> (...,).

    Reads only the rotation's first column, so (..., 3, 3) SE(2) poses work too.
    """
    T = np.asarray(T, dtype=np.float64)
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def scalar_yaw_of(T) -> float:
    """`yaw_of` of one pose (numpy or torch) as a Python float, with math.atan2.

    Not `float(yaw_of(T))`: numpy's arctan2 runs SIMD code on some CPUs (AVX-512) that rounds
    differently from the C library's atan2 in about one case in ten.
    """
    return math.atan2(float(T[1, 0]), float(T[0, 0]))


def se2_from_xy_yaw(x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(...,) x, y and yaw -> (..., 3, 3) SE(2) matrices (float64)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.zeros(np.shape(yaw) + (3, 3))
    T[..., 0, 0], T[..., 0, 1], T[..., 0, 2] = c, -s, x
    T[..., 1, 0], T[..., 1, 1], T[..., 1, 2] = s, c, y
    T[..., 2, 2] = 1.0
    return T


def se2_from_se3(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) poses -> (..., 3, 3) SE(2): x, y and the yaw of the body x axis."""
    T = np.asarray(T, dtype=np.float64)
    return se2_from_xy_yaw(T[..., 0, 3], T[..., 1, 3], yaw_of(T))

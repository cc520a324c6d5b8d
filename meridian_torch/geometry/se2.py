"""Batched SE(2) and planar angle helpers on torch tensors.

Poses are 3x3 homogeneous matrices `T_a_b` of shape (..., 3, 3) mapping 2D points from
frame b into frame a: p_a = R p_b + t. Angles are radians, counter-clockwise (right-handed
frames). Device and dtype always follow the inputs. `geometry.planar` holds the numpy
wrap_angle, yaw_of and se2_from_se3 (they round differently: not interchangeable bit for bit).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from meridian_torch.geometry import planar

__all__ = [
    "wrap_angle",
    "wrap_line_angle",
    "line_angle_between",
    "yaw_of",
    "rotation_matrix",
    "se2_matrix",
    "se2_from_se3",
    "se2_compose",
    "se2_inverse",
    "se2_apply",
]


def wrap_angle(theta: torch.Tensor) -> torch.Tensor:
    """Wrap angles into [-pi, pi); by rounding, an input a hair below -pi, -3pi, ... comes out as +pi."""
    return torch.remainder(theta + math.pi, 2.0 * math.pi) - math.pi


def wrap_line_angle(theta: torch.Tensor) -> torch.Tensor:
    """Direction angles of undirected lines into [0, pi); by rounding, an input a hair below 0,
    -pi, ... comes out as pi."""
    return torch.remainder(theta, math.pi)


def line_angle_between(phi_1: torch.Tensor, phi_2: torch.Tensor) -> torch.Tensor:
    """Sign-less angle between two lines given their angles in [0, pi): in [0, pi/2]."""
    diff = (phi_1 - phi_2).abs()
    return torch.minimum(diff, math.pi - diff)


def yaw_of(T: torch.Tensor) -> torch.Tensor:
    """Heading of the body x axis, (..., 3, 3) -> (...,)."""
    return torch.atan2(T[..., 1, 0], T[..., 0, 0])


def rotation_matrix(theta: torch.Tensor) -> torch.Tensor:
    """(...,) angles -> (..., 2, 2) proper rotation matrices."""
    c, s = torch.cos(theta), torch.sin(theta)
    return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)


def se2_matrix(theta: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(...,) angles and (..., 2) translations -> (..., 3, 3) homogeneous transforms."""
    T = t.new_zeros(t.shape[:-1] + (3, 3))
    T[..., :2, :2] = rotation_matrix(theta)
    T[..., :2, 2] = t
    T[..., 2, 2] = 1.0
    return T


def se2_from_se3(T: np.ndarray) -> torch.Tensor:
    """(..., 4, 4) numpy poses -> (..., 3, 3) float64 SE(2): x, y and the yaw of the body x axis."""
    T = np.asarray(T, dtype=np.float64)
    return se2_matrix(
        torch.as_tensor(np.asarray(planar.yaw_of(T))), torch.as_tensor(np.ascontiguousarray(T[..., :2, 3]))
    )


def se2_compose(T_a_b: torch.Tensor, T_b_c: torch.Tensor) -> torch.Tensor:
    """T_a_c = T_a_b T_b_c (broadcasting over leading dimensions)."""
    return T_a_b @ T_b_c


def se2_inverse(T_a_b: torch.Tensor) -> torch.Tensor:
    """T_b_a from T_a_b, using R^T instead of a general matrix inverse (exact for rigid motions)."""
    R_t = T_a_b[..., :2, :2].transpose(-1, -2)
    T_b_a = torch.zeros_like(T_a_b)
    T_b_a[..., :2, :2] = R_t
    T_b_a[..., :2, 2] = -(R_t @ T_a_b[..., :2, 2:3])[..., 0]
    T_b_a[..., 2, 2] = 1.0
    return T_b_a


def se2_apply(T_a_b: torch.Tensor, points_b: torch.Tensor) -> torch.Tensor:
    """Map (..., N, 2) points from frame b into frame a with (..., 3, 3) transforms."""
    return points_b @ T_a_b[..., :2, :2].transpose(-1, -2) + T_a_b[..., None, :2, 2]

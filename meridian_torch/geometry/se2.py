"""Batched SE(2) helpers on torch tensors.

Poses are 3x3 homogeneous matrices `T_a_b` of shape (..., 3, 3) mapping 2D points from
frame b into frame a: p_a = R p_b + t. Angles are radians, counter-clockwise (right-handed
frames). Device and dtype always follow the inputs.
"""

from __future__ import annotations

import math

import torch

__all__ = ["wrap_angle", "rotation_matrix", "se2_matrix", "se2_compose", "se2_inverse", "se2_apply"]


def wrap_angle(theta: torch.Tensor) -> torch.Tensor:
    """Wrap angles into [-pi, pi)."""
    return torch.remainder(theta + math.pi, 2.0 * math.pi) - math.pi


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

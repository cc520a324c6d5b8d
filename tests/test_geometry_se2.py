from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.geometry.se2 import (
    line_angle_between,
    rotation_matrix,
    se2_apply,
    se2_compose,
    se2_from_se3,
    se2_inverse,
    se2_matrix,
    wrap_angle,
    wrap_line_angle,
    yaw_of,
)
from meridian_torch.geometry.se3 import pose_from_xyz_yaw

angles = st.floats(-10.0, 10.0, allow_nan=False)
coords = st.floats(-1e3, 1e3, allow_nan=False)
poses = st.tuples(angles, coords, coords)


def _pose(p: tuple[float, float, float]) -> torch.Tensor:
    theta, x, y = p
    return se2_matrix(torch.tensor(theta, dtype=torch.float64), torch.tensor([x, y], dtype=torch.float64))


@given(angles)
def test_rotation_matrix_is_proper(theta: float) -> None:
    R = rotation_matrix(torch.tensor(theta, dtype=torch.float64))
    assert torch.allclose(R @ R.T, torch.eye(2, dtype=torch.float64), atol=1e-12)
    assert math.isclose(torch.linalg.det(R).item(), 1.0, abs_tol=1e-12)


@given(angles)
def test_wrap_angle_range_and_equivalence(theta: float) -> None:
    w = wrap_angle(torch.tensor(theta, dtype=torch.float64))
    assert -math.pi <= w.item() <= math.pi  # +pi only by rounding, just below -pi, -3pi, ...
    assert math.isclose(math.cos(w.item()), math.cos(theta), abs_tol=1e-9)
    assert math.isclose(math.sin(w.item()), math.sin(theta), abs_tol=1e-9)


@settings(max_examples=50)
@given(poses, poses)
def test_compose_inverse_round_trips(a: tuple[float, float, float], b: tuple[float, float, float]) -> None:
    T_a_b, T_b_c = _pose(a), _pose(b)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(se2_compose(T_a_b, se2_inverse(T_a_b)), eye, atol=1e-9)
    assert torch.allclose(se2_compose(se2_inverse(T_a_b), T_a_b), eye, atol=1e-9)
    assert torch.allclose(se2_inverse(se2_inverse(T_a_b)), T_a_b, atol=1e-9)
    # (T_a_b T_b_c)^-1 = T_b_c^-1 T_a_b^-1
    T_a_c = se2_compose(T_a_b, T_b_c)
    assert torch.allclose(se2_inverse(T_a_c), se2_compose(se2_inverse(T_b_c), se2_inverse(T_a_b)), atol=1e-9)


@settings(max_examples=50)
@given(poses, poses)
def test_apply_agrees_with_compose(a: tuple[float, float, float], b: tuple[float, float, float]) -> None:
    T_a_b, T_b_c = _pose(a), _pose(b)
    points_c = torch.tensor([[0.0, 0.0], [1.0, -2.0], [30.0, 4.5]], dtype=torch.float64)
    chained = se2_apply(T_a_b, se2_apply(T_b_c, points_c))
    assert torch.allclose(chained, se2_apply(se2_compose(T_a_b, T_b_c), points_c), atol=1e-8)
    assert torch.allclose(se2_apply(se2_inverse(T_b_c), se2_apply(T_b_c, points_c)), points_c, atol=1e-8)


def test_batched_shapes_follow_inputs() -> None:
    theta = torch.zeros(4, 5, dtype=torch.float32)
    t = torch.ones(4, 5, 2, dtype=torch.float32)
    T = se2_matrix(theta, t)
    assert T.shape == (4, 5, 3, 3) and T.dtype == torch.float32
    points = torch.zeros(4, 5, 7, 2, dtype=torch.float32)
    assert torch.equal(se2_apply(T, points), torch.ones(4, 5, 7, 2))
    assert torch.equal(se2_inverse(T)[..., :2, 2], -torch.ones(4, 5, 2))


def test_wrap_angle_at_the_ends() -> None:
    ends = torch.tensor([math.pi, -math.pi, 3 * math.pi, 0.0], dtype=torch.float64)
    assert wrap_angle(ends).tolist() == [-math.pi, -math.pi, -math.pi, 0.0]


@given(angles)
def test_wrap_line_angle_range_and_equivalence(theta: float) -> None:
    w = wrap_line_angle(torch.tensor(theta, dtype=torch.float64)).item()
    assert 0.0 <= w <= math.pi  # pi only by rounding, just below 0, -pi, ...
    # Same undirected line: the direction (cos, sin) agrees up to its sign.
    assert math.isclose(abs(math.cos(w) * math.cos(theta) + math.sin(w) * math.sin(theta)), 1.0, abs_tol=1e-9)


@given(angles, angles)
def test_line_angle_between_is_the_unsigned_angle_of_the_directions(a: float, b: float) -> None:
    phi_1, phi_2 = (wrap_line_angle(torch.tensor(v, dtype=torch.float64)) for v in (a, b))
    between = line_angle_between(phi_1, phi_2).item()
    assert 0.0 <= between <= math.pi / 2
    assert between == line_angle_between(phi_2, phi_1).item()
    cos = abs(math.cos(a) * math.cos(b) + math.sin(a) * math.sin(b))
    assert math.isclose(math.cos(between), cos, abs_tol=1e-9)


@settings(max_examples=50)
@given(poses)
def test_yaw_of_inverts_se2_matrix(p: tuple[float, float, float]) -> None:
    yaw = yaw_of(_pose(p)).item()
    assert math.isclose(math.cos(yaw), math.cos(p[0]), abs_tol=1e-12)
    assert math.isclose(math.sin(yaw), math.sin(p[0]), abs_tol=1e-12)


@settings(max_examples=50)
@given(poses, st.floats(-50.0, 50.0))
def test_se2_from_se3_keeps_x_y_and_yaw(p: tuple[float, float, float], z: float) -> None:
    theta, x, y = p
    T = pose_from_xyz_yaw(np.array([x, y, z]), np.array(theta))
    assert torch.allclose(se2_from_se3(T), _pose(p), atol=1e-9)
    assert se2_from_se3(np.stack([T, T])).shape == (2, 3, 3)

from __future__ import annotations

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.geometry.se2 import (
    rotation_matrix,
    se2_apply,
    se2_compose,
    se2_inverse,
    se2_matrix,
    wrap_angle,
)

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
    assert -math.pi <= w.item() < math.pi
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

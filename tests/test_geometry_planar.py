from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from meridian_torch.geometry import se2
from meridian_torch.geometry.planar import scalar_yaw_of, se2_from_se3, se2_from_xy_yaw, wrap_angle, yaw_of
from meridian_torch.geometry.se3 import pose_from_xyz_yaw

angles = st.floats(-20.0, 20.0, allow_nan=False)
coords = st.floats(-1e3, 1e3, allow_nan=False)


@given(arrays(np.float64, (16,), elements=angles))
def test_wrap_angle_range_and_equivalence(theta: np.ndarray) -> None:
    w = wrap_angle(theta)
    assert np.all((w >= -np.pi) & (w <= np.pi))  # +pi only by rounding, just below -pi, -3pi, ...
    assert np.allclose(np.cos(w), np.cos(theta), atol=1e-9)
    assert np.allclose(np.sin(w), np.sin(theta), atol=1e-9)


@given(angles)
def test_wrap_angle_of_a_python_float_is_that_of_an_array(theta: float) -> None:
    w = wrap_angle(theta)
    assert type(w) is float
    assert w == wrap_angle(np.array([theta]))[0]
    assert w == se2.wrap_angle(torch.tensor(theta, dtype=torch.float64)).item()


def test_wrap_angle_at_the_ends() -> None:
    assert wrap_angle(np.array([np.pi, -np.pi, 3 * np.pi, 0.0])).tolist() == [-np.pi, -np.pi, -np.pi, 0.0]
    assert wrap_angle(np.nextafter(-np.pi, -4.0)) == np.pi  # the rounding the docstring names


@settings(max_examples=50)
@given(coords, coords, angles)
def test_se2_from_xy_yaw_round_trips(x: float, y: float, yaw: float) -> None:
    T = se2_from_xy_yaw(x, y, yaw)
    assert T.shape == (3, 3) and T.dtype == np.float64
    assert np.allclose(T[:2, :2] @ T[:2, :2].T, np.eye(2), atol=1e-12)
    assert T[0, 2] == x and T[1, 2] == y and T[2].tolist() == [0.0, 0.0, 1.0]
    back = float(yaw_of(T))
    assert -math.pi <= back <= math.pi
    assert math.isclose(math.cos(back), math.cos(yaw), abs_tol=1e-12)
    assert math.isclose(math.sin(back), math.sin(yaw), abs_tol=1e-12)


@settings(max_examples=50)
@given(coords, coords, st.floats(-50.0, 50.0), angles)
def test_se2_from_se3_keeps_x_y_and_yaw(x: float, y: float, z: float, yaw: float) -> None:
    T = pose_from_xyz_yaw(np.array([x, y, z]), np.array(yaw))
    assert np.allclose(se2_from_se3(T), se2_from_xy_yaw(x, y, yaw), atol=1e-9)
    batch = np.stack([T, T, T])
    assert se2_from_se3(batch).shape == (3, 3, 3)
    assert np.array_equal(yaw_of(batch), np.full(3, yaw_of(T)))
    # The numpy and torch versions agree to rounding (not bit for bit: their cos/sin differ).
    assert np.allclose(se2_from_se3(T), se2.se2_from_se3(T).numpy(), atol=1e-12)


@settings(max_examples=50)
@given(coords, coords, angles)
def test_scalar_yaw_of_agrees_with_yaw_of(x: float, y: float, yaw: float) -> None:
    T = pose_from_xyz_yaw(np.array([x, y, 0.0]), np.array(yaw))
    one = scalar_yaw_of(T)
    assert type(one) is float
    assert math.isclose(one, float(yaw_of(T)), abs_tol=1e-15)
    assert one == scalar_yaw_of(torch.from_numpy(T))

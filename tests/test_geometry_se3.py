from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from meridian_torch.geometry.planar import yaw_of
from meridian_torch.geometry.se3 import (
    matrix_to_quat_xyzw,
    pose_from_xyz_yaw,
    quat_xyzw_to_matrix,
    se3_exp,
    se3_inverse,
    se3_log,
    so3_exp,
    so3_log,
)

finite = st.floats(-3.0, 3.0, allow_nan=False)
twists = arrays(np.float64, (6,), elements=finite)


def _is_rotation(R: np.ndarray) -> bool:
    return np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)


@given(arrays(np.float64, (4,), elements=st.floats(-1, 1)).filter(lambda q: np.linalg.norm(q) > 0.1))
def test_quaternion_round_trip(q: np.ndarray) -> None:
    R = quat_xyzw_to_matrix(q)
    assert _is_rotation(R)
    assert np.allclose(quat_xyzw_to_matrix(matrix_to_quat_xyzw(R)), R, atol=1e-9)


@given(twists)
def test_se3_exp_log_round_trip(xi: np.ndarray) -> None:
    T = se3_exp(xi)
    assert _is_rotation(T[:3, :3])
    # log is the inverse of exp on the principal branch (rotation angle < pi)
    if np.linalg.norm(xi[3:]) < np.pi - 1e-3:
        assert np.allclose(se3_log(T), xi, atol=1e-7)
    assert np.allclose(se3_exp(se3_log(T)), T, atol=1e-7)


@given(twists)
def test_inverse_composes_to_identity(xi: np.ndarray) -> None:
    T = se3_exp(xi)
    assert np.allclose(T @ se3_inverse(T), np.eye(4), atol=1e-9)


def test_so3_log_near_pi() -> None:
    for axis in (np.array([1.0, 0, 0]), np.array([0, 1.0, 1.0]) / np.sqrt(2)):
        w = axis * (np.pi - 1e-9)
        assert np.allclose(so3_exp(so3_log(so3_exp(w))), so3_exp(w), atol=1e-7)


@settings(max_examples=50)
@given(st.floats(-10, 10), st.floats(-10, 10), st.floats(-np.pi + 1e-6, np.pi - 1e-6))
def test_yaw_pose_round_trip(x: float, y: float, yaw: float) -> None:
    T = pose_from_xyz_yaw(np.array([x, y, 0.0]), np.array(yaw))
    assert np.isclose(yaw_of(T), yaw, atol=1e-12)
    assert np.allclose(T[:2, 3], [x, y])


def test_batched_equals_loop() -> None:
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(7, 6))
    batched = se3_exp(xi)
    assert np.allclose(batched, np.stack([se3_exp(x) for x in xi]))
    assert np.allclose(se3_log(batched), np.stack([se3_log(T) for T in batched]))

"""Batched SE(3) / SO(3) helpers in numpy float64.

Poses are 4x4 homogeneous matrices `T_a_b` mapping points from frame b into frame a.
Quaternions are Hamilton, stored (x, y, z, w) as in TUM files.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "quat_xyzw_to_matrix",
    "matrix_to_quat_xyzw",
    "so3_exp",
    "so3_log",
    "se3_exp",
    "se3_log",
    "se3_inverse",
    "pose_from_xyz_yaw",
    "interpolate_poses",
]

_EPS = 1e-12


def _skew(v: np.ndarray) -> np.ndarray:
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w) -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) quaternions (x, y, z, w) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    # Shepperd's method: pick the numerically largest of the four candidates per matrix.
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1)
    trace = diag.sum(-1)
    cand = np.stack([trace, diag[:, 0], diag[:, 1], diag[:, 2]], -1)
    k = cand.argmax(-1)
    q = np.empty((m.shape[0], 4))
    for case in range(4):
        sel = k == case
        if not sel.any():
            continue
        a = m[sel]
        if case == 0:
            s = np.sqrt(1.0 + trace[sel]) * 2
            q[sel] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s,
                               (a[:, 1, 0] - a[:, 0, 1]) / s, 0.25 * s], -1)
        elif case == 1:
            s = np.sqrt(1.0 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2]) * 2
            q[sel] = np.stack([0.25 * s, (a[:, 0, 1] + a[:, 1, 0]) / s,
                               (a[:, 0, 2] + a[:, 2, 0]) / s, (a[:, 2, 1] - a[:, 1, 2]) / s], -1)
        elif case == 2:
            s = np.sqrt(1.0 + a[:, 1, 1] - a[:, 0, 0] - a[:, 2, 2]) * 2
            q[sel] = np.stack([(a[:, 0, 1] + a[:, 1, 0]) / s, 0.25 * s,
                               (a[:, 1, 2] + a[:, 2, 1]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s], -1)
        else:
            s = np.sqrt(1.0 + a[:, 2, 2] - a[:, 0, 0] - a[:, 1, 1]) * 2
            q[sel] = np.stack([(a[:, 0, 2] + a[:, 2, 0]) / s, (a[:, 1, 2] + a[:, 2, 1]) / s,
                               0.25 * s, (a[:, 1, 0] - a[:, 0, 1]) / s], -1)
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q.reshape(R.shape[:-2] + (4,))


def so3_exp(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) rotations (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = _skew(w)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) rotation vectors, valid up to and including pi."""
    R = np.asarray(R, dtype=np.float64)
    # Through the quaternion: stable near 0 and near pi, unlike arccos of the trace.
    q = matrix_to_quat_xyzw(R)
    v, w = q[..., :3], q[..., 3]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    scale = np.where(s < 1e-12, 2.0 / np.maximum(w, _EPS), angle / np.maximum(s, _EPS))
    return v * scale[..., None]


def _left_jacobian(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = _skew(w)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    c = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (safe - np.sin(safe)) / safe**3)
    return K, np.eye(3) + b * K + c * (K @ K)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """(..., 6) twists (v, w) -> (..., 4, 4) poses."""
    xi = np.asarray(xi, dtype=np.float64)
    v, w = xi[..., :3], xi[..., 3:]
    _, J = _left_jacobian(w)
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = so3_exp(w)
    T[..., :3, 3] = (J @ v[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) poses -> (..., 6) twists (v, w)."""
    T = np.asarray(T, dtype=np.float64)
    w = so3_log(T[..., :3, :3])
    _, J = _left_jacobian(w)
    v = np.linalg.solve(J, T[..., :3, 3:4])[..., 0]
    return np.concatenate([v, w], axis=-1)


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> inverse poses."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def pose_from_xyz_yaw(xyz: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(..., 3) positions and (...,) yaw angles (about +z) -> (..., 4, 4) poses."""
    xyz = np.asarray(xyz, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.zeros(yaw.shape + (4, 4))
    T[..., 0, 0], T[..., 0, 1] = c, -s
    T[..., 1, 0], T[..., 1, 1] = s, c
    T[..., 2, 2] = 1.0
    T[..., :3, 3] = xyz
    T[..., 3, 3] = 1.0
    return T


def interpolate_poses(times: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """SE(3) geodesic interpolation T0 exp(s log(T0^-1 T1)) of a pose sequence at query times.

    Exact for motion with a constant body twist between samples (e.g. a car on a circle).
    `times` (N,) strictly increasing, `poses` (N, 4, 4), `query` (M,) inside [times[0], times[-1]].
    """
    times = np.asarray(times, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64)
    if query.size and (query.min() < times[0] or query.max() > times[-1]):
        raise ValueError("query times outside the trajectory's time span")
    if len(times) == 1:
        return np.repeat(poses[:1], len(query), axis=0)
    i = np.clip(np.searchsorted(times, query, side="right") - 1, 0, len(times) - 2)
    s = (query - times[i]) / (times[i + 1] - times[i])
    T0, T1 = poses[i], poses[i + 1]
    delta = se3_log(se3_inverse(T0) @ T1)
    return T0 @ se3_exp(delta * s[:, None])

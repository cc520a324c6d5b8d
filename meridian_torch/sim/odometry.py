"""Simulated odometry T_odom_base: exact, drifting, or read from an estimate file.

The odom frame is the first ground-truth pose's base frame, so odometry starts at identity.
"""

from __future__ import annotations

import numpy as np

from meridian_torch.config.sim import OdometryConfig
from meridian_torch.errors import SimulationError
from meridian_torch.geometry.se3 import pose_from_xyz_yaw, se3_inverse
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.poses import read_kitti, read_tum
from meridian_torch.sim.trajectory import kitti_to_base

__all__ = ["simulate_odometry"]


def simulate_odometry(gt: Trajectory, cfg: OdometryConfig, seed: int) -> Trajectory:
    """Odometry for ground truth `gt` (T_world_base).

    'perfect': gt relative to its first pose. 'drift': every step's relative motion gets a
    constant scale error, translation noise with std proportional to the step length and a
    yaw random walk with std proportional to sqrt(step length). 'file': an estimate (TUM, or
    KITTI camera poses converted to the base frame and timed by index with gt).
    """
    if cfg.kind == "file":
        return _from_file(gt, cfg)
    rel = se3_inverse(gt.poses[:1]) @ gt.poses
    if cfg.kind == "perfect" or len(gt) < 2:
        return Trajectory(gt.timestamps, rel)
    rng = np.random.default_rng(seed)
    steps = se3_inverse(gt.poses[:-1]) @ gt.poses[1:]
    dist = np.linalg.norm(steps[:, :3, 3], axis=1)
    scale = 1.0 + rng.normal(0.0, cfg.scale_drift)
    noisy = steps.copy()
    noisy[:, :3, 3] = steps[:, :3, 3] * scale + rng.normal(0.0, 1.0, (len(steps), 3)) * (cfg.translation_drift * dist)[:, None]
    noisy[:, 2, 3] = steps[:, 2, 3] * scale  # gravity-aligned odometry: no vertical noise
    dyaw = rng.normal(0.0, 1.0, len(steps)) * np.radians(cfg.yaw_drift_deg_per_sqrt_m) * np.sqrt(dist)
    noisy = noisy @ pose_from_xyz_yaw(np.zeros((len(steps), 3)), dyaw)
    out = np.empty_like(gt.poses)
    out[0] = np.eye(4)
    for i, step in enumerate(noisy):  # sequential composition, one 4x4 product per step
        out[i + 1] = out[i] @ step
    return Trajectory(gt.timestamps, out)


def _from_file(gt: Trajectory, cfg: OdometryConfig) -> Trajectory:
    if cfg.path is None:
        raise SimulationError("odometry kind 'file' needs a path")
    if cfg.format == "tum":
        est = read_tum(cfg.path)
    else:
        raw = read_kitti(cfg.path)
        if len(raw) != len(gt):
            raise SimulationError(f"{cfg.path}: {len(raw)} poses but the ground truth has {len(gt)}; "
                                  "KITTI estimates are timed by index")
        est = kitti_to_base(Trajectory(gt.timestamps, raw.poses))
    return Trajectory(est.timestamps, se3_inverse(est.poses[:1]) @ est.poses)

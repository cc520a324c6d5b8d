"""The pose graph in GTSAM (the only module that imports gtsam).

One Pose2 T_world_base per frame, BetweenFactorPose2 odometry factors between consecutive
frames, and every inlier loop closure as a unary PriorFactorPose2 on the frame nearest in time
to its submap. Plain Gaussian noise (CLIPPER removed the outliers already), Levenberg-Marquardt
with GTSAM's defaults. The initial values are the odometry aligned rigidly to the loop closures.
Poses in and out are numpy float64 (..., 3, 3) SE(2) matrices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from meridian_torch.config import BackendConfig
from meridian_torch.geometry.planar import se2_from_xy_yaw, yaw_of

__all__ = ["PoseGraphSolution", "align_odometry", "optimize_pose_graph", "propagate_covariance"]


def align_odometry(T_world_base: np.ndarray, T_odom_base: np.ndarray) -> np.ndarray:
    """The rigid T_world_odom (3, 3) that best maps odometry poses (K, 3, 3) onto measured world poses.

    Yaw = circular mean of the per-measurement yaw offsets; translation = least squares given that
    yaw (mean of p_world - R p_odom). The reference averages each measurement's T_world_odom
    instead, which equals this when the yaws agree.
    """
    dyaw = yaw_of(T_world_base) - yaw_of(T_odom_base)
    yaw = math.atan2(np.sin(dyaw).mean(), np.cos(dyaw).mean())
    R = se2_from_xy_yaw(0.0, 0.0, np.array(yaw))[:2, :2]
    t = (T_world_base[:, :2, 2] - T_odom_base[:, :2, 2] @ R.T).mean(axis=0)
    return se2_from_xy_yaw(t[0], t[1], np.array(yaw))


@dataclass(frozen=True)
class PoseGraphSolution:
    T_world_base: np.ndarray  # (N, 3, 3) optimized pose of every node
    covariance: np.ndarray | None  # (N, 3, 3) (or (1, 3, 3) for the last node) marginal covariance of (x, y, yaw), world axes
    initial_error: float  # graph error at the initial values
    final_error: float
    iterations: int


def optimize_pose_graph(
    T_odom_base: np.ndarray,
    prior_nodes: np.ndarray,
    T_world_base_priors: np.ndarray,
    cfg: BackendConfig,
    *,
    covariance: bool | Literal["last"] = False,
) -> PoseGraphSolution:
    """Optimize N nodes (odometry poses (N, 3, 3)) with K >= 1 loop-closure priors on `prior_nodes` (K,).

    `covariance=True` also returns every node's marginal covariance, rotated from GTSAM's body
    tangent space into world-aligned (x east, y north, yaw) axes; `"last"` only the last node's
    ((1, 3, 3), what an online estimate needs).
    """
    import gtsam

    T_odom_base = np.asarray(T_odom_base, dtype=np.float64)
    prior_nodes = np.asarray(prior_nodes, dtype=np.int64)
    T_world_base_priors = np.asarray(T_world_base_priors, dtype=np.float64)
    n = len(T_odom_base)
    if len(prior_nodes) == 0 or n == 0:
        raise ValueError("optimize_pose_graph needs at least one node and one loop-closure prior")
    if prior_nodes.min() < 0 or prior_nodes.max() >= n:
        raise ValueError(f"prior nodes must lie in [0, {n}), got {prior_nodes.min()}..{prior_nodes.max()}")

    def pose(T: np.ndarray) -> gtsam.Pose2:
        return gtsam.Pose2(float(T[0, 2]), float(T[1, 2]), float(yaw_of(T)))

    graph = gtsam.NonlinearFactorGraph()
    odom_noise = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([cfg.odom_trans_sigma_m, cfg.odom_trans_sigma_m, math.radians(cfg.odom_rot_sigma_deg)])
    )
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([cfg.prior_trans_sigma_m, cfg.prior_trans_sigma_m, math.radians(cfg.prior_rot_sigma_deg)])
    )
    steps = np.linalg.inv(T_odom_base[:-1]) @ T_odom_base[1:]
    for k, step in enumerate(steps):
        graph.add(gtsam.BetweenFactorPose2(k, k + 1, pose(step), odom_noise))
    for node, T in zip(prior_nodes, T_world_base_priors):
        graph.add(gtsam.PriorFactorPose2(int(node), pose(T), prior_noise))

    T_world_odom = align_odometry(T_world_base_priors, T_odom_base[prior_nodes])
    initial = gtsam.Values()
    for k, T in enumerate(T_world_odom @ T_odom_base):
        initial.insert(k, pose(T))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    result = optimizer.optimize()
    xyt = np.array([[p.x(), p.y(), p.theta()] for p in (result.atPose2(k) for k in range(n))])
    cov = None
    if covariance:
        marginals = gtsam.Marginals(graph, result)
        nodes = np.arange(n - 1, n) if covariance == "last" else np.arange(n)
        local = np.stack([marginals.marginalCovariance(int(k)) for k in nodes])
        rot = se2_from_xy_yaw(0.0, 0.0, xyt[nodes, 2])  # body tangent (x, y, theta) -> world-aligned axes
        rot[:, 2, 2] = 1.0
        cov = rot @ local @ np.swapaxes(rot, 1, 2)
    return PoseGraphSolution(
        T_world_base=se2_from_xy_yaw(xyt[:, 0], xyt[:, 1], xyt[:, 2]),
        covariance=cov,
        initial_error=float(graph.error(initial)),
        final_error=float(graph.error(result)),
        iterations=int(optimizer.iterations()),
    )


def propagate_covariance(covariance: np.ndarray, T_world_base: np.ndarray, cfg: BackendConfig) -> np.ndarray:
    """The (3, 3) covariance of (x, y, yaw), world axes, at the last of the poses (K, 3, 3) when
    the first one's is `covariance` and the K - 1 steps between them are odometry factors (the
    graph's noise): what the pose graph's marginal would be if no loop closure came after the
    first pose. To first order: the first pose's yaw error and every step's yaw noise swing the
    rest of the path about where they occur; each step adds its translation noise."""
    p = T_world_base[:, :2, 2]
    end = p[-1]

    def lever(points: np.ndarray) -> np.ndarray:  # (M, 3): d(end x, y, yaw) / d(yaw at each point)
        d = end - points
        return np.stack([-d[:, 1], d[:, 0], np.ones(len(d))], axis=1)

    J = np.eye(3)
    J[:, 2] = lever(p[:1])[0]
    out = J @ covariance @ J.T
    v = lever(p[1:])  # a step's yaw noise turns the path from the step's end on
    out += math.radians(cfg.odom_rot_sigma_deg) ** 2 * v.T @ v
    out[:2, :2] += (len(p) - 1) * cfg.odom_trans_sigma_m**2 * np.eye(2)
    return out

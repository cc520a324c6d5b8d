"""The pose graph in GTSAM (the only module that imports gtsam).

One Pose2 T_world_base per frame, BetweenFactorPose2 odometry factors between consecutive
frames, and every inlier loop closure as a unary PriorFactorPose2 on the frame nearest in time
to its submap, its sigmas the configured ones times the closure's scale (`closure_sigma_scales`:
larger for less probable hypotheses). Plain Gaussian noise (CLIPPER removed the outliers
already), Levenberg-Marquardt with GTSAM's defaults. The initial values are the odometry aligned
rigidly to the loop closures.
`IncrementalPoseGraph` keeps the same graph online in iSAM2: each update adds the new frames'
odometry factors and the loop closures that changed, instead of rebuilding and re-solving the
whole drive. Poses in and out are numpy float64 (..., 3, 3) SE(2) matrices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from meridian_torch.config import BackendConfig
from meridian_torch.geometry.planar import se2_from_xy_yaw, yaw_of

__all__ = [
    "IncrementalPoseGraph",
    "PoseGraphSolution",
    "align_odometry",
    "closure_sigma_scales",
    "optimize_pose_graph",
    "propagate_covariance",
]


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


def closure_sigma_scales(probability: np.ndarray, cfg: BackendConfig) -> np.ndarray:
    """Each loop closure's scale (K,) of the prior sigmas from its hypothesis probability (K,):
    sqrt(`prior_sigma_probability` / p) below that probability, clipped to
    [1, `prior_sigma_max_scale`]; all 1 when `prior_sigma_probability` is null. A closure's
    variance then grows as 1 / p below the reference: measured on the KITTI-map worlds, the
    closures turned by several degrees have low probabilities (README, Why the defaults)."""
    probability = np.asarray(probability, dtype=np.float64)
    if cfg.prior_sigma_probability is None:
        return np.ones_like(probability)
    ratio = cfg.prior_sigma_probability / np.maximum(probability, 1e-12)
    return np.clip(np.sqrt(ratio), 1.0, cfg.prior_sigma_max_scale)


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
    prior_scales: np.ndarray | None = None,
) -> PoseGraphSolution:
    """Optimize N nodes (odometry poses (N, 3, 3)) with K >= 1 loop-closure priors on `prior_nodes` (K,),
    their sigmas scaled by `prior_scales` (K,) (default 1: the configured sigmas).

    `covariance=True` also returns every node's marginal covariance, rotated from GTSAM's body
    tangent space into world-aligned (x east, y north, yaw) axes; `"last"` only the last node's
    ((1, 3, 3), what an online estimate needs).
    """
    import gtsam

    T_odom_base, prior_nodes, T_world_base_priors, prior_scales = _checked(
        T_odom_base, prior_nodes, T_world_base_priors, prior_scales
    )
    n = len(T_odom_base)
    graph = _factor_graph(T_odom_base, prior_nodes, T_world_base_priors, prior_scales, cfg)
    T_world_odom = align_odometry(T_world_base_priors, T_odom_base[prior_nodes])
    initial = gtsam.Values()
    for k, T in enumerate(T_world_odom @ T_odom_base):
        initial.insert(k, _pose2(T))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    result = optimizer.optimize()
    xyt = np.array([[p.x(), p.y(), p.theta()] for p in (result.atPose2(k) for k in range(n))])
    cov = None
    if covariance:
        marginals = gtsam.Marginals(graph, result)
        nodes = np.arange(n - 1, n) if covariance == "last" else np.arange(n)
        cov = _world_axes(np.stack([marginals.marginalCovariance(int(k)) for k in nodes]), xyt[nodes, 2])
    return PoseGraphSolution(
        T_world_base=se2_from_xy_yaw(xyt[:, 0], xyt[:, 1], xyt[:, 2]),
        covariance=cov,
        initial_error=float(graph.error(initial)),
        final_error=float(graph.error(result)),
        iterations=int(optimizer.iterations()),
    )


class IncrementalPoseGraph:
    """The online pose graph in iSAM2: the same factors as `optimize_pose_graph`, updated in place.

    The first `update` solves the graph in batch (Levenberg-Marquardt, as `optimize_pose_graph`)
    and hands that solution to iSAM2. Later updates add the odometry factors of the frames that
    arrived since, add the loop-closure priors that are new and remove those no longer given (a
    prior is identified by its node and measured pose, bit for bit), then let iSAM2 relinearize
    until the estimate settles. The cost of an update depends on what changed, not on the length
    of the drive.
    """

    _MAX_SETTLE_STEPS = 5  # extra iSAM2 steps after an update, while they still relinearize something

    def __init__(self, cfg: BackendConfig) -> None:
        self.cfg = cfg
        self._isam = None
        self._n = 0
        self._priors: dict[tuple[int, bytes], int] = {}  # (node, measured pose bytes) -> factor index

    @property
    def n_nodes(self) -> int:
        return self._n

    def update(
        self, T_odom_base: np.ndarray, prior_nodes: np.ndarray, T_world_base_priors: np.ndarray, *,
        covariance: bool = False, prior_scales: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Bring the graph to the frames T_odom_base (N, 3, 3) (the first n_nodes unchanged, N >=
        n_nodes) and exactly the priors given (sigmas scaled by `prior_scales`, default 1); returns
        the last node's optimized pose (3, 3) and, with `covariance`, its marginal covariance of
        (x, y, yaw) in world axes (3, 3)."""
        import gtsam

        T_odom_base, prior_nodes, T_world_base_priors, prior_scales = _checked(
            T_odom_base, prior_nodes, T_world_base_priors, prior_scales
        )
        n = len(T_odom_base)
        if n < self._n:
            raise ValueError(f"the pose graph has {self._n} nodes; an update cannot drop frames (got {n})")
        # A prior is its node, measured pose and scale, bit for bit.
        keys = [(int(k), np.ascontiguousarray(T).tobytes() + np.float64(s).tobytes())
                for k, T, s in zip(prior_nodes, T_world_base_priors, prior_scales)]
        if self._isam is None:
            self._start(T_odom_base, prior_nodes, T_world_base_priors, prior_scales, keys)
        else:
            factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            if n > self._n:  # new frames start where the odometry carries the last estimate
                T_world_odom = self._pose(self._n - 1) @ np.linalg.inv(T_odom_base[self._n - 1])
                _add_odometry(factors, T_odom_base[self._n - 1 :], self._n - 1, self.cfg)
                for k in range(self._n, n):
                    values.insert(k, _pose2(T_world_odom @ T_odom_base[k]))
            wanted = dict(zip(keys, zip(T_world_base_priors, prior_scales)))
            added = [key for key in wanted if key not in self._priors]
            for key in added:
                T, scale = wanted[key]
                factors.add(gtsam.PriorFactorPose2(key[0], _pose2(T), _prior_noise(self.cfg, float(scale))))
            removed = [key for key in self._priors if key not in wanted]
            result = self._isam.update(factors, values, [self._priors.pop(key) for key in removed])
            first_prior = factors.size() - len(added)
            indices = result.getNewFactorsIndices()
            for i, key in enumerate(added):
                self._priors[key] = int(indices[first_prior + i])
            self._settle(result)
        self._n = n
        T_last = self._pose(n - 1)
        cov = None
        if covariance:
            cov = _world_axes(self._isam.marginalCovariance(n - 1)[None], np.array([yaw_of(T_last)]))[0]
        return T_last, cov

    def _start(self, T_odom_base: np.ndarray, prior_nodes: np.ndarray, T_world_base_priors: np.ndarray,
               prior_scales: np.ndarray, keys: list[tuple[int, bytes]]) -> None:
        import gtsam

        sol = optimize_pose_graph(T_odom_base, prior_nodes, T_world_base_priors, self.cfg, prior_scales=prior_scales)
        graph = _factor_graph(T_odom_base, prior_nodes, T_world_base_priors, prior_scales, self.cfg)
        values = gtsam.Values()
        first_prior = len(T_odom_base) - 1  # after the odometry factors
        for k, T in enumerate(sol.T_world_base):
            values.insert(k, _pose2(T))
        params = gtsam.ISAM2Params()
        params.relinearizeSkip = 1  # relinearize what moved at every step (a few variables per update)
        params.enablePartialRelinearizationCheck = True  # check only the cliques an update touched: O(change), not O(drive)
        self._isam = gtsam.ISAM2(params)
        result = self._isam.update(graph, values)
        indices = result.getNewFactorsIndices()
        self._priors = {key: int(indices[first_prior + i]) for i, key in enumerate(keys)}

    def _settle(self, result) -> None:
        for _ in range(self._MAX_SETTLE_STEPS):
            if result.getVariablesRelinearized() == 0:
                return
            result = self._isam.update()

    def _pose(self, k: int) -> np.ndarray:
        p = self._isam.calculateEstimatePose2(k)
        return se2_from_xy_yaw(p.x(), p.y(), np.array(p.theta()))


def _checked(
    T_odom_base: np.ndarray, prior_nodes: np.ndarray, T_world_base_priors: np.ndarray, prior_scales: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    T_odom_base = np.asarray(T_odom_base, dtype=np.float64)
    prior_nodes = np.asarray(prior_nodes, dtype=np.int64)
    T_world_base_priors = np.asarray(T_world_base_priors, dtype=np.float64)
    n = len(T_odom_base)
    if len(prior_nodes) == 0 or n == 0:
        raise ValueError("the pose graph needs at least one node and one loop-closure prior")
    if prior_nodes.min() < 0 or prior_nodes.max() >= n:
        raise ValueError(f"prior nodes must lie in [0, {n}), got {prior_nodes.min()}..{prior_nodes.max()}")
    if prior_scales is None:
        prior_scales = np.ones(len(prior_nodes))
    prior_scales = np.asarray(prior_scales, dtype=np.float64)
    if prior_scales.shape != prior_nodes.shape or not (prior_scales > 0).all() or not np.isfinite(prior_scales).all():
        raise ValueError(f"prior scales must be {len(prior_nodes)} finite positive numbers, got {prior_scales}")
    return T_odom_base, prior_nodes, T_world_base_priors, prior_scales


def _pose2(T: np.ndarray):
    import gtsam

    return gtsam.Pose2(float(T[0, 2]), float(T[1, 2]), float(yaw_of(T)))


def _odometry_step_sigmas(T_base: np.ndarray, cfg: BackendConfig) -> tuple[np.ndarray, np.ndarray]:
    """Sigmas ((K - 1,) of x and of y in m, (K - 1,) of yaw in rad) of the odometry factors between
    consecutive poses T_base (K, 3, 3): the per-step term combined with the per-metre term over
    the step's length (a length, so odometry and world poses give the same)."""
    root_length = np.sqrt(np.linalg.norm(np.diff(T_base[:, :2, 2], axis=0), axis=1))
    trans = np.hypot(cfg.odom_trans_sigma_m, cfg.odom_trans_sigma_m_per_sqrt_m * root_length)
    rot = np.hypot(math.radians(cfg.odom_rot_sigma_deg), math.radians(cfg.odom_rot_sigma_deg_per_sqrt_m) * root_length)
    return trans, rot


def _prior_noise(cfg: BackendConfig, scale: float):
    """A loop-closure prior's GTSAM diagonal model, the configured sigmas times `scale`."""
    import gtsam

    return gtsam.noiseModel.Diagonal.Sigmas(
        scale * np.array([cfg.prior_trans_sigma_m, cfg.prior_trans_sigma_m, math.radians(cfg.prior_rot_sigma_deg)])
    )


def _factor_graph(T_odom_base: np.ndarray, prior_nodes: np.ndarray, T_world_base_priors: np.ndarray,
                  prior_scales: np.ndarray, cfg: BackendConfig):
    """The graph's factors: the odometry steps (nodes 0..N-1, first), then one prior per loop closure."""
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    _add_odometry(graph, T_odom_base, 0, cfg)
    for node, T, scale in zip(prior_nodes, T_world_base_priors, prior_scales):
        graph.add(gtsam.PriorFactorPose2(int(node), _pose2(T), _prior_noise(cfg, float(scale))))
    return graph


def _add_odometry(graph, T_odom_base: np.ndarray, first_node: int, cfg: BackendConfig) -> None:
    """Between-factors for the steps of T_odom_base (K, 3, 3), whose first pose is node `first_node`."""
    import gtsam

    steps = np.linalg.inv(T_odom_base[:-1]) @ T_odom_base[1:]
    trans, rot = _odometry_step_sigmas(T_odom_base, cfg)
    sigmas = np.stack([trans, trans, rot], axis=1)
    for k, (step, sigma) in enumerate(zip(steps, sigmas), start=first_node):
        graph.add(gtsam.BetweenFactorPose2(k, k + 1, _pose2(step), gtsam.noiseModel.Diagonal.Sigmas(sigma)))


def _world_axes(local: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Covariances (K, 3, 3) in GTSAM's body tangent space (x, y, theta) -> world-aligned axes."""
    rot = se2_from_xy_yaw(0.0, 0.0, yaw)
    rot[:, 2, 2] = 1.0
    return rot @ local @ np.swapaxes(rot, 1, 2)


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
    trans, rot = _odometry_step_sigmas(T_world_base, cfg)
    v = lever(p[1:])  # a step's yaw noise turns the path from the step's end on
    out += (v.T * rot**2) @ v
    out[:2, :2] += (trans**2).sum() * np.eye(2)
    return out

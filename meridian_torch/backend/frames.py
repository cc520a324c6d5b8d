"""The localizer's frames (times and odometry, grown as frames arrive), the anchors of its online
updates, and the lift of planar world poses back to SE(3) along the odometry."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from meridian_torch.geometry.se2 import se2_from_se3

__all__ = ["FrameBuffer", "OnlineUpdate", "lift_se2"]


def lift_se2(T_world_base_se2: np.ndarray, T_odom_base: np.ndarray) -> np.ndarray:
    """(N, 3, 3) planar world poses + (N, 4, 4) odometry poses -> (N, 4, 4) T_world_base.

    The planar correction T_world_odom = T_world_base_se2 * SE2(T_odom_base)^-1 (x, y, yaw) is
    applied to the full odometry pose: x, y and yaw come from the SE(2) pose, z, roll and pitch
    from the odometry.
    """
    correction = T_world_base_se2 @ np.linalg.inv(se2_from_se3(T_odom_base).numpy())
    C = np.tile(np.eye(4), (len(correction), 1, 1))
    C[:, :2, :2] = correction[:, :2, :2]
    C[:, :2, 3] = correction[:, :2, 2]
    return C @ T_odom_base


@dataclass
class OnlineUpdate:
    available_time: float
    T_world_odom: np.ndarray  # (3, 3) anchor: last optimized pose * its odometry pose^-1
    node: int  # the frame the anchor was optimized at
    covariance: np.ndarray | None  # (3, 3) marginal covariance of that frame's (x, y, yaw), world axes

    @property
    def withheld(self) -> bool:
        """A NaN anchor: the online estimate is withheld from `available_time` on."""
        return not np.isfinite(self.T_world_odom[0, 0])


class FrameBuffer:
    """Frame times and odometry poses that grow as frames arrive (capacity doubles, so a long
    drive appends in amortized constant time); the arrays handed out are views of the filled part."""

    def __init__(self) -> None:
        self.n = 0
        self._times = np.empty(0)
        self._T_odom_base = np.empty((0, 4, 4))
        self._odom_se2 = np.empty((0, 3, 3))

    def extend(self, times: np.ndarray, T_odom_base: np.ndarray) -> None:
        need = self.n + len(times)
        if need > len(self._times):
            capacity = max(need, 2 * len(self._times), 64)
            self._times = np.resize(self._times, capacity)
            self._T_odom_base = np.resize(self._T_odom_base, (capacity, 4, 4))
            self._odom_se2 = np.resize(self._odom_se2, (capacity, 3, 3))
        self._times[self.n : need] = times
        self._T_odom_base[self.n : need] = T_odom_base
        self._odom_se2[self.n : need] = se2_from_se3(T_odom_base).numpy()
        self.n = need

    @property
    def times(self) -> np.ndarray:
        return self._times[: self.n]

    @property
    def T_odom_base(self) -> np.ndarray:
        return self._T_odom_base[: self.n]

    @property
    def odom_se2(self) -> np.ndarray:
        return self._odom_se2[: self.n]

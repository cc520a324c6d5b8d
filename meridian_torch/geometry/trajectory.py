"""A timestamped pose sequence, the in-memory form of a TUM file."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from meridian_torch.geometry.planar import yaw_of
from meridian_torch.geometry.se3 import interpolate_poses

__all__ = ["Trajectory"]


@dataclass(frozen=True)
class Trajectory:
    """`poses[i]` is T_frame_body at `timestamps[i]` (seconds, strictly increasing)."""

    timestamps: np.ndarray  # (N,) float64
    poses: np.ndarray  # (N, 4, 4) float64

    def __post_init__(self) -> None:
        t = np.asarray(self.timestamps, dtype=np.float64)
        T = np.asarray(self.poses, dtype=np.float64)
        if t.ndim != 1 or T.shape != (len(t), 4, 4):
            raise ValueError(f"timestamps (N,) and poses (N, 4, 4) expected, got {t.shape} and {T.shape}")
        if len(t) > 1 and not np.all(np.diff(t) > 0):
            raise ValueError("timestamps must be strictly increasing")
        object.__setattr__(self, "timestamps", t)
        object.__setattr__(self, "poses", T)

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    @property
    def yaws(self) -> np.ndarray:
        return yaw_of(self.poses)

    def path_lengths(self) -> np.ndarray:
        """Cumulative travelled distance in metres at every pose, starting at 0."""
        steps = np.linalg.norm(np.diff(self.positions, axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(steps)])

    def covers(self, query: np.ndarray) -> bool:
        query = np.asarray(query, dtype=np.float64)
        return len(self) > 0 and query.min() >= self.timestamps[0] and query.max() <= self.timestamps[-1]

    def gaps_bridged(self, query: np.ndarray, max_gap_s: float) -> np.ndarray:
        """(G, 2) start and end times of the pose intervals longer than `max_gap_s` that hold a
        query time strictly inside: where `interpolate` would guess across missing poses."""
        query = np.asarray(query, dtype=np.float64)
        k = np.searchsorted(self.timestamps, query, side="right")
        inside = (k > 0) & (k < len(self)) & (query > self.timestamps[np.clip(k - 1, 0, len(self) - 1)])
        k = np.unique(k[inside])
        long = self.timestamps[k] - self.timestamps[k - 1] > max_gap_s
        return np.stack([self.timestamps[k[long] - 1], self.timestamps[k[long]]], axis=1)

    def interpolate(self, query: np.ndarray) -> np.ndarray:
        """Poses (M, 4, 4) at the query times by SE(3) geodesic interpolation."""
        return interpolate_poses(self.timestamps, self.poses, np.asarray(query, dtype=np.float64))

"""What the localizer returns: per-submap events, the final result with its stage timings, and
the matcher it calls."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
import torch

from meridian_torch.backend.candidates import LoopClosureCandidates
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.matching.hypotheses import Hypotheses
from meridian_torch.types import PrimitiveBatch, PrimitiveSet

__all__ = ["LocalizationResult", "LocalizerEvent", "Matcher", "StageSeconds"]


class Matcher(Protocol):
    def __call__(
        self,
        ground: PrimitiveSet,
        aerial: PrimitiveBatch,
        *,
        rotation_prior: torch.Tensor | float | None,
        config: object,
        generator: torch.Generator | None,
    ) -> Hypotheses: ...


@dataclass(frozen=True)
class LocalizerEvent:
    """What happened when one submap was added (for progress output and the run log)."""

    submap_index: int
    time: float
    state: Literal["pre", "post"]  # state after this submap
    n_patches: int  # patches this submap was matched against
    n_hypotheses: int  # its candidates (valid hypotheses with enough associations)
    n_candidates: int  # candidates in the pool
    n_inliers: int  # inliers of the pool after this submap
    attempted: bool  # a fix attempt ran
    fix_committed: bool  # the global fix was committed on this submap
    seconds: float
    fix_revoked: bool = False  # the submaps since the fix failed its gate: back to the global search
    fix_doubted: bool = False  # they failed it, not yet enough times in a row: the estimate is withheld


@dataclass(frozen=True)
class LocalizationResult:
    """Final and incremental trajectories at every frame time; NaN where there is no estimate."""

    frame_times: np.ndarray  # (N,)
    T_world_base: np.ndarray  # (N, 4, 4) final optimized poses (NaN when not localized)
    covariance: np.ndarray | None  # (N, 3, 3) marginal covariance of world (x, y, yaw), or None
    T_world_base_incremental: np.ndarray  # (N, 4, 4) online estimate, NaN before the fix
    localized: bool  # the final inlier set passes the fix gate
    inliers: LoopClosureCandidates  # the final inlier loop closures
    fix_submap_index: int | None  # submap on which the online fix was committed
    fix_time: float | None  # time at which that fix became available
    submap_hypotheses: dict[int, LoopClosureCandidates]  # candidates of each submap's first matching
    submap_matching_mode: dict[int, str]  # how: "place_recognition" (before the fix) or "rotation_prior"
    final_hypotheses: LoopClosureCandidates  # every submap re-matched in the final pass (empty without it)
    events: list[LocalizerEvent]
    timings: dict[str, float]  # seconds per stage: matching, consistency, pose_graph
    rejected_because: str | None = None  # a solution passed the fix gate but failed the sanity gate (why)
    # (N, 3, 3) covariance of the online estimate's world (x, y, yaw), NaN before the fix; None
    # without the online updates' covariances
    covariance_incremental: np.ndarray | None = None

    @property
    def final_trajectory(self) -> Trajectory | None:
        return Trajectory(self.frame_times, self.T_world_base) if self.localized else None

    @property
    def incremental_frames(self) -> np.ndarray:
        """(N,) bool: the frames with an online estimate (from the fix on)."""
        return np.isfinite(self.T_world_base_incremental[:, 0, 0])

    @property
    def incremental_trajectory(self) -> Trajectory | None:
        """The online estimate from the fix on (None without a fix)."""
        ok = self.incremental_frames
        if not ok.any():
            return None
        return Trajectory(self.frame_times[ok], self.T_world_base_incremental[ok])


@dataclass
class StageSeconds:
    """Seconds the localizer spent per stage (its result's `timings`)."""

    seconds: dict[str, float] = field(
        default_factory=lambda: {"matching": 0.0, "consistency": 0.0, "pose_graph": 0.0}
    )

    def add(self, name: str, start: float) -> None:
        self.seconds[name] += time.perf_counter() - start

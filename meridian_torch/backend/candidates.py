"""Loop-closure candidates: every matching hypothesis as a measured world pose of the robot.

A hypothesis T_world_odom of submap k against patch p becomes the candidate
T_world_base = T_world_odom * T_odom_base(t_k) in SE(2), with its probability and its
quality q = probability / (best probability of the submap over every patch of its matching
call), or of the same (submap, patch) pair (the reference's "frequency-ratio"). Poses are
float64 (3, 3) SE(2) matrices.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Literal

import torch
from torch import Tensor

from meridian_torch.geometry.se2 import se2_from_se3
from meridian_torch.matching.hypotheses import Hypotheses
from meridian_torch.types import GroundSubmap

__all__ = ["LoopClosureCandidates", "candidates_from_hypotheses"]


@dataclass(frozen=True)
class LoopClosureCandidates:
    """N candidates; every field has N rows (float64 / int64 tensors on the CPU)."""

    submap_index: Tensor  # (N,) int64, GroundSubmap.index
    patch_index: Tensor  # (N,) int64, index into the aerial map's patches
    time: Tensor  # (N,) float64 submap time, seconds
    path_length_m: Tensor  # (N,) float64 odometry path length at the submap time
    T_odom_base: Tensor  # (N, 3, 3) odometry pose of the base at the submap time
    T_world_base: Tensor  # (N, 3, 3) the measured world pose of the base
    probability: Tensor  # (N,) hypothesis probability (cluster weight / particles)
    quality: Tensor  # (N,) probability relative to the best of its (submap, patch) pair, in (0, 1]
    n_associations: Tensor  # (N,) int64 associations of the hypothesis

    def __len__(self) -> int:
        return int(self.submap_index.shape[0])

    def select(self, index: Tensor) -> LoopClosureCandidates:
        """The candidates at `index` (bool mask or int64 indices)."""
        return LoopClosureCandidates(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def translated(self, dxy: tuple[float, float]) -> LoopClosureCandidates:
        """The same candidates with their world positions moved by `dxy` (change of world origin)."""
        T = self.T_world_base.clone()
        T[:, 0, 2] += dxy[0]
        T[:, 1, 2] += dxy[1]
        return replace(self, T_world_base=T)

    @staticmethod
    def concat(parts: list[LoopClosureCandidates]) -> LoopClosureCandidates:
        parts = [p for p in parts if len(p)] or [LoopClosureCandidates.empty()]
        return LoopClosureCandidates(
            **{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(parts[0])}
        )

    @staticmethod
    def empty() -> LoopClosureCandidates:
        f64, i64 = torch.float64, torch.int64
        return LoopClosureCandidates(
            submap_index=torch.zeros(0, dtype=i64),
            patch_index=torch.zeros(0, dtype=i64),
            time=torch.zeros(0, dtype=f64),
            path_length_m=torch.zeros(0, dtype=f64),
            T_odom_base=torch.zeros(0, 3, 3, dtype=f64),
            T_world_base=torch.zeros(0, 3, 3, dtype=f64),
            probability=torch.zeros(0, dtype=f64),
            quality=torch.zeros(0, dtype=f64),
            n_associations=torch.zeros(0, dtype=i64),
        )


def candidates_from_hypotheses(
    hypotheses: Hypotheses, submap: GroundSubmap, patch_index: Tensor, *, min_associations: int,
    quality_scope: Literal["submap", "patch"],
) -> LoopClosureCandidates:
    """The valid hypotheses (P, L) of one submap against the patches `patch_index` (P,) as candidates.

    Hypotheses with fewer than `min_associations` associations or zero probability are dropped.
    The quality is computed over the valid hypotheses before that filter: relative to the best of
    all P patches (`quality_scope` "submap": verified probabilities compare across patches, so a
    decoy patch's best hypothesis no longer counts as much as the true patch's), or of each patch
    ("patch", the reference's frequency ratio: the top hypothesis of every pair has q = 1).
    """
    n_patches, n_hyp = hypotheses.valid.shape
    valid = hypotheses.valid.cpu()
    prob = hypotheses.probability.detach().cpu().to(torch.float64).masked_fill(~valid, 0.0)
    best = prob.amax(dim=1, keepdim=True)
    if quality_scope == "submap":
        best = best.amax(dim=0, keepdim=True) if len(best) else best
    quality = torch.where(best > 0, prob / best.clamp_min(1e-300), torch.zeros_like(prob))
    n_assoc = hypotheses.association_mask.cpu().sum(-1)
    keep = valid & (n_assoc >= min_associations) & (prob > 0)
    T_odom_base = se2_from_se3(submap.T_odom_base)
    T_world_base = hypotheses.T_world_odom.detach().cpu().to(torch.float64) @ T_odom_base
    n = int(keep.sum())
    patches = torch.as_tensor(patch_index, dtype=torch.int64).cpu()[:, None].expand(n_patches, n_hyp)
    return LoopClosureCandidates(
        submap_index=torch.full((n,), submap.index, dtype=torch.int64),
        patch_index=patches[keep],
        time=torch.full((n,), float(submap.time), dtype=torch.float64),
        path_length_m=torch.full((n,), float(submap.path_length_m), dtype=torch.float64),
        T_odom_base=T_odom_base.expand(n, 3, 3).clone(),
        T_world_base=T_world_base[keep],
        probability=prob[keep],
        quality=quality[keep],
        n_associations=n_assoc[keep].to(torch.int64),
    )

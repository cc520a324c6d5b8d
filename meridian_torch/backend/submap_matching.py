"""Which aerial patches a submap is matched against, and the matching itself, for the localizer:
place recognition before the fix (exhaustive, coarse search or global descriptors), the patches
near a predicted position after it, and the matcher's hypotheses turned into loop-closure
candidates. One seeded generator drives every matching call, in the localizer's order."""

from __future__ import annotations

import time

import numpy as np
import torch

from meridian_torch.backend.candidates import LoopClosureCandidates, candidates_from_hypotheses
from meridian_torch.backend.results import Matcher, StageSeconds
from meridian_torch.config import MeridianConfig
from meridian_torch.core.timing import stage
from meridian_torch.errors import ConfigError
from meridian_torch.matching.place_recognition import (
    CoarseSearch,
    reads_global_descriptors,
    resolved_mode,
    select_patches,
    stack_similarity,
)
from meridian_torch.types import AerialMap, GroundSubmap

__all__ = ["SubmapMatching"]


class SubmapMatching:
    """Patch selection and matching of submaps against one aerial map (map frame, its device)."""

    def __init__(
        self, aerial_map: AerialMap, cfg: MeridianConfig, matcher: Matcher, seed: int, timer: StageSeconds
    ) -> None:
        self.aerial_map = aerial_map
        self.cfg = cfg
        self.timer = timer
        self._matcher = matcher
        device = aerial_map.primitives.points_xy.device
        self._generator = torch.Generator(device=device).manual_seed(seed)
        self._patch_bounds = torch.as_tensor(aerial_map.patches.bounds_xy, dtype=torch.float64)
        self._coarse: CoarseSearch | None = None  # built on the first submap that needs it

    def match(
        self, submap: GroundSubmap, patches: torch.Tensor, rotation_prior: float | torch.Tensor | None
    ) -> LoopClosureCandidates:
        if len(patches) == 0:
            return LoopClosureCandidates.empty()
        start = time.perf_counter()
        with stage("matching"):
            aerial = self.aerial_map.primitives.select(patches)
            ground = submap.primitives.to(device=aerial.points_xy.device, dtype=aerial.points_xy.dtype)
            hyps = self._matcher(
                ground, aerial, rotation_prior=rotation_prior, config=self.cfg.matching, generator=self._generator
            )
        self.timer.add("matching", start)
        return candidates_from_hypotheses(
            hyps, submap, patches, min_associations=self.cfg.backend.min_associations,
            quality_scope=self.cfg.backend.quality_scope,
        )

    def place_recognition_patches(self, submap: GroundSubmap) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The patches to match `submap` against before the fix, and their rotation priors: the
        coarse chain's yaw at each patch (`coarse_yaw_prior`), or None (free rotation)."""
        pr = self.cfg.matching.place_recognition
        n_patches = len(self.aerial_map)
        similarity = None
        if reads_global_descriptors(pr, n_patches, self.aerial_map.global_descriptor_backend):
            frames = submap.frame_descriptors.to(self.aerial_map.global_descriptors)
            if len(frames) and frames.shape[1] != self.aerial_map.global_descriptors.shape[1]:
                raise ConfigError(
                    f"submap {submap.index}: its frames' global descriptors have {frames.shape[1]} dimensions, the "
                    f"aerial map's {self.aerial_map.global_descriptors.shape[1]}: they come from different describers"
                )
            valid = torch.ones(1, frames.shape[0], dtype=torch.bool, device=frames.device)
            similarity = stack_similarity(frames[None], valid, self.aerial_map.global_descriptors)
        coarse_scores = coarse_yaw = None
        if resolved_mode(pr, n_patches) == "coarse":
            if self._coarse is None:
                with stage("coarse map"):
                    self._coarse = CoarseSearch(self.aerial_map.primitives, self._patch_bounds, pr.coarse)
            with stage("coarse search"):
                centre = torch.as_tensor(submap.T_odom_base[:2, 3])
                priors = self._coarse.add_submap(submap.primitives, centre)
                coarse_scores, coarse_yaw = priors.score[None], priors.yaw
        idx, ok = select_patches(pr, 1, n_patches, similarity=similarity, coarse_scores=coarse_scores)
        patches = idx[0][ok[0]].cpu()
        return patches, coarse_yaw[patches].double() if pr.coarse_yaw_prior and coarse_yaw is not None else None

    def near_patches(self, xy: np.ndarray) -> list[torch.Tensor]:
        """Patches near each predicted position (S, 2), largest disk overlap first."""
        pr = self.cfg.matching.place_recognition.model_copy(update={"mode": "near"})
        idx, ok = select_patches(
            pr,
            len(xy),
            len(self.aerial_map),
            predicted_xy=torch.as_tensor(xy, dtype=torch.float64),
            patch_bounds_xy=self._patch_bounds,
        )
        return [i[o] for i, o in zip(idx, ok)]

"""Patch selection by global descriptors, exhaustively or near a position (batched over submaps).

- global: the top-K patches by the maximum cosine similarity between the patch descriptor and
  any descriptor of the submap's frame stack (the paper's place recognition);
- exhaustive: every patch (small maps, where matching all is affordable);
- coarse: the top-K patches by the coarse search's scores (`place_recognition.coarse`);
- auto: exhaustive up to `exhaustive_max_patches` patches, else coarse;
- near: the patches whose squares overlap most with a disk around a predicted position
  (after a global fix).
"""

from __future__ import annotations

import torch

from meridian_torch.config.matching import PlaceRecognitionConfig

__all__ = ["stack_similarity", "select_patches", "disk_overlap", "resolved_mode"]

_DISK_SAMPLES = 32  # per axis: the disk's overlap with a box is estimated on a 32 x 32 grid


def stack_similarity(
    frame_descriptors: torch.Tensor, frame_valid: torch.Tensor, patch_descriptors: torch.Tensor
) -> torch.Tensor:
    """(S, F, D) submap frame stacks with (S, F) validity vs (P, D) patches -> (S, P) max cosine.

    Submaps without any valid frame score -inf against every patch.
    """
    frames = torch.nn.functional.normalize(frame_descriptors, dim=-1)
    patches = torch.nn.functional.normalize(patch_descriptors, dim=-1)
    cos = torch.einsum("sfd,pd->sfp", frames, patches)
    cos = cos.masked_fill(~frame_valid[..., None], float("-inf"))
    return cos.amax(dim=1)


def disk_overlap(centres_xy: torch.Tensor, radius_m: float, bounds_xy: torch.Tensor) -> torch.Tensor:
    """Fraction of each disk (S, 2 centres) inside each box (P, 4: x_min, x_max, y_min, y_max) -> (S, P)."""
    u = (torch.arange(_DISK_SAMPLES, dtype=centres_xy.dtype, device=centres_xy.device) + 0.5) / _DISK_SAMPLES * 2 - 1
    gx, gy = torch.meshgrid(u, u, indexing="xy")
    inside = gx.square() + gy.square() <= 1.0
    offsets = torch.stack([gx[inside], gy[inside]], dim=-1) * radius_m  # (Q, 2)
    pts = centres_xy[:, None, :] + offsets[None]  # (S, Q, 2)
    b = bounds_xy.to(pts)
    x, y = pts[..., 0:1], pts[..., 1:2]  # (S, Q, 1) against (P,)
    in_box = (x >= b[:, 0]) & (x <= b[:, 1]) & (y >= b[:, 2]) & (y <= b[:, 3])  # (S, Q, P)
    return in_box.to(pts.dtype).mean(dim=1)


def resolved_mode(cfg: PlaceRecognitionConfig, n_patches: int) -> str:
    """The mode `cfg` means on a map of `n_patches` patches ('auto' becomes 'exhaustive' or 'coarse')."""
    if cfg.mode != "auto":
        return cfg.mode
    return "exhaustive" if n_patches <= cfg.exhaustive_max_patches else "coarse"


def select_patches(
    cfg: PlaceRecognitionConfig,
    n_submaps: int,
    n_patches: int,
    *,
    similarity: torch.Tensor | None = None,
    coarse_scores: torch.Tensor | None = None,
    predicted_xy: torch.Tensor | None = None,
    patch_bounds_xy: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Patch indices (S, K) and their validity (S, K) for S = n_submaps submaps, by `cfg.mode`.

    'global' needs `similarity` (S, P) from `stack_similarity`; 'coarse' needs `coarse_scores` (S, P)
    (`CoarsePriors.score`); 'near' needs `predicted_xy` (S, 2)
    and `patch_bounds_xy` (P, 4); 'exhaustive' needs only `n_patches`; 'auto' needs what the mode
    it resolves to needs (`resolved_mode`). Indices are sorted best first; invalid entries (patches
    with -inf similarity or no overlap) have validity False.
    """
    mode = resolved_mode(cfg, n_patches)
    if mode == "exhaustive":
        idx = torch.arange(n_patches).expand(n_submaps, n_patches)
        return idx, torch.ones_like(idx, dtype=torch.bool)
    if mode == "global":
        if similarity is None:
            raise ValueError("place recognition mode 'global' needs the similarity matrix")
        k = min(cfg.k_global, similarity.shape[1])
        score, idx = similarity.topk(k, dim=1)
        return idx, torch.isfinite(score)
    if mode == "coarse":
        if coarse_scores is None:
            raise ValueError("place recognition mode 'coarse' needs the coarse search's patch scores")
        score, idx = coarse_scores.topk(min(cfg.k_coarse, coarse_scores.shape[1]), dim=1)
        return idx, torch.isfinite(score)
    if predicted_xy is None or patch_bounds_xy is None:
        raise ValueError("place recognition mode 'near' needs predicted_xy and patch_bounds_xy")
    overlap = disk_overlap(predicted_xy, cfg.near_radius_m, patch_bounds_xy)
    k = min(cfg.near_patches, overlap.shape[1])
    score, idx = overlap.topk(k, dim=1)
    return idx, score > 0

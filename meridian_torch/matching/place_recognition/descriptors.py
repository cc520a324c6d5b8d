"""Patch selection by global descriptors, exhaustively or near a position (batched over submaps).

- global: the top-K patches by the maximum cosine similarity between the patch descriptor and
  any descriptor of the submap's frame stack (the paper's place recognition);
- exhaustive: every patch (small maps, where matching all is affordable);
- coarse: the top-K patches by the coarse search's scores (`place_recognition.coarse`), fused
  with the global descriptors' ranking when these carry place information (`fuses_global`);
- auto: exhaustive up to `exhaustive_max_patches` patches, else coarse;
- near: the patches whose squares overlap most with a disk around a predicted position
  (after a global fix).
"""

from __future__ import annotations

import torch

from meridian_torch.config.matching import PlaceRecognitionConfig

__all__ = [
    "NEURAL_GLOBAL_BACKENDS", "disk_overlap", "fuses_global", "rank_fusion", "reads_global_descriptors",
    "resolved_mode", "select_patches", "stack_similarity",
]

_DISK_SAMPLES = 32  # per axis: the disk's overlap with a box is estimated on a 32 x 32 grid
_OVERLAP_ELEMENTS = 1 << 20  # (disk, axis sample, box) tests per chunk of disks
# Global describers whose descriptors rank places (the classical one ranks the true patch at chance).
NEURAL_GLOBAL_BACKENDS = ("anyloc", "gem")


def stack_similarity(
    frame_descriptors: torch.Tensor, frame_valid: torch.Tensor, patch_descriptors: torch.Tensor
) -> torch.Tensor:
    """(S, F, D) submap frame stacks with (S, F) validity vs (P, D) patches -> (S, P) max cosine.

    Submaps without any valid frame score -inf against every patch.
    """
    if frame_descriptors.shape[1] == 0:
        return frame_descriptors.new_full((frame_descriptors.shape[0], patch_descriptors.shape[0]), float("-inf"))
    frames = torch.nn.functional.normalize(frame_descriptors, dim=-1)
    patches = torch.nn.functional.normalize(patch_descriptors, dim=-1)
    cos = torch.einsum("sfd,pd->sfp", frames, patches)
    cos = cos.masked_fill(~frame_valid[..., None], float("-inf"))
    return cos.amax(dim=1)


def disk_overlap(centres_xy: torch.Tensor, radius_m: float, bounds_xy: torch.Tensor) -> torch.Tensor:
    """Fraction of each disk (S, 2 centres) inside each box (P, 4: x_min, x_max, y_min, y_max) -> (S, P):
    the share of the centres of a 32 x 32 grid over the disk's square that lie in the disk and the box.

    The grid is a product of x and y samples, and a box is a product of x and y intervals, so a
    sample is inside iff its x and its y are: the counts come from (S, 32, P) tests per axis instead
    of (S, Q, P) tests per sample (a whole drive's submaps, as the final pass asks, held gigabytes),
    a chunk of disks at a time. Sums of ones are exact, so the fractions do not depend on either.
    """
    dtype, device = centres_xy.dtype, centres_xy.device
    u = (torch.arange(_DISK_SAMPLES, dtype=dtype, device=device) + 0.5) / _DISK_SAMPLES * 2 - 1
    in_disk = (u[:, None].square() + u[None, :].square() <= 1.0).to(dtype)  # (y sample, x sample)
    n_samples = in_disk.sum()
    offsets = u * radius_m
    b = bounds_xy.to(centres_xy)
    chunk = max(1, _OVERLAP_ELEMENTS // max(1, _DISK_SAMPLES * len(b)))
    fractions = []
    for centres in centres_xy.split(chunk):
        x = (centres[:, 0:1] + offsets)[..., None]  # (s, 32, 1) against (P,)
        y = (centres[:, 1:2] + offsets)[..., None]
        in_x = ((x >= b[:, 0]) & (x <= b[:, 1])).to(dtype)  # (s, 32, P)
        in_y = ((y >= b[:, 2]) & (y <= b[:, 3])).to(dtype)
        fractions.append(torch.einsum("ji,sip,sjp->sp", in_disk, in_x, in_y) / n_samples)
    return torch.cat(fractions)  # no disks: split still yields one empty chunk


def resolved_mode(cfg: PlaceRecognitionConfig, n_patches: int) -> str:
    """The mode `cfg` means on a map of `n_patches` patches ('auto' becomes 'exhaustive' or 'coarse')."""
    if cfg.mode != "auto":
        return cfg.mode
    return "exhaustive" if n_patches <= cfg.exhaustive_max_patches else "coarse"


def fuses_global(cfg: PlaceRecognitionConfig, n_patches: int, map_global_backend: str | None) -> bool:
    """Whether the coarse search's ranking is fused with the global descriptors' on this map: in
    'coarse' mode (also as 'auto' resolves it), by `cfg.global_fusion` ('auto': when the map's
    global descriptors come from one of `NEURAL_GLOBAL_BACKENDS`)."""
    if resolved_mode(cfg, n_patches) != "coarse" or cfg.global_fusion == "never":
        return False
    return cfg.global_fusion == "always" or map_global_backend in NEURAL_GLOBAL_BACKENDS


def reads_global_descriptors(cfg: PlaceRecognitionConfig, n_patches: int, map_global_backend: str | None) -> bool:
    """Whether place recognition on this map compares the submaps' frame descriptors with the
    map's global descriptors ('global' mode or a fused coarse search)."""
    return resolved_mode(cfg, n_patches) == "global" or fuses_global(cfg, n_patches, map_global_backend)


def rank_fusion(scores: list[torch.Tensor], k: float) -> torch.Tensor:
    """Reciprocal rank fusion of rankings of the same P patches: list of (S, P) scores (higher is
    better) -> (S, P) sum over the rankings of 1 / (k + rank), rank 1 the best (ties: the lower
    patch index first). Non-finite scores are unranked and add nothing; a patch unranked in
    every ranking scores -inf."""
    fused = torch.zeros_like(scores[0], dtype=torch.float64)
    ranked_any = torch.zeros_like(scores[0], dtype=torch.bool)
    for score in scores:
        finite = torch.isfinite(score)
        order = torch.sort(torch.where(finite, score, float("-inf")), dim=1, descending=True, stable=True).indices
        rank = torch.empty_like(order)
        rank.scatter_(1, order, torch.arange(1, order.shape[1] + 1, device=order.device).expand_as(order))
        fused = fused + torch.where(finite, 1.0 / (k + rank.to(torch.float64)), 0.0)
        ranked_any |= finite
    return torch.where(ranked_any, fused, float("-inf"))


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
    (`CoarsePriors.score`), fused with `similarity` by `rank_fusion` when that is given too
    (`fuses_global` says when); 'near' needs `predicted_xy` (S, 2)
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
        if similarity is not None:
            coarse_scores = rank_fusion([coarse_scores, similarity], cfg.fusion_rank_constant)
        score, idx = coarse_scores.topk(min(cfg.k_coarse, coarse_scores.shape[1]), dim=1)
        return idx, torch.isfinite(score)
    if predicted_xy is None or patch_bounds_xy is None:
        raise ValueError("place recognition mode 'near' needs predicted_xy and patch_bounds_xy")
    overlap = disk_overlap(predicted_xy, cfg.near_radius_m, patch_bounds_xy)
    k = min(cfg.near_patches, overlap.shape[1])
    score, idx = overlap.topk(k, dim=1)
    return idx, score > 0

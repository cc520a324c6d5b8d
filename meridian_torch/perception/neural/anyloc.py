"""AnyLoc place-recognition descriptors: DINOv2 facet tokens aggregated by VLAD, or by GeM.

AnyLoc (paper setting): ViT-G/14, value facet of block 31, every token L2-normalized, VLAD over
32 cluster centres with hard cosine assignment, per-cluster (intra) normalization, then a global
L2 normalization. Vocabularies are AnyLoc's published `c_centers.pt` files (a bare (K, D) tensor)
or our own files from `fit_vocabulary`, which add the backbone, layer and facet they were fitted on.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from meridian_torch.core.kmeans import cosine_kmeans
from meridian_torch.errors import ModelWeightsError
from meridian_torch.perception.neural.dinov2 import (
    DinoVisionTransformer,
    Facet,
    center_crop_to_patch_multiple,
    imagenet_normalize,
    resize_to_patch_multiple,
)

__all__ = [
    "vlad",
    "gem",
    "anyloc_input",
    "AnyLocFacet",
    "VladHead",
    "Vocabulary",
    "load_vocabulary",
    "save_vocabulary",
    "fit_vocabulary",
]


def vlad(tokens: torch.Tensor, centers: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """VLAD of token sets (B, N, D) over centres (K, D) -> (B, K * D), L2-normalized.

    Each valid token goes to the centre of highest cosine similarity (the centres are normalized
    for this step only). Cluster k's residual is sum(assigned tokens) - count * centre_k; each
    residual is L2-normalized (intra-normalization), then the flattened vector is normalized.
    Empty clusters contribute zeros.
    """
    k = centers.shape[0]
    nearest = (tokens @ F.normalize(centers, dim=-1).T).argmax(dim=-1)  # (B, N)
    assign = (nearest[..., None] == torch.arange(k, device=tokens.device)).to(tokens.dtype)  # (B, N, K)
    if valid is not None:
        assign = assign * valid[..., None].to(tokens.dtype)
    sums = assign.transpose(1, 2) @ tokens  # (B, K, D)
    residuals = sums - assign.sum(dim=1)[..., None] * centers
    return F.normalize(F.normalize(residuals, dim=-1).flatten(1), dim=-1)


def gem(tokens: torch.Tensor, p: float, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Generalized mean over tokens (B, N, D) -> (B, D), L2-normalized (DINO-GeM, p = 3 in the reference).

    m = mean_n sign(f) |f|^p (= mean f^3 for p = 3), d = sign(m) |m|^(1/p) with |m| >= 1e-12.
    """
    powered = tokens.sign() * tokens.abs().pow(p)
    if valid is None:
        mean = powered.mean(dim=1)
    else:
        w = valid[..., None].to(tokens.dtype)
        mean = (powered * w).sum(dim=1) / w.sum(dim=1).clamp_min(1)
    return F.normalize(mean.sign() * mean.abs().clamp_min(1e-12).pow(1.0 / p), dim=-1)


def anyloc_input(images: torch.Tensor, resize_short_side_px: int | None) -> torch.Tensor:
    """AnyLoc preprocessing of RGB in [0, 1]: native resolution centre-cropped to multiples of 14,
    or (if `resize_short_side_px` is set) resized so both sides are multiples of 14."""
    if resize_short_side_px is None:
        return center_crop_to_patch_multiple(images)
    return resize_to_patch_multiple(images, resize_short_side_px)


class AnyLocFacet(nn.Module):
    """Export wrapper: RGB images in [0, 1] with sides multiple of 14 -> L2-normalized facet tokens (B, N, D).

    Only blocks 0..layer run.
    """

    def __init__(self, backbone: DinoVisionTransformer, layer: int, facet: Facet) -> None:
        super().__init__()
        if not -backbone.depth <= layer < backbone.depth:
            raise ValueError(f"layer {layer} out of range for a {backbone.depth}-block DINOv2")
        self.backbone = backbone
        self.layer = layer % backbone.depth
        self.facet = facet

    @property
    def dim(self) -> int:
        return self.backbone.embed_dim

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        tokens = self.backbone.facet(imagenet_normalize(images), self.layer, self.facet)
        return F.normalize(tokens, dim=-1)


class VladHead(nn.Module):
    """Export wrapper: tokens (B, N, D) -> VLAD vector (B, K * D) over fixed centres."""

    def __init__(self, centers: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("centers", centers.detach().clone())

    @property
    def dim(self) -> int:
        return self.centers.numel()

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        return vlad(tokens, self.centers)


@dataclass(frozen=True)
class Vocabulary:
    """VLAD cluster centres (K, D) and, when known, what they were fitted on."""

    centers: torch.Tensor
    architecture: str | None = None
    layer: int | None = None
    facet: str | None = None

    def check_fits(
        self, path: str | os.PathLike[str], *, dim: int, architecture: str, layer: int, facet: str
    ) -> None:
        """Raise ModelWeightsError (naming `path`) if these centres cannot describe the given tokens."""
        if self.centers.shape[1] != dim:
            raise ModelWeightsError(
                f"{path}: vocabulary centres have dimension {self.centers.shape[1]}, "
                f"but {architecture} tokens have dimension {dim}"
            )
        fitted = {"architecture": self.architecture, "layer": self.layer, "facet": self.facet}
        wanted = {"architecture": architecture, "layer": layer, "facet": facet}
        wrong = [f"{k} {v!r} (configured: {wanted[k]!r})" for k, v in fitted.items() if v not in (None, wanted[k])]
        if wrong:
            raise ModelWeightsError(f"{path}: vocabulary was fitted on other features: {', '.join(wrong)}")


def load_vocabulary(path: str | os.PathLike[str]) -> Vocabulary:
    """Read an AnyLoc `c_centers.pt` (a bare (K, D) tensor) or a file written by `save_vocabulary`."""
    path = Path(path)
    if not path.is_file():
        raise ModelWeightsError(f"vocabulary file not found: {path}")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # any reader failure means the file is not a usable vocabulary
        raise ModelWeightsError(f"{path}: not a readable vocabulary ({type(exc).__name__}: {exc})") from None
    meta: dict = {}
    if isinstance(data, dict):
        meta = {k: data.get(k) for k in ("architecture", "layer", "facet")}
        data = data.get("centers")
    if not (isinstance(data, torch.Tensor) and data.ndim == 2 and data.is_floating_point() and data.shape[0] > 0):
        raise ModelWeightsError(f"{path}: expected cluster centres as a non-empty (K, D) float tensor")
    if not torch.isfinite(data).all():
        raise ModelWeightsError(f"{path}: cluster centres contain NaN or infinite values")
    return Vocabulary(data.float(), **meta)


def save_vocabulary(path: str | os.PathLike[str], vocabulary: Vocabulary) -> None:
    """Write centres and their provenance atomically (readable with `torch.load(weights_only=True)`)."""
    from meridian_torch.io.atomic import atomic_path

    data = {"centers": vocabulary.centers.detach().cpu().contiguous()}
    for key in ("architecture", "layer", "facet"):
        if getattr(vocabulary, key) is not None:
            data[key] = getattr(vocabulary, key)
    with atomic_path(path) as tmp:
        torch.save(data, tmp)


def fit_vocabulary(
    facet: AnyLocFacet,
    images: Iterable[torch.Tensor],
    *,
    num_clusters: int,
    resize_short_side_px: int | None,
    seed: int,
    tokens_per_image: int | None = None,
    iterations: int = 100,
    progress: Callable[[int, int], None] | None = None,
    total: int = 0,
) -> torch.Tensor:
    """Cosine k-means centres (K, D) over the facet tokens of `images` (each (1, 3, H, W) in [0, 1]).

    `tokens_per_image` keeps a seeded random subset of each image's tokens (None: all), which bounds
    memory on large image sets. The same seed and images give the same centres.
    """
    generator = torch.Generator().manual_seed(seed)
    param = next(facet.parameters())
    collected = []
    with torch.inference_mode():
        for i, image in enumerate(images):
            tokens = facet(anyloc_input(image.to(param), resize_short_side_px)).flatten(0, 1).float().cpu()
            if tokens_per_image is not None and tokens.shape[0] > tokens_per_image:
                tokens = tokens[torch.randperm(tokens.shape[0], generator=generator)[:tokens_per_image]]
            collected.append(tokens)
            if progress is not None:
                progress(i + 1, total)
    if not collected:
        raise ValueError("fit_vocabulary needs at least one image")
    tokens = torch.cat(collected)
    if tokens.shape[0] < num_clusters:
        raise ValueError(f"{tokens.shape[0]} tokens are too few for {num_clusters} clusters")
    centers, _ = cosine_kmeans(tokens, num_clusters, iterations=iterations, generator=generator)
    return centers

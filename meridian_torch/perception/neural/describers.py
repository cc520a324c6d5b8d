"""DINOv2 back ends of the describer protocols: mask-pooled segment descriptors, AnyLoc-VLAD and GeM.

Models follow the images: each call moves its (shared) model to the images' device and dtype,
which is free when it is already there (and done outside inference mode, so the parameters stay
usable elsewhere).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from meridian_torch.perception.neural.anyloc import AnyLocFacet, VladHead, anyloc_input, gem
from meridian_torch.perception.neural.dinov2 import DinoDenseFeatures, resize_to_patch_multiple

__all__ = [
    "bilinear_upsampling_matrix",
    "masked_feature_pool",
    "DinoSegmentDescriber",
    "AnyLocGlobalDescriber",
    "GemGlobalDescriber",
]


def bilinear_upsampling_matrix(
    n_out: int, n_in: int, *, device: torch.device, dtype: torch.dtype
) -> torch.Tensor:
    """(n_out, n_in) matrix R with R @ v = F.interpolate(v, n_out, mode="linear", align_corners=False).

    Half-pixel centres: output i interpolates linearly between the two input samples around
    position (i + 0.5) * n_in / n_out - 0.5, clamped to the first and last sample.
    """
    dst = torch.arange(n_out, device=device, dtype=torch.float64)
    src = ((dst + 0.5) * (n_in / n_out) - 0.5).clamp_min(0)
    lo = src.floor().long().clamp_max(n_in - 1)
    hi = (lo + 1).clamp_max(n_in - 1)
    frac = src - lo
    r = torch.zeros(n_out, n_in, device=device, dtype=torch.float64)
    rows = torch.arange(n_out, device=device)
    r.index_put_((rows, lo), 1 - frac, accumulate=True)
    r.index_put_((rows, hi), frac, accumulate=True)
    return r.to(dtype)


def masked_feature_pool(features: torch.Tensor, masks: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean of bilinearly upsampled features over each mask, L2-normalized, without upsampling.

    features (B, C, h, w), masks (B, M, H, W) bool, valid (B, M) -> (B, M, C). Upsampling the
    features to H x W (half-pixel centres) and summing over a mask equals weighting the patch grid
    with R_y^T M R_x, so the full-resolution feature map is never built. Normalizing the sum equals
    normalizing the mean. Invalid or empty masks give zero rows.
    """
    h, w = features.shape[-2:]
    r_y = bilinear_upsampling_matrix(masks.shape[-2], h, device=features.device, dtype=features.dtype)
    r_x = bilinear_upsampling_matrix(masks.shape[-1], w, device=features.device, dtype=features.dtype)
    m = (masks & valid[..., None, None]).to(features.dtype)
    weights = r_y.T @ (m @ r_x)  # (B, M, h, w)
    return F.normalize(torch.einsum("bmhw,bchw->bmc", weights, features), dim=-1)


class DinoSegmentDescriber:
    """Segment descriptors: DINOv2 final patch features pooled over each mask (reference section 7).

    Images are resized so the short side is about `short_side_px` (256 in the reference) with
    both sides multiples of 14; masks stay at the input resolution.
    """

    def __init__(self, features: DinoDenseFeatures, *, short_side_px: int) -> None:
        self.features = features
        self.short_side_px = short_side_px
        self.dim = features.dim

    def describe(self, images: torch.Tensor, masks: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        model = self.features.to(images)  # outside inference mode: parameters must stay normal tensors
        with torch.inference_mode():
            dense = model(resize_to_patch_multiple(images, self.short_side_px))
            return masked_feature_pool(dense, masks, valid)


class AnyLocGlobalDescriber:
    """Place-recognition descriptors: L2-normalized facet tokens of one DINOv2 block, VLAD-aggregated."""

    def __init__(self, facet: AnyLocFacet, head: VladHead, *, resize_short_side_px: int | None) -> None:
        self.facet = facet
        self.head = head
        self.resize_short_side_px = resize_short_side_px
        self.dim = head.dim

    def describe(self, images: torch.Tensor) -> torch.Tensor:
        facet, head = self.facet.to(images), self.head.to(images)
        with torch.inference_mode():
            return head(facet(anyloc_input(images, self.resize_short_side_px)))


class GemGlobalDescriber:
    """Place-recognition descriptors: GeM over DINOv2 final patch features (the reference's dino-gem)."""

    def __init__(self, features: DinoDenseFeatures, *, short_side_px: int, p: float) -> None:
        self.features = features
        self.short_side_px = short_side_px
        self.p = p
        self.dim = features.dim

    def describe(self, images: torch.Tensor) -> torch.Tensor:
        model = self.features.to(images)
        with torch.inference_mode():
            dense = model(resize_to_patch_multiple(images, self.short_side_px))
            return gem(dense.flatten(2).transpose(1, 2), self.p)

"""Classical describers: masked means of `PixelFeatures` per segment, and generalized-mean pooling
over a spatial pyramid per image."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from meridian_torch.perception.classical.pixel_features import PixelFeatures, check_images

__all__ = ["ColourTextureDescriber", "ColourTextureGlobalDescriber", "masked_mean"]


def masked_mean(
    features: torch.Tensor, masks: torch.Tensor, mask_buffer: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Average one image's (C, H, W) features over its (M, H, W) masks with one einsum.

    `mask_buffer`, an (M, H, W) tensor of the features' dtype, takes the float copy of the masks
    (a caller describing many images reuses it). Returns (M, C) means (zeros for empty masks)
    and (M,) pixel counts.
    """
    w = features.new_empty(masks.shape) if mask_buffer is None else mask_buffer
    w.copy_(masks)
    area = w.sum(dim=(1, 2))
    summed = torch.einsum("chw,mhw->mc", features, w)
    return summed / area.clamp(min=1)[..., None], area


def _histogram_descriptor(
    hist: torch.Tensor, colour_channels: int, colour_weight: float, texture_weight: float
) -> torch.Tensor:
    """(..., C) pooled histograms -> (..., C) unit vectors.

    Each block is centred on the uniform histogram before normalizing: raw histograms are
    non-negative, so even unrelated ones have cosine ~0.5; centred, unrelated ones are near
    orthogonal and the cosine spans the range the matcher's thresholds expect.
    """
    colour, texture = hist[..., :colour_channels], hist[..., colour_channels:]
    colour = F.normalize(colour - colour.mean(dim=-1, keepdim=True), dim=-1)
    texture = F.normalize(texture - texture.mean(dim=-1, keepdim=True), dim=-1)
    return F.normalize(torch.cat([colour_weight * colour, texture_weight * texture], dim=-1), dim=-1)


class ColourTextureDescriber:
    """Per-segment descriptor: masked means of `PixelFeatures`, block-centred and L2-normalized.

    Implements `SegmentDescriber`; `dim` = hue_bins + 1 + texture_bins.
    """

    def __init__(self, features: PixelFeatures, *, colour_weight: float, texture_weight: float) -> None:
        self.features = features
        self.colour_weight = colour_weight
        self.texture_weight = texture_weight
        self.dim = features.channels

    @torch.no_grad()
    def describe(self, images: torch.Tensor, masks: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W), masks (B, M, H, W) bool, valid (B, M) -> (B, M, dim)."""
        check_images(images)
        b, _, h, w = images.shape
        if masks.shape[0] != b or masks.shape[2:] != (h, w) or valid.shape != masks.shape[:2]:
            raise ValueError(
                f"masks (B, M, H, W) and valid (B, M) must match images {tuple(images.shape)}, "
                f"got {tuple(masks.shape)} and {tuple(valid.shape)}"
            )
        # One image at a time: a batch's float masks, feature maps and their temporaries (about
        # 200 MB for 8 frames of 480 x 270 with 20 masks) would be fresh allocations that the
        # allocator maps and unmaps on every batch, and their page faults cost as much as the
        # arithmetic; one image's fit in reused heap memory. At one torch thread the numbers are
        # bitwise those of the whole batch.
        hist = images.new_empty((b, masks.shape[1], self.dim))
        area = images.new_empty(masks.shape[:2])
        mask_buffer = images.new_empty(masks.shape[1:])
        for i in range(b):
            hist[i], area[i] = masked_mean(self.features(images[i : i + 1])[0], masks[i], mask_buffer)
        desc = _histogram_descriptor(hist, self.features.colour_channels, self.colour_weight, self.texture_weight)
        keep = valid & (area > 0)
        return torch.where(keep[..., None], desc, torch.zeros_like(desc))


class ColourTextureGlobalDescriber:
    """Image descriptor: generalized-mean pooled `PixelFeatures` over a spatial pyramid.

    Level 0 pools the whole image (rotation invariant, as aerial patches have arbitrary
    heading); level l adds a 2^l x 2^l grid. Each cell is block-centred and normalized like a
    segment descriptor, the cells are concatenated and the result L2-normalized.
    Implements `GlobalDescriber`; `dim` = channels x sum_l 4^l.
    """

    def __init__(
        self,
        features: PixelFeatures,
        *,
        pyramid_levels: int,
        gem_p: float,
        colour_weight: float,
        texture_weight: float,
    ) -> None:
        self.features = features
        self.pyramid_levels = pyramid_levels
        self.gem_p = gem_p
        self.colour_weight = colour_weight
        self.texture_weight = texture_weight
        self.dim = features.channels * sum(4**level for level in range(pyramid_levels))

    @torch.no_grad()
    def describe(self, images: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W) -> (B, dim)."""
        check_images(images)
        # one image at a time, as the segment describer (page faults)
        cell = torch.cat([self._pyramid_cells(images[i : i + 1]) for i in range(images.shape[0])])
        desc = _histogram_descriptor(cell, self.features.colour_channels, self.colour_weight, self.texture_weight)
        return F.normalize(desc.flatten(1), dim=-1)

    def _pyramid_cells(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> (B, cells, C) GeM-pooled features of every pyramid cell, level by level."""
        feats = self.features(images).clamp(min=1e-6) ** self.gem_p
        cells = []
        for level in range(self.pyramid_levels):
            pooled = F.adaptive_avg_pool2d(feats, 2**level) ** (1.0 / self.gem_p)  # (B, C, g, g)
            cells.append(pooled.flatten(2).transpose(1, 2))  # (B, g*g, C)
        return torch.cat(cells, dim=1)

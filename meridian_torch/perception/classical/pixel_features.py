"""Per-pixel features of the classical describers: soft hue and texture histograms, and the image
checks and blur they rest on."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["PixelFeatures", "check_images"]


def check_images(images: torch.Tensor) -> None:
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"images must have shape (B, 3, H, W), got {tuple(images.shape)}")
    if not images.is_floating_point():
        raise ValueError(f"images must be a float tensor in [0, 1], got {images.dtype}")


def _gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (B, C, H, W) with replicate padding; identity for sigma <= 0.

    Shift-and-add over the kernel taps (a loop over 2r + 1 taps, not over pixels): on the CPU
    this is 5x faster than a depthwise convolution for images of few channels (8 x 480 x 270,
    sigma 3: 18 vs 92 ms) and agrees with it to float32 rounding."""
    if sigma <= 0:
        return x
    r = max(1, math.ceil(3 * sigma))
    t = torch.arange(-r, r + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    taps = (k / k.sum()).tolist()
    h, w = x.shape[-2:]
    x = F.pad(x, (r, r, r, r), mode="replicate")
    rows = x[..., :, 0:w] * taps[0]
    for i in range(1, 2 * r + 1):
        rows.add_(x[..., :, i : i + w], alpha=taps[i])
    out = rows[..., 0:h, :] * taps[0]
    for i in range(1, 2 * r + 1):
        out.add_(rows[..., i : i + h, :], alpha=taps[i])
    return out


def _soft_bins(value: torch.Tensor, bins: int, circular: bool, out: torch.Tensor | None = None) -> torch.Tensor:
    """(B, H, W) values in bin units -> (B, bins, H, W) triangular soft assignment summing to 1
    (written into `out` when given; in place, one full-size buffer)."""
    centres = torch.arange(bins, device=value.device, dtype=value.dtype).view(1, -1, 1, 1)
    d = torch.sub(value[:, None], centres, out=out) if out is not None else value[:, None] - centres
    d.abs_()
    if circular:
        torch.minimum(d, bins - d, out=d)
    # Half-width 1.5 bins spreads each pixel over ~3 bins, so small hue shifts move mass smoothly.
    d.div_(1.5).neg_().add_(1.0).clamp_(min=0)
    return d.div_(d.sum(dim=1, keepdim=True))


class PixelFeatures:
    """Per-pixel soft histograms of hue (plus an achromatic bin) and of relative gradient magnitude.

    Chromaticity rgb / (r + g + b) removes brightness, so shading, exposure and the different
    lighting of a canopy seen from above and a tree seen from the side change it little. Pixels
    with low saturation (grey roads, roofs, shadows) go to the achromatic bin. Texture is the
    gradient magnitude divided by the local mean brightness, again brightness invariant.

    Shape:
        images (B, 3, H, W) -> (B, C, H, W) with C = hue_bins + 1 + texture_bins; each of the
        two blocks sums to 1 per pixel.
    """

    def __init__(
        self,
        *,
        hue_bins: int,
        saturation_knee: float,
        texture_bins: int,
        texture_max: float,
        texture_smoothing_px: float,
    ) -> None:
        self.hue_bins = hue_bins
        self.saturation_knee = saturation_knee
        self.texture_bins = texture_bins
        self.texture_max = texture_max
        self.texture_smoothing_px = texture_smoothing_px

    @property
    def channels(self) -> int:
        return self.hue_bins + 1 + self.texture_bins

    @property
    def colour_channels(self) -> int:
        return self.hue_bins + 1

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        check_images(images)
        x = images.clamp(0, 1)
        r, g, b = x.unbind(1)
        total = r + g + b
        # The offset makes very dark pixels achromatic instead of amplifying their noise.
        denom = total + 0.03
        cr, cg, cb = r / denom, g / denom, b / denom
        o1 = (cr - cg) / math.sqrt(2.0)
        o2 = (cr + cg - 2 * cb) / math.sqrt(6.0)
        sat = torch.sqrt(o1**2 + o2**2)
        chroma = (sat / self.saturation_knee).clamp(max=1.0)
        hue = (torch.atan2(o2, o1) % (2 * math.pi)) * (self.hue_bins / (2 * math.pi))
        # every block is written into one output buffer (no concatenation copies)
        out = images.new_empty((images.shape[0], self.channels) + images.shape[2:])
        hb = self.hue_bins
        _soft_bins(hue, hb, True, out=out[:, :hb]).mul_(chroma[:, None])
        torch.sub(1.0, chroma, out=out[:, hb])

        intensity = _gaussian_blur((total / 3)[:, None], self.texture_smoothing_px)
        gy = intensity[..., 1:, :] - intensity[..., :-1, :]
        gx = intensity[..., :, 1:] - intensity[..., :, :-1]
        gy = F.pad(gy, (0, 0, 0, 1), mode="replicate")
        gx = F.pad(gx, (0, 1, 0, 0), mode="replicate")
        local = _gaussian_blur(intensity, 3.0)
        rel = torch.sqrt(gx**2 + gy**2)[:, 0] / (local[:, 0] + 0.02)
        level = (rel / self.texture_max).clamp(max=1.0) * (self.texture_bins - 1)
        _soft_bins(level, self.texture_bins, False, out=out[:, hb + 1 :])
        return out

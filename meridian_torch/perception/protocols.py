"""The perception interfaces every segmentation and description back end implements.

Conventions shared by all back ends:

* images are `(B, 3, H, W)` RGB float tensors in [0, 1];
* results live on the images' device and, for floating outputs, have the images' dtype;
* segment sets are padded over the batch: image b owns the masks `masks[b, valid[b]]`, padded
  entries are all-False masks with score 0;
* descriptors are L2-normalized and compared by cosine similarity; padded entries are zeros.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import torch

__all__ = ["Segmentation", "Segmenter", "SegmentDescriber", "GlobalDescriber"]


@dataclass(frozen=True)
class Segmentation:
    """Segments of a batch of images, padded to the largest segment count M.

    Shape:
        masks: (B, M, H, W) bool, at the input image resolution.
        scores: (B, M) float, back-end confidence in [0, 1] (0 for padding).
        valid: (B, M) bool, False for padding.
        labels: (B, H, W) int64 or None. When the masks partition each image (the classical back
            end), this is the index of each pixel's mask, and the valid masks come first. Where
            there are labels, readers may go over the pixels once instead of over every mask.
    """

    masks: torch.Tensor
    scores: torch.Tensor
    valid: torch.Tensor
    labels: torch.Tensor | None = None

    @property
    def num_segments(self) -> torch.Tensor:
        """(B,) int64 number of valid segments per image."""
        return self.valid.sum(dim=1)


@runtime_checkable
class Segmenter(Protocol):
    """Splits images into segments (objects and region pieces)."""

    def segment(self, images: torch.Tensor, meters_per_pixel: float | None) -> Segmentation:
        """Segment `images` (B, 3, H, W) in [0, 1].

        `meters_per_pixel` is the ground sample distance of aerial images, which lets a back end
        keep its segment sizes constant in square metres. Perspective (ground camera) frames have
        no single scale and pass None.
        """
        ...


@runtime_checkable
class SegmentDescriber(Protocol):
    """Describes each masked segment with an L2-normalized vector of length `dim`."""

    dim: int

    def describe(self, images: torch.Tensor, masks: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W), masks (B, M, H, W) bool, valid (B, M) bool -> (B, M, dim).

        Rows of invalid (or empty) masks are zeros; all others have unit norm.
        """
        ...


@runtime_checkable
class GlobalDescriber(Protocol):
    """Describes whole images with an L2-normalized vector of length `dim` (place recognition)."""

    dim: int

    def describe(self, images: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W) -> (B, dim)."""
        ...

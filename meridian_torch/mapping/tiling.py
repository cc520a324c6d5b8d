"""Tiling an orthophoto into overlapping square patches that cover every pixel.

Patch corners step by the stride (patch size x (1 - overlap)); when the image size is not a
whole number of strides, one more row/column of patches is aligned to the right/bottom border,
so edge areas are never dropped (the reference implementation drops them). Images smaller than
a patch give patches clipped to the image.
"""

from __future__ import annotations

import numpy as np

from meridian_torch.types import PatchGrid

__all__ = ["tile_image", "crop_offsets"]


def _starts(length_px: int, patch_px: int, stride_px: int) -> np.ndarray:
    if length_px <= patch_px:
        return np.array([0], dtype=np.int64)
    starts = np.arange(0, length_px - patch_px + 1, stride_px, dtype=np.int64)
    if starts[-1] != length_px - patch_px:
        starts = np.append(starts, length_px - patch_px)
    return starts


def crop_offsets(length: int, crop: int) -> np.ndarray:
    """Offsets of `ceil(length / crop)` crops of size `crop` spread evenly over `length`."""
    if crop >= length:
        return np.array([0], dtype=np.int64)
    n = int(np.ceil(length / crop))
    return np.round(np.arange(n) * (length - crop) / (n - 1)).astype(np.int64)


def tile_image(
    width_px: int,
    height_px: int,
    meters_per_pixel: float,
    origin_xy: tuple[float, float],
    patch_size_m: float,
    overlap: float,
) -> PatchGrid:
    """Patches of `patch_size_m` with `overlap` covering a north-up image (north-up, `origin_xy` = world x, y of its top-left corner)."""
    if width_px < 1 or height_px < 1:
        raise ValueError(f"image size must be positive, got {width_px}x{height_px}")
    patch_px = max(1, int(round(patch_size_m / meters_per_pixel)))
    stride_px = max(1, int(round(patch_px * (1.0 - overlap))))
    cols = _starts(width_px, patch_px, stride_px)
    rows = _starts(height_px, patch_px, stride_px)
    jj, ii = np.meshgrid(np.arange(len(rows)), np.arange(len(cols)), indexing="ij")
    c0 = cols[ii.ravel()]
    r0 = rows[jj.ravel()]
    c1 = np.minimum(c0 + patch_px, width_px)
    r1 = np.minimum(r0 + patch_px, height_px)
    x0, y0 = origin_xy
    bounds = np.stack(
        [x0 + c0 * meters_per_pixel, x0 + c1 * meters_per_pixel, y0 - r1 * meters_per_pixel, y0 - r0 * meters_per_pixel],
        axis=1,
    )
    centres = np.stack([(bounds[:, 0] + bounds[:, 1]) / 2, (bounds[:, 2] + bounds[:, 3]) / 2], axis=1)
    return PatchGrid(
        pixel_boxes=np.stack([c0, r0, c1, r1], axis=1),
        grid_index=np.stack([ii.ravel(), jj.ravel()], axis=1).astype(np.int64),
        bounds_xy=bounds,
        centres_xy=centres,
    )

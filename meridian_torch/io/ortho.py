"""Georeferenced orthophotos: north-up RGB images with a metric world frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Orthophoto"]


@dataclass(frozen=True)
class Orthophoto:
    """Pixel centre (col, row) lies at x = x0 + (col + 0.5) * mpp, y = y0 - (row + 0.5) * mpp."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    meters_per_pixel: float
    origin_xy: tuple[float, float]  # world x, y of the top-left corner of pixel (0, 0)
    crs: str | None = None  # projected CRS (e.g. "EPSG:32632") when world is georeferenced

    @property
    def size_px(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.image.shape[1], self.image.shape[0]

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) world x, y -> (..., 2) continuous (col, row); pixel centres at integers."""
        xy = np.asarray(xy, dtype=np.float64)
        col = (xy[..., 0] - self.origin_xy[0]) / self.meters_per_pixel - 0.5
        row = (self.origin_xy[1] - xy[..., 1]) / self.meters_per_pixel - 0.5
        return np.stack([col, row], axis=-1)

    def pixel_to_world(self, colrow: np.ndarray) -> np.ndarray:
        colrow = np.asarray(colrow, dtype=np.float64)
        x = self.origin_xy[0] + (colrow[..., 0] + 0.5) * self.meters_per_pixel
        y = self.origin_xy[1] - (colrow[..., 1] + 0.5) * self.meters_per_pixel
        return np.stack([x, y], axis=-1)

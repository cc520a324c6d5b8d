"""The simulator's world: 2.5D rasters (class, height, colours) plus ground-truth objects and borders.

Raster convention = orthophoto convention: cell (row, col) covers world x in
[x0 + col*res, x0 + (col+1)*res] and y in [y0 - (row+1)*res, y0 - row*res] (row 0 is north).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["WorldObject", "RegionBorder", "World"]


@dataclass(frozen=True)
class WorldObject:
    """A compact object (building, tree, bush, rock, car) or a fence, in world metres."""

    object_id: int
    class_id: int
    centre_xy: tuple[float, float]
    footprint_xy: np.ndarray  # (K, 2) closed polygon (first vertex not repeated) or fence polyline
    height_m: float


@dataclass(frozen=True)
class RegionBorder:
    """A border polyline between two region classes, in world metres."""

    class_a: int
    class_b: int
    polyline_xy: np.ndarray  # (K, 2)


@dataclass
class World:
    resolution_m: float
    origin_xy: tuple[float, float]  # world x, y of the top-left corner of cell (0, 0)
    class_map: np.ndarray  # (H, W) uint8 SimClass ids
    height: np.ndarray  # (H, W) float32 surface height above the datum, metres
    albedo: np.ndarray  # (H, W, 3) float32 in [0, 1], colour of the top surface
    wall_albedo: np.ndarray  # (H, W, 3) float32 in [0, 1], colour of vertical faces at the cell
    instance_map: np.ndarray  # (H, W) int32 object_id or -1
    objects: list[WorldObject] = field(default_factory=list)
    borders: list[RegionBorder] = field(default_factory=list)
    road_centrelines: list[np.ndarray] = field(default_factory=list)  # (K, 2) polylines, world metres

    @property
    def shape(self) -> tuple[int, int]:
        return self.class_map.shape

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) in world metres."""
        h, w = self.shape
        x0, y0 = self.origin_xy
        return x0, x0 + w * self.resolution_m, y0 - h * self.resolution_m, y0

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) world x, y -> (..., 2) continuous (col, row); cell centres at integers."""
        xy = np.asarray(xy, dtype=np.float64)
        col = (xy[..., 0] - self.origin_xy[0]) / self.resolution_m - 0.5
        row = (self.origin_xy[1] - xy[..., 1]) / self.resolution_m - 0.5
        return np.stack([col, row], axis=-1)

    def cell_to_world(self, colrow: np.ndarray) -> np.ndarray:
        colrow = np.asarray(colrow, dtype=np.float64)
        x = self.origin_xy[0] + (colrow[..., 0] + 0.5) * self.resolution_m
        y = self.origin_xy[1] - (colrow[..., 1] + 0.5) * self.resolution_m
        return np.stack([x, y], axis=-1)

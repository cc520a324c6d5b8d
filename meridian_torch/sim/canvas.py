"""Raster painting shared by every world builder: `Canvas` (world rasters under construction),
smooth noise, footprint shapes and top surfaces, object colours, and `scatter_objects` (trees,
bushes, rocks)."""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np
import shapely

from meridian_torch.sim.classes import BASE_COLOURS, SimClass
from meridian_torch.sim.world import World, WorldObject

__all__ = [
    "Canvas",
    "smooth_noise",
    "rect_polygon",
    "disc_polygon",
    "dome_surface",
    "random_tint",
    "car_colour",
    "roof_colours",
    "scatter_objects",
    "Surface",
    "CAR_SIZE_M",
]

CAR_SIZE_M = (4.5, 1.9, 1.5)  # length, width, height

# A relative height (m) above terrain at world points x, y (arrays of the same shape).
Surface = Callable[[np.ndarray, np.ndarray], np.ndarray]


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], scale_cells: float) -> np.ndarray:
    """Zero-mean, unit-std smooth random field (float32) with features about `scale_cells` wide."""
    h, w = shape
    scale = max(float(scale_cells), 1.0)
    gh, gw = int(math.ceil(h / scale)) + 3, int(math.ceil(w / scale)) + 3
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    up = cv2.resize(coarse, (int(gw * scale), int(gh * scale)), interpolation=cv2.INTER_CUBIC)
    field = up[int(scale) : int(scale) + h, int(scale) : int(scale) + w]
    return ((field - field.mean()) / max(float(field.std()), 1e-6)).astype(np.float32)


def rect_polygon(centre: np.ndarray, angle: float, length: float, width: float) -> np.ndarray:
    """(4, 2) corners of a rectangle whose `length` side points along `angle` (rad, from +x)."""
    d = np.array([math.cos(angle), math.sin(angle)])
    n = np.array([-d[1], d[0]])
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64) * 0.5
    return np.asarray(centre, dtype=np.float64) + corners[:, :1] * length * d + corners[:, 1:] * width * n


def disc_polygon(centre: np.ndarray, radius: float, n: int = 20, roughness: float = 0.0,
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """(n, 2) polygon approximating a disc; `roughness` > 0 perturbs the radius (rocks, bushes)."""
    a = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    r = np.full(n, radius)
    if roughness > 0 and rng is not None:
        # Smooth radial perturbation: a few low harmonics with random phases.
        for k in (2, 3, 5):
            r += radius * roughness / k * np.cos(k * a + rng.uniform(0, 2 * math.pi))
    return np.asarray(centre, dtype=np.float64) + np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def dome_surface(centre: np.ndarray, radius: float, height: float, base_fraction: float) -> Surface:
    """Canopy/rock top: `base_fraction * height` at the rim rising to `height` in the centre."""
    cx, cy = float(centre[0]), float(centre[1])

    def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r = np.minimum(np.hypot(x - cx, y - cy) / radius, 1.0)
        return height * (base_fraction + (1.0 - base_fraction) * np.sqrt(1.0 - r * r))

    return surface


def random_tint(rng: np.random.Generator, base: np.ndarray, brightness: float = 0.15, hue: float = 0.06) -> np.ndarray:
    """`base` colour with a random brightness and a small per-channel change, clipped to [0, 1]."""
    tint = base * math.exp(rng.normal(0.0, brightness)) * (1.0 + rng.normal(0.0, hue, 3))
    return np.clip(tint, 0.0, 1.0).astype(np.float32)


_CAR_PALETTE = np.array(
    [[0.80, 0.80, 0.80], [0.08, 0.08, 0.09], [0.50, 0.51, 0.53], [0.30, 0.31, 0.33],
     [0.12, 0.18, 0.40], [0.85, 0.85, 0.82]], dtype=np.float32)


def car_colour(rng: np.random.Generator) -> np.ndarray:
    """Real fleets are mostly white/black/grey; the class base colour (red) is one option of seven."""
    k = rng.integers(0, len(_CAR_PALETTE) + 1)
    base = BASE_COLOURS[SimClass.CAR] if k == len(_CAR_PALETTE) else _CAR_PALETTE[k]
    return random_tint(rng, base, 0.08, 0.04)


def roof_colours(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(roof, facade) colours: tiled roofs near the class base colour, or grey/dark flat roofs."""
    grey = np.array([0.42, 0.42, 0.44], dtype=np.float32)
    dark = np.array([0.20, 0.20, 0.22], dtype=np.float32)
    base = BASE_COLOURS[SimClass.BUILDING]
    w = rng.dirichlet([2.0, 1.2, 0.6])
    roof = random_tint(rng, w[0] * base + w[1] * grey + w[2] * dark, 0.12, 0.05)
    facade = random_tint(rng, np.array([0.72, 0.68, 0.60], dtype=np.float32), 0.15, 0.06)
    return roof, facade


class Canvas:
    """World rasters under construction; objects are painted into them and recorded."""

    def __init__(self, shape: tuple[int, int], resolution_m: float, origin_xy: tuple[float, float],
                 terrain: np.ndarray, class_map: np.ndarray) -> None:
        self.resolution_m = float(resolution_m)
        self.origin_xy = (float(origin_xy[0]), float(origin_xy[1]))
        self.terrain = terrain.astype(np.float32)
        self.class_map = np.asarray(class_map, dtype=np.uint8)  # shared: callers keep painting regions
        self.height = self.terrain.copy()
        self.albedo = np.zeros(shape + (3,), np.float32)
        self.wall_albedo = np.zeros(shape + (3,), np.float32)
        self.instance_map = np.full(shape, -1, np.int32)
        self.objects: list[WorldObject] = []

    @property
    def shape(self) -> tuple[int, int]:
        return self.class_map.shape

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """World x, y -> continuous (col, row), cell centres at integers (World.world_to_cell)."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.stack([(xy[..., 0] - self.origin_xy[0]) / self.resolution_m - 0.5,
                         (self.origin_xy[1] - xy[..., 1]) / self.resolution_m - 0.5], axis=-1)

    def cell_xy(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (self.origin_xy[0] + (cols + 0.5) * self.resolution_m,
                self.origin_xy[1] - (rows + 0.5) * self.resolution_m)

    def footprint_mask(self, shape_xy: np.ndarray, line_width_m: float | None = None,
                       margin_m: float = 0.0) -> tuple[int, int, np.ndarray] | None:
        """(row0, col0, local bool mask) of a polygon (or a polyline of `line_width_m`), None if off-map."""
        px = self.to_px(shape_xy)
        pad = 2 + int(math.ceil(margin_m / self.resolution_m + (line_width_m or 0.0) / self.resolution_m))
        h, w = self.shape
        c0, r0 = (np.floor(px.min(axis=0)).astype(int) - pad).tolist()
        c1, r1 = (np.ceil(px.max(axis=0)).astype(int) + pad + 1).tolist()
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, w), min(r1, h)
        if c1 <= c0 or r1 <= r0:
            return None
        local = np.zeros((r1 - r0, c1 - c0), np.uint8)
        pts = np.round((px - [c0, r0]) * 16).astype(np.int32)  # 4 fractional bits
        if line_width_m is None:
            cv2.fillPoly(local, [pts], 1, lineType=cv2.LINE_8, shift=4)
        else:
            thick = max(1, int(round(line_width_m / self.resolution_m)))
            cv2.polylines(local, [pts], False, 1, thickness=thick, lineType=cv2.LINE_8, shift=4)
        if margin_m > 0:
            k = 2 * int(round(margin_m / self.resolution_m)) + 1
            local = cv2.dilate(local, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
        if not local.any():
            return None
        return r0, c0, local.astype(bool)

    def fits(self, shape_xy: np.ndarray, allowed: tuple[int, ...], margin_m: float = 0.0,
             line_width_m: float | None = None, free_of_objects: bool = True) -> bool:
        """True if the shape (grown by `margin_m`) is fully on the map, on allowed classes only."""
        found = self.footprint_mask(shape_xy, line_width_m, margin_m)
        if found is None:
            return False
        r0, c0, m = found
        px = self.to_px(shape_xy)
        h, w = self.shape
        if px.min() < 0 or px[:, 0].max() > w - 1 or px[:, 1].max() > h - 1:
            return False
        sl = np.s_[r0 : r0 + m.shape[0], c0 : c0 + m.shape[1]]
        if not np.isin(self.class_map[sl][m], allowed).all():
            return False
        return not (free_of_objects and (self.instance_map[sl][m] >= 0).any())

    def add_object(self, class_id: int, footprint_xy: np.ndarray, height_m: float, top_rgb: np.ndarray,
                   wall_rgb: np.ndarray, surface: Surface | None = None, merge_max: bool = False,
                   clip: np.ndarray | None = None, line_width_m: float | None = None) -> WorldObject | None:
        """Paint an object and record it. `surface` gives its relative top height (flat `height_m`
        by default); `merge_max` keeps higher existing surfaces (overlapping canopies); `clip`
        is a full-size bool mask the painted cells must lie in. None if nothing was painted."""
        found = self.footprint_mask(footprint_xy, line_width_m)
        if found is None:
            return None
        r0, c0, m = found
        sl = np.s_[r0 : r0 + m.shape[0], c0 : c0 + m.shape[1]]
        if clip is not None:
            m &= clip[sl]
        if surface is None:
            rel = np.full(m.shape, height_m, np.float32)
        else:
            rows, cols = np.mgrid[r0 : r0 + m.shape[0], c0 : c0 + m.shape[1]]
            rel = surface(*self.cell_xy(rows, cols)).astype(np.float32)
        top = self.terrain[sl] + rel
        if merge_max:
            m &= top > self.height[sl]
        if not m.any():
            return None
        oid = len(self.objects)
        self.class_map[sl][m] = class_id
        self.height[sl][m] = top[m]
        self.albedo[sl][m] = top_rgb
        self.wall_albedo[sl][m] = wall_rgb
        self.instance_map[sl][m] = oid
        pts = np.asarray(footprint_xy, dtype=np.float64)
        centre = shapely.Polygon(pts).centroid if line_width_m is None and len(pts) >= 3 else None
        cxy = (centre.x, centre.y) if centre is not None else tuple(pts.mean(axis=0))
        obj = WorldObject(oid, int(class_id), (float(cxy[0]), float(cxy[1])), pts, float(height_m))
        self.objects.append(obj)
        return obj

    def region_albedo(self, rng: np.random.Generator, palette: np.ndarray) -> None:
        """Albedo of every cell from its class colour with large-scale, per-class variation."""
        h, w = self.shape
        n1 = smooth_noise(rng, (h, w), 12.0 / self.resolution_m)
        n2 = smooth_noise(rng, (h, w), 4.0 / self.resolution_m)
        alb = palette[self.class_map]
        grass = self.class_map == SimClass.GRASS
        # Dry, yellowish patches in lawns and meadows.
        dry = np.clip(0.25 + 0.3 * n1, 0.0, 0.7)[..., None] * grass[..., None]
        alb = alb * (1 - dry) + np.array([0.48, 0.46, 0.26], np.float32) * dry
        alb *= (1.0 + 0.07 * n2 + 0.05 * n1)[..., None]
        np.clip(alb, 0.0, 1.0, out=alb)
        self.albedo[:] = alb
        self.wall_albedo[:] = alb

    def to_world(self, road_centrelines: list[np.ndarray]) -> World:
        from meridian_torch.sim.ground_truth import extract_region_borders  # it needs World, not us

        world = World(self.resolution_m, self.origin_xy, self.class_map, self.height, self.albedo,
                      self.wall_albedo, self.instance_map, list(self.objects), [],
                      [np.asarray(c, dtype=np.float64) for c in road_centrelines])
        world.borders = extract_region_borders(world)
        return world


_SCATTER_SIZES = {  # radius range (m), height range (m), rim height fraction, outline roughness
    SimClass.TREE: ((1.5, 4.0), (5.0, 14.0), 0.55, 0.12),
    SimClass.BUSH: ((0.6, 1.5), (0.8, 2.0), 0.3, 0.2),
    SimClass.ROCK: ((0.4, 1.5), (0.3, 1.2), 0.2, 0.35),
}


def scatter_objects(canvas: Canvas, rng: np.random.Generator, class_id: SimClass, count: float,
                    zone: np.ndarray | None, clump: np.ndarray | None, allowed: tuple[int, ...],
                    palette: np.ndarray) -> None:
    """Up to `count` trees, bushes or rocks at clumped random places inside `zone` (None = anywhere)
    whose centre lies on `allowed` classes; canopies may overlap other vegetation only."""
    (r_lo, r_hi), (h_lo, h_hi), rim, rough = _SCATTER_SIZES[class_id]
    n = int(round(count))
    if n == 0:
        return
    res = canvas.resolution_m
    h, w = canvas.shape
    # Distance to the nearest cell a canopy must not cover (roads, buildings, water, ...);
    # only vegetation is painted below, so it stays valid while we place.
    coverable = np.isin(canvas.class_map, [int(c) for c in allowed + (SimClass.TREE, SimClass.BUSH)])
    clearance = cv2.distanceTransform(coverable.astype(np.uint8), cv2.DIST_L2, 3) * res
    ok = np.isin(canvas.class_map, [int(c) for c in allowed]) & (clearance > r_lo)
    if zone is not None:
        ok &= zone
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return
    cand = rng.choice(idx, size=min(len(idx), 20 * n), replace=len(idx) < 20 * n)
    if clump is not None:  # groves and thickets
        cand = cand[rng.random(len(cand)) < 1.0 / (1.0 + np.exp(-2.0 * clump.reshape(-1)[cand]))]
    trunk = max(1, int(round(1.0 / res)))
    placed = 0
    for r, c in zip(*np.unravel_index(cand, (h, w))):
        if placed >= n:
            break
        radius = rng.uniform(r_lo, r_hi)
        if clearance[r, c] < radius or canvas.class_map[r, c] not in allowed:
            continue
        # Trees may stand under other canopies; bushes and rocks need free ground around them.
        if class_id != SimClass.TREE and (canvas.instance_map[max(r - trunk, 0) : r + trunk + 1,
                                                              max(c - trunk, 0) : c + trunk + 1] >= 0).any():
            continue
        centre = np.array(canvas.cell_xy(np.float64(r), np.float64(c)))
        height = rng.uniform(h_lo, h_hi) if class_id != SimClass.TREE else \
            float(np.clip(radius * rng.uniform(2.2, 3.8), h_lo, h_hi))
        top = random_tint(rng, palette[class_id], 0.15, 0.07)
        wall = top * 0.7 if class_id != SimClass.TREE else random_tint(rng, np.array([0.25, 0.18, 0.12], np.float32))
        poly = disc_polygon(centre, radius, 16, rough, rng)
        if canvas.add_object(class_id, poly, height, top, wall, dome_surface(centre, radius * 1.15, height, rim),
                             merge_max=True) is not None:
            placed += 1

"""Procedural worlds: a perturbed road grid, urban and natural zones, buildings, cars, trees and more.

Also home of the raster painting helpers shared by every world builder (`Canvas`,
`smooth_noise`, footprint shapes) and of `road_graph`, the junction graph of road centrelines.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import networkx as nx
import numpy as np
import shapely
from shapely.geometry import LineString, MultiLineString, box
from shapely.ops import linemerge

from meridian_torch.config.sim import WorldConfig
from meridian_torch.errors import SimulationError
from meridian_torch.sim.classes import BASE_COLOURS, SimClass
from meridian_torch.sim.world import World, WorldObject

__all__ = [
    "generate_world",
    "Canvas",
    "smooth_noise",
    "rect_polygon",
    "disc_polygon",
    "dome_surface",
    "random_tint",
    "car_colour",
    "roof_colours",
    "road_graph",
    "road_samples",
    "scatter_objects",
    "SIDEWALK_WIDTH_M",
    "CAR_SIZE_M",
]

SIDEWALK_WIDTH_M = 2.0
CAR_SIZE_M = (4.5, 1.9, 1.5)  # length, width, height
FENCE_WIDTH_M = 0.2
FENCE_HEIGHT_M = 1.5

# A relative height (m) above terrain at world points x, y (arrays of the same shape).
Surface = Callable[[np.ndarray, np.ndarray], np.ndarray]


# ----------------------------------------------------------------------------- noise & shapes


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


# ----------------------------------------------------------------------------- canvas


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


# ----------------------------------------------------------------------------- roads


def road_graph(centrelines: list[np.ndarray]) -> nx.MultiGraph:
    """Junction graph of road centrelines: lines are split where they cross and merged through
    degree-2 points. Nodes carry `xy`; edges carry `xy` (K, 2) running from `start` node."""
    lines = [LineString(c) for c in centrelines if len(c) >= 2]
    if not lines:
        raise SimulationError("the world has no road centrelines")
    noded = shapely.union_all(lines)
    merged = linemerge(noded) if not isinstance(noded, LineString) else noded
    parts = list(merged.geoms) if hasattr(merged, "geoms") else [merged]
    g = nx.MultiGraph()
    index: dict[tuple[float, float], int] = {}

    def node(p: np.ndarray) -> int:
        key = (round(float(p[0]), 3), round(float(p[1]), 3))
        if key not in index:
            index[key] = len(index)
            g.add_node(index[key], xy=np.array(key))
        return index[key]

    for part in parts:
        xy = np.asarray(part.coords)[:, :2]
        if part.length < 1e-6:
            continue
        u, v = node(xy[0]), node(xy[-1])
        g.add_edge(u, v, xy=xy, start=u, length=float(part.length))
    return g


def _grid_roads(cfg: WorldConfig, rng: np.random.Generator, size: tuple[float, float]) -> list[np.ndarray]:
    """Centrelines of a rotated, jittered grid of gently curving roads, clipped to the world."""
    sx, sy = size
    centre = np.array([sx / 2, sy / 2])
    theta = rng.uniform(0, math.pi / 2)
    R = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    half = 0.5 * math.hypot(sx, sy) + cfg.road_spacing_m
    t = np.arange(-half, half + 4.0, 4.0)
    lines: list[np.ndarray] = []
    for axis in (0, 1):
        spacing = cfg.road_spacing_m * rng.uniform(0.85, 1.2)
        offsets = np.arange(-half, half, spacing) + rng.uniform(0, spacing)
        offsets += rng.uniform(-0.2, 0.2, len(offsets)) * spacing
        for off in offsets:
            wiggle = smooth_noise(rng, (1, len(t)), rng.uniform(15, 40))[0] * rng.uniform(0.5, 0.08 * spacing)
            uv = np.stack([off + wiggle, t], axis=1) if axis == 0 else np.stack([t, off + wiggle], axis=1)
            lines.append(uv @ R.T + centre)
    clip = box(0.5, 0.5, sx - 0.5, sy - 0.5)
    out: list[np.ndarray] = []
    for line in lines:
        piece = LineString(line).intersection(clip)
        for g in getattr(piece, "geoms", [piece]):
            if isinstance(g, LineString) and g.length > cfg.road_width_m:
                out.append(np.asarray(g.coords))
    return out


def _prune_roads(lines: list[np.ndarray], urban_at: Callable[[np.ndarray], bool],
                 rng: np.random.Generator) -> list[np.ndarray]:
    """Drop some grid edges (more in natural zones) while the network stays connected."""
    g = road_graph(lines)
    edges = list(g.edges(keys=True, data=True))
    for i in rng.permutation(len(edges)):
        u, v, k, data = edges[i]
        mid = data["xy"][len(data["xy"]) // 2]
        if rng.random() > (0.12 if urban_at(mid) else 0.4) or g.degree(u) <= 2 or g.degree(v) <= 2:
            continue
        g.remove_edge(u, v, k)
        if not nx.is_connected(g):
            g.add_edge(u, v, k, **data)
    merged = linemerge(MultiLineString([d["xy"] for _, _, d in g.edges(data=True)]))
    return [np.asarray(p.coords) for p in getattr(merged, "geoms", [merged])]


def road_samples(lines: list[np.ndarray], step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step` metres along all centrelines and their unit tangents."""
    pts, tans = [], []
    for line in lines:
        ls = LineString(line)
        s = np.arange(0.0, ls.length, step)
        p = shapely.get_coordinates(shapely.line_interpolate_point(ls, s))
        q = shapely.get_coordinates(shapely.line_interpolate_point(ls, np.minimum(s + 0.5, ls.length)))
        d = q - p
        d[-1] = d[-2] if len(d) > 1 else d[-1]
        pts.append(p)
        tans.append(d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9))
    return np.concatenate(pts), np.concatenate(tans)


# ----------------------------------------------------------------------------- generator


def generate_world(cfg: WorldConfig, seed: int) -> World:
    """A procedural world of `cfg.size_m` at `cfg.resolution_m`; same seed, same world."""
    rng = np.random.default_rng(seed)
    res = cfg.resolution_m
    w, h = int(round(cfg.size_m[0] / res)), int(round(cfg.size_m[1] / res))
    if w < 16 or h < 16:
        raise SimulationError(f"world of {cfg.size_m} m at {res} m is too small")
    size = (w * res, h * res)
    origin = (0.0, size[1])
    rw = cfg.road_width_m

    urban_noise = smooth_noise(rng, (h, w), 150.0 / res)
    if cfg.urban_fraction > 0:
        urban = urban_noise >= np.quantile(urban_noise, 1.0 - cfg.urban_fraction)
    else:
        urban = np.zeros((h, w), bool)

    def urban_at(xy: np.ndarray) -> bool:
        r = min(max(int((origin[1] - xy[1]) / res), 0), h - 1)
        c = min(max(int((xy[0] - origin[0]) / res), 0), w - 1)
        return bool(urban[r, c])

    roads = _prune_roads(_grid_roads(cfg, rng, size), urban_at, rng)

    # Terrain: gentle undulation; roads, water and everything else sit on it.
    terrain = 0.8 * smooth_noise(rng, (h, w), 120.0 / res) + 0.12 * smooth_noise(rng, (h, w), 20.0 / res)
    cls = np.full((h, w), SimClass.GRASS, np.uint8)
    canvas = Canvas((h, w), res, origin, terrain, cls)
    road_px = [np.round(canvas.to_px(c) * 16).astype(np.int32) for c in roads]
    walk = np.zeros((h, w), np.uint8)
    cv2.polylines(walk, road_px, False, 1, thickness=max(1, int(round((rw + 2 * SIDEWALK_WIDTH_M) / res))), shift=4)
    road = np.zeros((h, w), np.uint8)
    cv2.polylines(road, road_px, False, 1, thickness=max(1, int(round(rw / res))), shift=4)
    road_dist = cv2.distanceTransform((road == 0).astype(np.uint8), cv2.DIST_L2, 5) * res

    natural = ~urban & (walk == 0)
    soil_n = smooth_noise(rng, (h, w), 25.0 / res)
    if natural.any() and cfg.soil_fraction > 0:
        cls[natural & (soil_n >= np.quantile(soil_n[natural], 1.0 - cfg.soil_fraction))] = SimClass.SOIL
    water_n = smooth_noise(rng, (h, w), 45.0 / res)
    pondable = natural & (road_dist > rw + 4.0)
    if pondable.any() and cfg.water_fraction > 0:
        cls[pondable & (water_n >= np.quantile(water_n[natural], 1.0 - cfg.water_fraction))] = SimClass.WATER
    cls[(walk > 0) & urban] = SimClass.SIDEWALK
    cls[road > 0] = SimClass.ROAD
    water = cls == SimClass.WATER
    # Ponds: the water surface lies below the banks, deepest away from the shore.
    shore = cv2.distanceTransform(water.astype(np.uint8), cv2.DIST_L2, 5) * res
    canvas.terrain -= np.where(water, 0.3 + np.minimum(shore, 3.0) * 0.05, 0.0).astype(np.float32)
    canvas.terrain += np.where(cls == SimClass.SIDEWALK, 0.12, 0.0).astype(np.float32)  # kerb

    # Per-world palette jitter so that worlds differ in season and light, not only in layout.
    palette = BASE_COLOURS * np.exp(rng.normal(0.0, 0.06, BASE_COLOURS.shape)).astype(np.float32)
    pts, tans = road_samples(roads, 1.0)
    node_xy = np.array([d["xy"] for _, d in road_graph(roads).nodes(data=True)])
    junction_dist = np.min(np.linalg.norm(pts[:, None, :] - node_xy[None, :, :], axis=2), axis=1)
    pts_urban = np.array([urban_at(p) for p in pts])
    urban_ha = urban.sum() * res * res / 1e4
    natural_ha = (~urban).sum() * res * res / 1e4
    ground = (SimClass.GRASS, SimClass.SOIL)

    lot_cars = _place_parking(canvas, rng, cfg, pts, tans, pts_urban & (junction_dist > rw + 8.0), urban_ha)
    canvas.height[:] = canvas.terrain
    canvas.region_albedo(rng, palette)  # regions are final; objects below bring their own colours
    _place_buildings(canvas, rng, cfg, pts, tans, pts_urban, urban_ha, urban_noise)
    for poly in lot_cars:
        if canvas.fits(poly, (SimClass.PARKING,)):
            canvas.add_object(SimClass.CAR, poly, CAR_SIZE_M[2], car_colour(rng), car_colour(rng) * 0.6)
    roadside = pts_urban & (junction_dist > rw / 2 + SIDEWALK_WIDTH_M + 5.0)
    _place_roadside_cars(canvas, rng, cfg, pts, tans, roadside, cfg.cars_per_ha * urban_ha * 0.5)
    _place_fences(canvas, rng, cfg, pts, tans, junction_dist)
    clump = smooth_noise(rng, (h, w), 30.0 / res)
    scatter_objects(canvas, rng, SimClass.TREE, cfg.trees_per_ha * natural_ha, ~urban, clump,
             ground + (SimClass.TREE,), palette)
    scatter_objects(canvas, rng, SimClass.TREE, 0.3 * cfg.trees_per_ha * urban_ha, urban, clump,
             (SimClass.GRASS, SimClass.TREE), palette)
    scatter_objects(canvas, rng, SimClass.BUSH, cfg.bushes_per_ha * (natural_ha + 0.5 * urban_ha), None, clump,
             ground, palette)
    scatter_objects(canvas, rng, SimClass.ROCK, cfg.rocks_per_ha * natural_ha, ~urban, None, ground, palette)
    return canvas.to_world(roads)


def _pick(rng: np.random.Generator, ok: np.ndarray) -> int | None:
    idx = np.flatnonzero(ok)
    return int(rng.choice(idx)) if len(idx) else None


def _normal(t: np.ndarray, side: float) -> np.ndarray:
    """Unit normal of tangent `t`: left for side +1, right for side -1."""
    return side * np.array([-t[1], t[0]])


def _place_parking(canvas: Canvas, rng: np.random.Generator, cfg: WorldConfig, pts: np.ndarray, tans: np.ndarray,
                   ok: np.ndarray, urban_ha: float) -> list[np.ndarray]:
    """Paint parking lots next to urban roads; return the footprints of the cars parked in them."""
    target = int(round(urban_ha * 0.6))
    setback = cfg.road_width_m / 2 + SIDEWALK_WIDTH_M
    d_slot, w_slot = 5.0, 2.6
    cars: list[np.ndarray] = []
    lots = 0
    for _ in range(8 * target):
        if lots >= target:
            break
        i = _pick(rng, ok)
        if i is None:
            break
        length, depth = rng.uniform(20, 45), rng.uniform(16, 30)
        n = _normal(tans[i], rng.choice([-1.0, 1.0]))
        centre = pts[i] + n * (setback + 0.6 + depth / 2)
        angle = math.atan2(tans[i][1], tans[i][0])
        poly = rect_polygon(centre, angle, length, depth)
        if not canvas.fits(poly, (SimClass.GRASS,), margin_m=0.3):
            continue
        r0, c0, m = canvas.footprint_mask(poly)
        canvas.class_map[r0 : r0 + m.shape[0], c0 : c0 + m.shape[1]][m] = SimClass.PARKING
        lots += 1
        d = np.array([math.cos(angle), math.sin(angle)])
        for row_off in (-depth / 2 + d_slot / 2 + 0.5, depth / 2 - d_slot / 2 - 0.5):
            for s in np.arange(-length / 2 + w_slot / 2 + 0.5, length / 2 - w_slot / 2, w_slot):
                if rng.random() < 0.55:
                    c = centre + d * s + n * row_off + rng.normal(0, 0.15, 2)
                    cars.append(rect_polygon(c, angle + math.pi / 2 + rng.normal(0, 0.04), *CAR_SIZE_M[:2]))
    return cars


def _place_buildings(canvas: Canvas, rng: np.random.Generator, cfg: WorldConfig, pts: np.ndarray, tans: np.ndarray,
                     pts_urban: np.ndarray, urban_ha: float, urban_noise: np.ndarray) -> None:
    """Rectangular and L-shaped buildings facing urban roads, set back from the sidewalk."""
    target = int(round(cfg.buildings_per_ha * urban_ha))
    setback = cfg.road_width_m / 2 + SIDEWALK_WIDTH_M
    placed = 0
    for _ in range(25 * target):
        if placed >= target:
            break
        i = _pick(rng, pts_urban)
        if i is None:
            return
        width, depth = rng.uniform(8, 30), rng.uniform(8, 20)
        n = _normal(tans[i], rng.choice([-1.0, 1.0]))
        centre = pts[i] + n * (setback + rng.uniform(2.0, 9.0) + depth / 2)
        angle = math.atan2(tans[i][1], tans[i][0])
        poly = rect_polygon(centre, angle, width, depth)
        if rng.random() < 0.3:  # L-shape: a wing reaching back from one end
            d = np.array([math.cos(angle), math.sin(angle)])
            ww, wd = rng.uniform(0.3, 0.5) * width, rng.uniform(6, 14)
            wing = rect_polygon(centre + d * rng.choice([-1, 1]) * (width - ww) / 2 + n * (depth + wd) / 2,
                                angle, ww, wd + 0.5)
            poly = np.asarray(shapely.union(shapely.Polygon(poly), shapely.Polygon(wing)).exterior.coords)[:-1]
        if not canvas.fits(poly, (SimClass.GRASS,), margin_m=1.5):
            continue
        col, row = canvas.to_px(centre).astype(int)
        core = float(urban_noise[min(max(row, 0), canvas.shape[0] - 1), min(max(col, 0), canvas.shape[1] - 1)])
        # Taller buildings in the urban core, a long tail of high-rises.
        height = float(np.clip(rng.lognormal(math.log(7.0 + 4.0 * max(core, 0.0)), 0.35), 4.0, 25.0))
        roof, facade = roof_colours(rng)
        surface = None
        if height < 12 and len(poly) == 4 and rng.random() < 0.5:
            surface = _gable(centre, angle, height, rng.uniform(1.5, 3.0), depth / 2)
        canvas.add_object(SimClass.BUILDING, poly, height, roof, facade, surface)
        placed += 1


def _gable(centre: np.ndarray, angle: float, height: float, drop: float, half_depth: float) -> Surface:
    """Gable roof with the ridge along `angle` through `centre`, eaves `drop` metres lower."""
    rn = np.array([-math.sin(angle), math.cos(angle)])

    def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        off = np.abs((x - centre[0]) * rn[0] + (y - centre[1]) * rn[1])
        return height - drop * np.minimum(off / half_depth, 1.0)

    return surface


def _place_roadside_cars(canvas: Canvas, rng: np.random.Generator, cfg: WorldConfig, pts: np.ndarray,
                         tans: np.ndarray, ok: np.ndarray, count: float) -> None:
    """Cars parked along the kerb of urban roads, away from junctions."""
    lateral = cfg.road_width_m / 2 - 0.45 - CAR_SIZE_M[1] / 2
    placed = 0
    for _ in range(int(6 * count)):
        if placed >= count:
            break
        i = _pick(rng, ok)
        if i is None:
            return
        centre = pts[i] + _normal(tans[i], rng.choice([-1.0, 1.0])) * lateral
        angle = math.atan2(tans[i][1], tans[i][0]) + rng.normal(0, 0.02)
        poly = rect_polygon(centre, angle, *CAR_SIZE_M[:2])
        if canvas.fits(poly, (SimClass.ROAD,), margin_m=0.2):
            canvas.add_object(SimClass.CAR, poly, CAR_SIZE_M[2], car_colour(rng), car_colour(rng) * 0.6)
            placed += 1


def _place_fences(canvas: Canvas, rng: np.random.Generator, cfg: WorldConfig, pts: np.ndarray,
                  tans: np.ndarray, junction_dist: np.ndarray) -> None:
    """Fences parallel to roads along parcel borders, on open ground only."""
    colour = BASE_COLOURS[SimClass.FENCE]
    placed = 0
    for _ in range(30 * cfg.fences):
        if placed >= cfg.fences:
            break
        i = _pick(rng, junction_dist > 30.0)
        if i is None:
            return
        n_pts = int(rng.uniform(20, 60))
        j = min(i + n_pts, len(pts) - 1)
        seg = np.arange(i, j + 1)
        if j - i < 15 or np.linalg.norm(pts[j] - pts[i]) < 0.8 * (j - i):  # crosses onto another road
            continue
        side = rng.choice([-1.0, 1.0])
        off = cfg.road_width_m / 2 + SIDEWALK_WIDTH_M + rng.uniform(1.0, 4.0)
        line = pts[seg] + side * np.stack([-tans[seg, 1], tans[seg, 0]], axis=1) * off
        line = line[::3]
        if canvas.fits(line, (SimClass.GRASS, SimClass.SOIL), margin_m=0.3, line_width_m=FENCE_WIDTH_M):
            canvas.add_object(SimClass.FENCE, line, FENCE_HEIGHT_M, random_tint(rng, colour, 0.1),
                              random_tint(rng, colour, 0.1), line_width_m=FENCE_WIDTH_M)
            placed += 1


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

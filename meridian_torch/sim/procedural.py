"""Procedural worlds: a perturbed road grid, urban and natural zones, and the placement of
buildings, parking lots, cars, fences, trees, bushes and rocks in them."""

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
from meridian_torch.sim.canvas import (
    CAR_SIZE_M,
    Canvas,
    Surface,
    car_colour,
    random_tint,
    rect_polygon,
    roof_colours,
    scatter_objects,
    smooth_noise,
)
from meridian_torch.sim.classes import BASE_COLOURS, SimClass
from meridian_torch.sim.roads import road_graph, road_samples
from meridian_torch.sim.world import World

__all__ = ["generate_world", "SIDEWALK_WIDTH_M"]

SIDEWALK_WIDTH_M = 2.0
FENCE_WIDTH_M = 0.2
FENCE_HEIGHT_M = 1.5


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

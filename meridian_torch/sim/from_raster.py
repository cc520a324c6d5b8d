"""Worlds from a semantic class raster (a label image or a folder of `classK.png` masks).

Region classes are painted as given. Object classes become objects: each connected
building (car, fence) area is one object with its own height and colours; tree, bush and
rock areas are filled with individual instances. Cars are added along the kerbs of wide
roads and road centrelines come from the skeleton of the road class.

World frame: x east from the raster's west edge; for `flip_vertical` (stored y-up) rasters
y = 0 is the raster's south edge, otherwise y = raster height (m) is its north edge, so that
the stored row 0 is anchored exactly (see `load_trajectory` alignments).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import shapely
from scipy.ndimage import convolve, gaussian_filter1d
from skimage.morphology import skeletonize

from meridian_torch.config.sim import ClassRasterConfig, WorldConfig
from meridian_torch.errors import SimulationError
from meridian_torch.sim.canvas import (
    CAR_SIZE_M,
    Canvas,
    car_colour,
    random_tint,
    rect_polygon,
    roof_colours,
    scatter_objects,
    smooth_noise,
)
from meridian_torch.sim.classes import BASE_COLOURS, REGION_CLASSES, SimClass, class_by_name
from meridian_torch.sim.world import World

__all__ = ["world_from_class_raster", "read_class_raster"]

MIN_BUILDING_AREA_M2 = 15.0
SKELETON_CELL_M = 1.0
MIN_SPUR_M = 12.0
_MASK_NAME = re.compile(r"class(\d+)\.png$", re.IGNORECASE)


def read_class_raster(rc: ClassRasterConfig) -> np.ndarray:
    """(H, W) int16 raster ids as stored (no flip); -1 where no mask claims a pixel."""
    path = Path(rc.path)
    if path.is_dir():
        masks = sorted((int(m.group(1)), p) for p in path.iterdir() if (m := _MASK_NAME.search(p.name)))
        if not masks:
            raise SimulationError(f"{path}: no classK.png masks")
        labels = None
        for k, p in masks:
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)  # 3-channel masks are identical channels
            if img is None:
                raise SimulationError(f"{p}: unreadable mask")
            if labels is None:
                labels = np.full(img.shape, -1, np.int16)
            elif img.shape != labels.shape:
                raise SimulationError(f"{p}: size {img.shape} differs from the other masks {labels.shape}")
            labels[img < 128] = k  # 0 = inside
        return labels
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SimulationError(f"{path}: unreadable label image")
    return (img[..., 0] if img.ndim == 3 else img).astype(np.int16)


def world_from_class_raster(cfg: WorldConfig, seed: int) -> World:
    """Build a World from `cfg.class_raster` at `cfg.resolution_m`; same seed, same world."""
    rc = cfg.class_raster
    if rc is None:
        raise SimulationError("world kind 'class_raster' needs the class_raster block")
    rng = np.random.default_rng(seed)
    ids = read_class_raster(rc)
    if rc.flip_vertical:
        ids = ids[::-1]
    lut = np.full(int(max(ids.max(), 0)) + 2, int(class_by_name(rc.fill_class)), np.uint8)  # index id + 1
    for k, name in rc.classes.items():
        if 0 <= k < len(lut) - 1:
            lut[k + 1] = int(class_by_name(name))
    src = lut[ids.astype(np.int32) + 1]

    res = cfg.resolution_m
    h_m, w_m = ids.shape[0] * rc.meters_per_pixel, ids.shape[1] * rc.meters_per_pixel
    rows, cols = max(16, int(round(h_m / res))), max(16, int(round(w_m / res)))
    origin = (0.0, rows * res if rc.flip_vertical else h_m)
    sem = _resample_classes(src, (rows, cols))

    fill = class_by_name(rc.fill_class)
    ground_fill = fill if fill in REGION_CLASSES else SimClass.GRASS
    regions = np.where(np.isin(sem, [int(c) for c in REGION_CLASSES]), sem, ground_fill).astype(np.uint8)
    terrain = 0.6 * smooth_noise(rng, (rows, cols), 120.0 / res) + 0.1 * smooth_noise(rng, (rows, cols), 20.0 / res)
    water = regions == SimClass.WATER
    terrain -= np.where(water, 0.4, 0.0).astype(np.float32)
    canvas = Canvas((rows, cols), res, origin, terrain, regions)
    palette = BASE_COLOURS * np.exp(rng.normal(0.0, 0.06, BASE_COLOURS.shape)).astype(np.float32)
    canvas.region_albedo(rng, palette)

    for cls in (SimClass.BUILDING, SimClass.CAR, SimClass.FENCE):
        if (sem == cls).any():
            _component_objects(canvas, rng, sem == cls, cls)
    spacing2 = rc.object_spacing_m**2
    ground = (SimClass.GRASS, SimClass.SOIL)
    for cls, allowed, density in ((SimClass.TREE, ground + (SimClass.TREE,), 1.0),
                                  (SimClass.BUSH, ground, 2.0), (SimClass.ROCK, ground, 0.5)):
        zone = sem == cls
        area = zone.sum() * res * res
        if area > 0:
            scatter_objects(canvas, rng, cls, density * area / spacing2, zone, None, allowed, palette)
            if cls == SimClass.TREE:  # an understorey of bushes
                scatter_objects(canvas, rng, SimClass.BUSH, 0.3 * area / spacing2, zone, None, ground, palette)
    _kerb_cars(canvas, rng, cfg.cars_per_ha)
    return canvas.to_world(_road_centrelines(canvas))


def _resample_classes(src: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Class raster resampled to `shape` by the argmax of bilinearly resampled class masks,
    which keeps borders smooth instead of blocky."""
    present = np.unique(src)
    if len(present) == 1:
        return np.full(shape, present[0], np.uint8)
    best = np.full(shape, -1.0, np.float32)
    out = np.zeros(shape, np.uint8)
    for c in present:
        score = cv2.resize((src == c).astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
        better = score > best
        out[better], best[better] = c, score[better]
    return out


def _component_objects(canvas: Canvas, rng: np.random.Generator, mask: np.ndarray, cls: SimClass) -> None:
    """One object per connected area of `mask` (outer outline, simplified to 0.3 m)."""
    res = canvas.resolution_m
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    min_cells = (MIN_BUILDING_AREA_M2 if cls == SimClass.BUILDING else 1.0) / (res * res)
    for i in range(1, n):
        x, y, w, h, area = stats[i]
        if area < min_cells:
            continue
        local = (labels[y : y + h, x : x + w] == i).astype(np.uint8)
        contours, _ = cv2.findContours(local, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        outline = max(contours, key=cv2.contourArea)[:, 0, :].astype(np.float64) + [x, y]
        if len(outline) < 3:
            continue
        xy = np.stack(canvas.cell_xy(outline[:, 1], outline[:, 0]), axis=1)
        poly = shapely.Polygon(xy).simplify(0.3)
        if poly.is_empty or poly.geom_type != "Polygon" or len(poly.exterior.coords) < 4:
            continue
        foot = np.asarray(poly.exterior.coords)[:-1]
        if cls == SimClass.BUILDING:
            size = area * res * res
            height = float(np.clip(rng.lognormal(math.log(7.0 + 2.0 * math.log10(1 + size / 100)), 0.35), 4.0, 25.0))
            top, wall = roof_colours(rng)
        elif cls == SimClass.CAR:
            height, top = CAR_SIZE_M[2], car_colour(rng)
            wall = top * 0.6
        else:
            height = 1.5
            top = wall = random_tint(rng, BASE_COLOURS[cls], 0.1)
        canvas.add_object(cls, foot, height, top, wall, clip=mask)


def _kerb_cars(canvas: Canvas, rng: np.random.Generator, cars_per_ha: float) -> None:
    """Cars parked along the kerbs of roads at least ~7.5 m wide."""
    res = canvas.resolution_m
    road = (canvas.class_map == SimClass.ROAD).astype(np.uint8)
    if not road.any():
        return
    dist = cv2.distanceTransform(road, cv2.DIST_L2, 5) * res
    k = 2 * int(round(4.0 / res)) + 1
    wide = cv2.dilate(dist, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) >= 3.75
    centre_d = 0.35 + CAR_SIZE_M[1] / 2
    band = (np.abs(dist - centre_d) < 0.6 * res + 0.05) & wide
    rows, cols = np.nonzero(band)
    count = int(round(cars_per_ha * 0.5 * road.sum() * res * res / 1e4))
    if len(rows) == 0 or count == 0:
        return
    gy = cv2.Sobel(dist, cv2.CV_32F, 0, 1, ksize=3)
    gx = cv2.Sobel(dist, cv2.CV_32F, 1, 0, ksize=3)
    placed = 0
    for i in rng.permutation(len(rows))[: 30 * count]:
        if placed >= count:
            break
        r, c = rows[i], cols[i]
        # The distance gradient points away from the kerb; the car lies along the kerb.
        angle = math.atan2(gy[r, c], -gx[r, c]) + math.pi / 2  # row axis points south
        centre = np.array(canvas.cell_xy(np.float64(r), np.float64(c)))
        poly = rect_polygon(centre, angle, *CAR_SIZE_M[:2])
        if canvas.fits(poly, (SimClass.ROAD,), margin_m=0.15):
            canvas.add_object(SimClass.CAR, poly, CAR_SIZE_M[2], car_colour(rng), car_colour(rng) * 0.6)
            placed += 1


def _road_centrelines(canvas: Canvas) -> list[np.ndarray]:
    """Polylines (world metres) along the skeleton of road + parking at ~1 m cells, split at
    junctions (every polyline ends exactly at a junction centre) with short spurs removed."""
    f = max(1, int(round(SKELETON_CELL_M / canvas.resolution_m)))
    drivable = np.isin(canvas.class_map, [SimClass.ROAD, SimClass.PARKING, SimClass.CAR]).astype(np.float32)
    h, w = (canvas.shape[0] // f) * f, (canvas.shape[1] // f) * f
    coarse = cv2.resize(drivable[:h, :w], (w // f, h // f), interpolation=cv2.INTER_AREA) > 0.5
    coarse = cv2.morphologyEx(coarse.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    skel = skeletonize(coarse > 0)
    lines = _trace_skeleton(skel)
    cell = f * canvas.resolution_m
    out = []
    for line in lines:
        if len(line) > 4:  # smooth pixel stairs, keep the junction end points exact
            inner = gaussian_filter1d(line.astype(np.float64), 1.5, axis=0, mode="nearest")
            line = np.vstack([line[:1], inner[1:-1], line[-1:]])
        x = canvas.origin_xy[0] + (line[:, 0] + 0.5) * cell
        y = canvas.origin_xy[1] - (line[:, 1] + 0.5) * cell
        out.append(np.stack([x, y], axis=1))
    return [p for p in out if np.linalg.norm(np.diff(p, axis=0), axis=1).sum() > 1.0]


def _trace_skeleton(skel: np.ndarray) -> list[np.ndarray]:
    """(col, row) polylines between junctions / ends of an 8-connected skeleton, spurs shorter
    than MIN_SPUR_M (in cells) dropped. Junction pixel clusters collapse to their centroid."""
    sk = skel.astype(np.uint8)
    count = convolve(sk, np.ones((3, 3), np.uint8), mode="constant") - 1
    node_mask = (sk > 0) & (count != 2)
    n_clusters, cluster = cv2.connectedComponents(node_mask.astype(np.uint8), connectivity=8)
    centroid = np.zeros((n_clusters, 2))
    rr, cc = np.nonzero(node_mask)
    np.add.at(centroid, cluster[rr, cc], np.stack([cc, rr], 1))
    centroid /= np.maximum(np.bincount(cluster[rr, cc], minlength=n_clusters), 1)[:, None]
    degree = np.zeros(n_clusters, int)
    offsets = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
    hgt, wid = sk.shape
    visited = np.zeros(sk.shape, bool)
    edges: list[tuple[int, int, list]] = []
    linked: set[tuple[int, int]] = set()

    def neighbours(r: int, c: int) -> list[tuple[int, int]]:
        return [(r + dr, c + dc) for dr, dc in offsets
                if 0 <= r + dr < hgt and 0 <= c + dc < wid and sk[r + dr, c + dc]]

    for r0, c0 in zip(rr, cc):
        a = cluster[r0, c0]
        for r, c in neighbours(r0, c0):
            if node_mask[r, c]:
                b = cluster[r, c]
                if b != a and (min(a, b), max(a, b)) not in linked:
                    linked.add((min(a, b), max(a, b)))
                    edges.append((a, b, []))
                continue
            if visited[r, c]:
                continue
            path, prev, cur, b = [], (r0, c0), (r, c), a
            while True:
                visited[cur] = True
                path.append((cur[1], cur[0]))
                nb = [p for p in neighbours(*cur) if p != prev]
                # Reaching a junction ends the walk (back at the start one only after a loop).
                hit = [p for p in nb if node_mask[p] and (cluster[p] != a or len(path) > 1)]
                if hit:
                    b = cluster[hit[0]]
                    break
                free = [p for p in nb if not node_mask[p] and not visited[p]]
                if not free:
                    break
                prev, cur = cur, free[0]
            edges.append((a, b, path))
    for a, b, _ in edges:
        degree[a] += 1
        degree[b] += 1
    out = []
    for a, b, path in edges:
        spur = min(degree[a], degree[b]) <= 1 and len(path) < MIN_SPUR_M / SKELETON_CELL_M
        if spur or (a == b and len(path) < 3):
            continue
        out.append(np.vstack([centroid[a], np.asarray(path, dtype=np.float64).reshape(-1, 2), centroid[b]]))
    return out

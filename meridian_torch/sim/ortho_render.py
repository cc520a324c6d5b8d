"""Render a north-up aerial orthophoto of a World: texture, hillshade, cast shadows, road markings.

The "outdated" option imitates imagery taken at another time: vegetation changes colour
(season), some objects are gone and a few new ones appear. It only changes the image; the
World (and so every ground truth) stays as it is.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.spatial import cKDTree

from meridian_torch.config.sim import OrthoRenderConfig
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.sim.canvas import (
    CAR_SIZE_M,
    Canvas,
    car_colour,
    rect_polygon,
    scatter_objects,
    smooth_noise,
)
from meridian_torch.sim.classes import BASE_COLOURS, SimClass
from meridian_torch.sim.ground_truth import nearest_ground_index
from meridian_torch.sim.roads import road_samples
from meridian_torch.sim.world import World

__all__ = ["render_orthophoto"]

AMBIENT = 0.38  # share of sky light: what a fully shadowed flat surface still receives
# Texture amplitude per class: (fine grain ~1 px, mottling ~1.5 m).
_TEXTURE = np.array(
    [
        [0.10, 0.12],  # grass
        [0.09, 0.10],  # soil
        [0.02, 0.04],  # water
        [0.06, 0.04],  # road
        [0.06, 0.04],  # parking
        [0.05, 0.03],  # sidewalk
        [0.05, 0.04],  # building
        [0.20, 0.18],  # tree canopy
        [0.16, 0.12],  # bush
        [0.10, 0.08],  # rock
        [0.02, 0.00],  # car
        [0.05, 0.00],  # fence
    ],
    dtype=np.float32,
)
_SRGB_LUT = (np.power(np.arange(4096, dtype=np.float32) / 4095, 1 / 2.2) * 255).astype(np.float32)
_SEASONS = np.array([[1.30, 1.05, 0.65], [1.35, 1.20, 0.85], [0.85, 1.12, 0.80]], np.float32)  # autumn, dry, spring
_VEGETATION = (SimClass.GRASS, SimClass.TREE, SimClass.BUSH)
_CHANGEABLE = (SimClass.CAR, SimClass.TREE, SimClass.BUSH, SimClass.ROCK, SimClass.BUILDING, SimClass.FENCE)


def render_orthophoto(world: World, cfg: OrthoRenderConfig, seed: int) -> Orthophoto:
    """Orthophoto of `world` at `cfg.meters_per_pixel` with the world's origin."""
    rng = np.random.default_rng(seed)
    if cfg.outdated:
        cls, height, albedo = _outdate(world, cfg.outdated_change_fraction, rng)
    else:
        cls, height, albedo = world.class_map, world.height, world.albedo
    h, w = world.shape
    scale = world.resolution_m / cfg.meters_per_pixel
    size = (max(1, int(round(w * scale))), max(1, int(round(h * scale))))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR  # area-average when shrinking
    alb = cv2.resize(albedo.astype(np.float32), size, interpolation=interp)
    hgt = cv2.resize(height.astype(np.float32), size, interpolation=interp)
    cls_o = cv2.resize(cls, size, interpolation=cv2.INTER_NEAREST)
    mpp = cfg.meters_per_pixel

    if cfg.texture_strength > 0:
        alb *= _texture(rng, cls_o, mpp, cfg.texture_strength)[..., None]
    ortho = Orthophoto(np.zeros((1, 1, 3), np.uint8), mpp, world.origin_xy)
    _paint_markings(alb, cls_o, world.road_centrelines, ortho)

    az, el = math.radians(cfg.sun_azimuth_deg), math.radians(cfg.sun_elevation_deg)
    sun = np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)], np.float32)
    smooth = cv2.GaussianBlur(hgt, (0, 0), 0.7)
    # Slopes clipped at ~70 deg so that mixed roof/ground pixels at walls stay plausible.
    dzdx = np.clip(np.gradient(smooth, axis=1) / mpp, -3, 3)
    dzdy = np.clip(-np.gradient(smooth, axis=0) / mpp, -3, 3)
    lambert = np.maximum((-dzdx * sun[0] - dzdy * sun[1] + sun[2]) / np.sqrt(1 + dzdx**2 + dzdy**2), 0.0)
    if cfg.shadows:
        lambert *= 1.0 - _shadow(hgt, mpp, az, el)
    irradiance = (AMBIENT + (1 - AMBIENT) * lambert) / (AMBIENT + (1 - AMBIENT) * sun[2])
    linear = alb * (irradiance * np.float32(4095))[..., None] * np.exp(rng.normal(0, 0.04, 3)).astype(np.float32)
    linear += rng.standard_normal(linear.shape[:2], dtype=np.float32)[..., None] * np.float32(16)  # sensor noise
    srgb = _SRGB_LUT[np.clip(linear, 0, 4095).astype(np.uint16)]  # white balance above, gamma here
    image = cv2.GaussianBlur(srgb, (0, 0), 0.5)  # optics / resampling softness
    return Orthophoto(np.clip(image + 0.5, 0, 255).astype(np.uint8), mpp, world.origin_xy)


def _texture(rng: np.random.Generator, cls: np.ndarray, mpp: float, strength: float) -> np.ndarray:
    """Multiplicative brightness texture: per-class grain and mottling (canopy clumps, grass tufts)."""
    fine = cv2.GaussianBlur(rng.standard_normal(cls.shape, dtype=np.float32), (0, 0), 0.8)
    fine /= max(float(fine.std()), 1e-6)
    mottle = smooth_noise(rng, cls.shape, 1.5 / mpp)
    amp = _TEXTURE[cls]
    return np.maximum(1.0 + strength * (amp[..., 0] * fine + amp[..., 1] * mottle), 0.2)


def _paint_markings(alb: np.ndarray, cls: np.ndarray, centrelines: list[np.ndarray], ortho: Orthophoto) -> None:
    """Dashed white centre lines (3 m dash, 6 m gap) on road pixels."""
    if not centrelines:
        return
    mask = np.zeros(cls.shape, np.float32)
    width = max(1, int(round(0.15 / ortho.meters_per_pixel)))
    for line in centrelines:
        seg = np.diff(line, axis=0)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
        t = np.arange(0.0, s[-1], 0.5)
        pts = np.stack([np.interp(t, s, line[:, 0]), np.interp(t, s, line[:, 1])], axis=1)
        on = (t % 9.0) < 3.0
        starts = np.flatnonzero(on & ~np.roll(on, 1))
        ends = np.flatnonzero(on & ~np.roll(on, -1))
        px = np.round(ortho.world_to_pixel(pts) * 16).astype(np.int32)
        dashes = [px[a : b + 1] for a, b in zip(starts, ends) if b > a]
        cv2.polylines(mask, dashes, False, 1.0, thickness=width, lineType=cv2.LINE_AA, shift=4)
    on = (mask > 0) & (cls == SimClass.ROAD)
    alb[on] += (np.array([0.80, 0.80, 0.76], np.float32) - alb[on]) * (0.85 * mask[on][:, None])


def _shadow(height: np.ndarray, mpp: float, az: float, el: float) -> np.ndarray:
    """Cast-shadow strength in [0, 1]. The height map is rotated so that sun rays run along
    rows; then the shadow surface is one running maximum, max_{j<=i}(h_j + j t) - i t."""
    h, w = height.shape
    phi = math.atan2(math.cos(az), -math.sin(az))  # image direction (col, row) the light travels
    c, s = math.cos(phi), math.sin(phi)
    wr = int(math.ceil(abs(w * c) + abs(h * s))) + 2
    hr = int(math.ceil(abs(w * s) + abs(h * c))) + 2
    M = np.array([[c, s, wr / 2 - c * w / 2 - s * h / 2], [-s, c, hr / 2 + s * w / 2 - c * h / 2]])
    low = float(height.min()) - 1e3
    rot = cv2.warpAffine(height, M, (wr, hr), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=low)
    ramp = np.arange(wr, dtype=np.float32) * np.float32(math.tan(el) * mpp)
    depth = np.maximum.accumulate(rot + ramp, axis=1) - ramp - rot
    back = cv2.warpAffine(depth, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    shadow = np.clip((back - 0.1) / 0.25, 0.0, 1.0)
    return cv2.GaussianBlur(shadow, (0, 0), 0.6)  # penumbra


def _outdate(world: World, fraction: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Copies of (class, height, albedo) with a seasonal vegetation colour, a `fraction` of the
    movable objects removed (buildings a third as often) and a few new cars and bushes/trees."""
    cls, height, albedo = world.class_map.copy(), world.height.copy(), world.albedo.copy()
    veg = np.isin(cls, [int(c) for c in _VEGETATION])
    albedo[veg] = np.clip(albedo[veg] * _SEASONS[rng.integers(len(_SEASONS))], 0, 1)

    obj_cls = np.array([o.class_id for o in world.objects], dtype=np.int64)
    p = np.where(obj_cls == SimClass.BUILDING, fraction / 3, fraction) * np.isin(obj_cls, [int(c) for c in _CHANGEABLE])
    removed = np.concatenate([[False], rng.random(len(obj_cls)) < p])  # index instance + 1
    gone = removed[world.instance_map + 1]
    nearest = nearest_ground_index(world.class_map)[gone]
    cls[gone] = world.class_map.reshape(-1)[nearest]
    height[gone] = world.height.reshape(-1)[nearest]
    albedo[gone] = albedo.reshape(-1, 3)[nearest]

    terrain = height.reshape(-1)[nearest_ground_index(cls)]  # new objects stand on the ground under them
    canvas = Canvas(world.shape, world.resolution_m, world.origin_xy, terrain, cls)
    canvas.height, canvas.albedo = height, albedo
    canvas.instance_map = np.where(gone, -1, world.instance_map).astype(np.int32)
    n_new = int(round(fraction * len(obj_cls) / 4))
    _add_cars(canvas, rng, world, n_new)
    scatter_objects(canvas, rng, SimClass.BUSH, n_new, None, None, (SimClass.GRASS, SimClass.SOIL), BASE_COLOURS)
    scatter_objects(canvas, rng, SimClass.TREE, n_new / 2, None, None, (SimClass.GRASS,), BASE_COLOURS)
    return canvas.class_map, canvas.height, canvas.albedo


def _add_cars(canvas: Canvas, rng: np.random.Generator, world: World, count: int) -> None:
    """New cars on free parking cells, aligned with the nearest road."""
    rows, cols = np.nonzero(canvas.class_map == SimClass.PARKING)
    if count == 0 or len(rows) == 0 or not world.road_centrelines:
        return
    pts, tans = road_samples(world.road_centrelines, 2.0)
    tree = cKDTree(pts)
    placed = 0
    for k in rng.permutation(len(rows))[: 20 * count]:
        if placed >= count:
            break
        centre = np.array(canvas.cell_xy(np.float64(rows[k]), np.float64(cols[k])))
        t = tans[tree.query(centre)[1]]
        angle = math.atan2(t[1], t[0]) + rng.choice([0.0, math.pi / 2])
        poly = rect_polygon(centre, angle, *CAR_SIZE_M[:2])
        if canvas.fits(poly, (SimClass.PARKING,), margin_m=0.3):
            canvas.add_object(SimClass.CAR, poly, CAR_SIZE_M[2], car_colour(rng), car_colour(rng))
            placed += 1

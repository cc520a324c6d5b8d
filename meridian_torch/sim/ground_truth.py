"""Ground truth of simulated worlds: region-border polylines, and saving/loading it to a folder.

Folder layout written by `save_ground_truth` (all coordinates world metres, x east, y north):

- `world.json`: `{"schema": "meridian-sim-ground-truth/1", "resolution_m": r, "origin_xy": [x0, y0],
  "shape": [H, W], "classes": {"0": "grass", ...}, "road_centrelines": [[[x, y], ...], ...]}`.
  `origin_xy` is the top-left corner of raster cell (0, 0); cell (row, col) covers
  x in [x0 + col*r, x0 + (col+1)*r], y in [y0 - (row+1)*r, y0 - row*r].
- `objects.json`: `{"objects": [{"id": int, "class": name, "centre_xy": [x, y], "height_m": h,
  "shape": "polygon" | "polyline", "footprint_xy": [[x, y], ...]}, ...]}`; polygons are closed
  implicitly (first vertex not repeated); fences are polylines.
- `borders.json`: `{"borders": [{"class_a": name, "class_b": name, "polyline_xy": [[x, y], ...]}, ...]}`
  with class_a < class_b in SimClass order; building outlines appear as borders whose
  class_b is "building".
- `class_map.png`: (H, W) uint8 SimClass ids. `height.npy`: (H, W) float16 surface height (m).
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import shapely

from meridian_torch.errors import SimulationError
from meridian_torch.io.atomic import write_bytes_atomic, write_text_atomic
from meridian_torch.sim.classes import CLASS_NAMES, REGION_CLASSES, SimClass, class_by_name
from meridian_torch.sim.world import RegionBorder, World, WorldObject

__all__ = ["GroundTruth", "nearest_ground_index", "ground_layer", "extract_region_borders", "save_ground_truth", "load_ground_truth"]

SCHEMA = "meridian-sim-ground-truth/1"
SIMPLIFY_TOLERANCE_M = 0.3
MIN_BORDER_LENGTH_M = 2.0

# 8-neighbourhood offsets (drow, dcol).
_NEIGHBOURS = np.array([[0, 1], [0, -1], [1, 0], [-1, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]])


@dataclass
class GroundTruth:
    """What `load_ground_truth` returns: the saved part of a World."""

    resolution_m: float
    origin_xy: tuple[float, float]
    class_map: np.ndarray
    height: np.ndarray
    objects: list[WorldObject] = field(default_factory=list)
    borders: list[RegionBorder] = field(default_factory=list)
    road_centrelines: list[np.ndarray] = field(default_factory=list)


def nearest_ground_index(class_map: np.ndarray) -> np.ndarray:
    """(H, W) flat index of the nearest region (ground) cell; ground cells point to themselves."""
    is_obj = ~np.isin(class_map, [int(c) for c in REGION_CLASSES])
    if is_obj.all():
        raise SimulationError("the world has no ground cells")
    if not is_obj.any():
        return np.arange(class_map.size).reshape(class_map.shape)
    _, labels = cv2.distanceTransformWithLabels(is_obj.astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    ground = ~is_obj
    lut = np.zeros(int(labels.max()) + 1, np.int64)
    lut[labels[ground]] = np.flatnonzero(ground)
    return lut[labels]


def ground_layer(world: World) -> tuple[np.ndarray, np.ndarray]:
    """(region class, ground height) of every cell; cells of objects take the values of the
    nearest region cell, i.e. what lies under the object."""
    nearest = nearest_ground_index(world.class_map)
    return world.class_map.reshape(-1)[nearest], world.height.reshape(-1)[nearest].astype(np.float32)


def extract_region_borders(world: World) -> list[RegionBorder]:
    """Polylines (world metres) between different region classes and around buildings.

    Objects other than buildings are replaced by the ground under them. Each border is
    traced once, on the side of its lower class id, moved half a cell onto the class edge,
    simplified to 0.3 m and kept if at least 2 m long.
    """
    regions, _ = ground_layer(world)
    regions[world.class_map == SimClass.BUILDING] = SimClass.BUILDING
    padded = np.pad(regions, 1, constant_values=255)  # 255 = off the map, never a border
    res = world.resolution_m
    min_pts = max(2, int(MIN_BORDER_LENGTH_M / res / 1.5))
    borders: list[RegionBorder] = []
    for a in np.unique(regions):
        contours, _ = cv2.findContours((regions == a).astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        for cnt in contours:
            if len(cnt) < min_pts:
                continue
            cols, rows = cnt[:, 0, 0], cnt[:, 0, 1]
            neigh = padded[rows[:, None] + 1 + _NEIGHBOURS[:, 0], cols[:, None] + 1 + _NEIGHBOURS[:, 1]]
            higher = np.where((neigh > a) & (neigh != 255), neigh, 255)
            other = higher.min(axis=1)
            # Move each point half a cell towards the neighbours of its partner class.
            toward = (neigh == other[:, None]) & (other[:, None] != 255)
            step = (toward[..., None] * _NEIGHBOURS[None]).sum(1) / np.maximum(toward.sum(1), 1)[:, None]
            norm = np.maximum(np.linalg.norm(step, axis=1, keepdims=True), 1e-9)
            rc = np.stack([rows, cols], 1) + 0.5 * step / norm * (norm > 1e-6)
            xy = world.cell_to_world(rc[:, ::-1])
            borders.extend(_runs_to_borders(int(a), other, xy))
    return borders


def _runs_to_borders(a: int, other: np.ndarray, xy: np.ndarray) -> list[RegionBorder]:
    """Split a closed contour into runs of one partner class and turn them into borders."""
    n = len(other)
    change = np.flatnonzero(other != np.roll(other, 1))
    if len(change) == 0:
        if other[0] == 255:
            return []
        runs = [(other[0], np.vstack([xy, xy[:1]]))]
    else:
        start = change[0]
        other, xy = np.roll(other, -start), np.roll(xy, -start, axis=0)
        bounds = np.append(change - start, n)
        runs = [(other[s], xy[s:e]) for s, e in zip(bounds[:-1], bounds[1:])]
    out = []
    for b, pts in runs:
        if b == 255 or len(pts) < 2:
            continue
        line = shapely.LineString(pts).simplify(SIMPLIFY_TOLERANCE_M)
        if line.length >= MIN_BORDER_LENGTH_M:
            out.append(RegionBorder(a, int(b), np.asarray(line.coords)))
    return out


def _xy_list(a: np.ndarray) -> list[list[float]]:
    return np.round(np.asarray(a, dtype=np.float64), 3).tolist()


def save_ground_truth(world: World, folder: str | os.PathLike[str]) -> None:
    """Write world.json, objects.json, borders.json, class_map.png and height.npy (atomically each)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    meta = {
        "schema": SCHEMA,
        "resolution_m": world.resolution_m,
        "origin_xy": list(world.origin_xy),
        "shape": list(world.shape),
        "classes": {str(k): v for k, v in CLASS_NAMES.items()},
        "road_centrelines": [_xy_list(c) for c in world.road_centrelines],
    }
    objects = [
        {"id": o.object_id, "class": CLASS_NAMES[o.class_id], "centre_xy": _xy_list(o.centre_xy),
         "height_m": round(o.height_m, 3), "shape": "polyline" if o.class_id == SimClass.FENCE else "polygon",
         "footprint_xy": _xy_list(o.footprint_xy)}
        for o in world.objects
    ]
    borders = [
        {"class_a": CLASS_NAMES[b.class_a], "class_b": CLASS_NAMES[b.class_b], "polyline_xy": _xy_list(b.polyline_xy)}
        for b in world.borders
    ]
    ok, png = cv2.imencode(".png", world.class_map.astype(np.uint8), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise SimulationError("could not encode the class map as PNG")
    buf = io.BytesIO()
    np.save(buf, world.height.astype(np.float16))
    write_bytes_atomic(folder / "class_map.png", png.tobytes())
    write_bytes_atomic(folder / "height.npy", buf.getvalue())
    write_text_atomic(folder / "objects.json", json.dumps({"objects": objects}, separators=(",", ":")))
    write_text_atomic(folder / "borders.json", json.dumps({"borders": borders}, separators=(",", ":")))
    write_text_atomic(folder / "world.json", json.dumps(meta, separators=(",", ":")))  # last: marks completion


def load_ground_truth(folder: str | os.PathLike[str]) -> GroundTruth:
    """Read what `save_ground_truth` wrote."""
    folder = Path(folder)
    try:
        meta = json.loads((folder / "world.json").read_text())
        objects = json.loads((folder / "objects.json").read_text())["objects"]
        borders = json.loads((folder / "borders.json").read_text())["borders"]
        class_map = cv2.imread(str(folder / "class_map.png"), cv2.IMREAD_UNCHANGED)
        height = np.load(folder / "height.npy").astype(np.float32)
    except (OSError, KeyError, ValueError) as exc:
        raise SimulationError(f"{folder}: unreadable ground truth: {exc}") from exc
    if meta.get("schema") != SCHEMA or class_map is None or class_map.shape != tuple(meta["shape"]):
        raise SimulationError(f"{folder}: not a {SCHEMA} folder or its rasters do not match world.json")
    return GroundTruth(
        resolution_m=float(meta["resolution_m"]),
        origin_xy=(float(meta["origin_xy"][0]), float(meta["origin_xy"][1])),
        class_map=class_map,
        height=height,
        objects=[WorldObject(int(o["id"]), int(class_by_name(o["class"])), tuple(o["centre_xy"]),
                             np.asarray(o["footprint_xy"], dtype=np.float64), float(o["height_m"])) for o in objects],
        borders=[RegionBorder(int(class_by_name(b["class_a"])), int(class_by_name(b["class_b"])),
                              np.asarray(b["polyline_xy"], dtype=np.float64)) for b in borders],
        road_centrelines=[np.asarray(c, dtype=np.float64) for c in meta["road_centrelines"]],
    )

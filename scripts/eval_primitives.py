#!/usr/bin/env python
"""Aerial-map primitives (points, lines) against ground truth on simulated and real orthophotos.

Builds the aerial map (`build_aerial_map`, configs/default.yaml perception/primitive settings)
of a centred square crop (`--crop-m`) of each dataset's orthophoto and scores its primitives with
`meridian_torch.evaluation.primitive_metrics` (see that module for the exact metric):
points: optimal one-to-one (Hungarian) matching within 2 m, after merging the duplicates of
overlapping patches (0.5 m); lines: by length, a piece counts when within 1 m of a GT line whose
direction is within 10 deg, predicted lines taken as a union (overlap duplicates counted once).
Only primitives / GT inside the crop shrunk by `--margin-m` count (patch borders of the image
edge produce spurious lines).

Ground truth per dataset
  sim-tiny      configs/tiny.yaml world (120 x 120 m; the crop is the whole world).
  sim-default   configs/default.yaml world (400 x 400 m), centre crop of --crop-m.
  sim-outdated  the sim-default world and crop, orthophoto rendered with `outdated: true`
                (season colours, some objects removed/added; GT is the current world).
      Simulated GT: points = centres of compact non-building objects (tree, bush, rock, car)
      with footprint area < 50 m^2; lines = world.borders polylines (borders between region
      classes) + building footprint outlines.
  deepforest    NEON 0.1 m image 2019_YELL_2_528000_4978000_image_crop2.jpg (no georeference:
                world frame = pixel grid x 0.1 m, origin at the top-left corner); points = centres
                of the VOC tree boxes. Points only (no line GT). Point precision is a lower
                bound: predicted points also come from logs, shrubs, shadows.
  spacenet      solaris sample_geotiff.tif (0.5 m, panchromatic, EPSG:32616) with
                geotiff_labels.geojson: lines = building footprint outlines. No point GT: the
                houses are 100-300 m^2 (none is a compact object), and trees/cars are not
                labelled, so point precision would be meaningless. Line precision is a lower
                bound: road edges and tree/lawn borders are real edges without labels. (The road
                centrelines of the folder belong to another tile, road_mask_input.tif, in
                EPSG:4326, which read_orthophoto rejects; not used.)
  kitti0        world from the cross_view_slam kitti0 class masks (WorldConfig kind class_raster,
                0.5 m cells, classes terrain->grass, road->road, building->building,
                vegetation->tree; flipped vertically), rendered at 0.3 m, centre crop; GT as for
                simulated worlds (class borders and building outlines = lines, the synthesized
                trees/cars < 50 m^2 = points).

Example: python scripts/eval_primitives.py --datasets sim-tiny deepforest --crop-m 60
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import torch

from meridian_torch.config import load_config
from meridian_torch.evaluation.primitive_metrics import (
    batch_primitives,
    line_metrics,
    point_metrics,
    polygon_ring,
    world_ground_truth,
)
from meridian_torch.io.ortho import Orthophoto, read_orthophoto
from meridian_torch.mapping.aerial_map import AerialMapper, build_aerial_map

REPO = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DATASETS = ("sim-tiny", "sim-default", "sim-outdated", "deepforest", "spacenet", "kitti0")


def crop_orthophoto(ortho: Orthophoto, size_m: float | None) -> Orthophoto:
    """Centred square crop of `size_m` (None or larger than the image: unchanged)."""
    if size_m is None:
        return ortho
    w, h = ortho.size_px
    n = int(round(size_m / ortho.meters_per_pixel))
    cw, ch = min(n, w), min(n, h)
    c0, r0 = (w - cw) // 2, (h - ch) // 2
    x0, y0 = ortho.origin_xy
    mpp = ortho.meters_per_pixel
    return Orthophoto(np.ascontiguousarray(ortho.image[r0:r0 + ch, c0:c0 + cw]), mpp,
                      (x0 + c0 * mpp, y0 - r0 * mpp), ortho.crs)


def extent(ortho: Orthophoto) -> tuple[float, float, float, float]:
    w, h = ortho.size_px
    x0, y0 = ortho.origin_xy
    return x0, x0 + w * ortho.meters_per_pixel, y0 - h * ortho.meters_per_pixel, y0


# ------------------------------------------------------------------------------ datasets
# Each loader returns (orthophoto, gt points (M, 2) or None, gt polylines or None, note).


def _sim(config: Path, outdated: bool = False, overrides: tuple[str, ...] = ()):
    from meridian_torch.sim.ortho_render import render_orthophoto
    from meridian_torch.sim.simulate import _stage_seeds, build_world

    cfg = load_config(config, list(overrides))
    world = build_world(cfg.sim)
    ortho_cfg = cfg.sim.ortho.model_copy(update={"outdated": outdated})
    ortho = render_orthophoto(world, ortho_cfg, _stage_seeds(cfg.sim.seed)["ortho"])
    points, lines = world_ground_truth(world)
    return ortho, points, lines


def load_dataset(name: str):
    if name == "sim-tiny":
        return _sim(REPO / "configs" / "tiny.yaml")
    if name in ("sim-default", "sim-outdated"):
        return _sim(REPO / "configs" / "default.yaml", outdated=name == "sim-outdated")
    if name == "deepforest":
        folder = DATA / "deepforest_neon"
        stem = "2019_YELL_2_528000_4978000_image_crop2"
        import cv2

        image = cv2.cvtColor(cv2.imread(str(folder / f"{stem}.jpg"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        mpp = 0.1  # README: NEON 0.1 m ground sample distance
        ortho = Orthophoto(np.ascontiguousarray(image), mpp, (0.0, image.shape[0] * mpp))
        boxes = []
        for box in ET.parse(folder / f"{stem}.xml").getroot().iter("bndbox"):
            boxes.append([float(box.find(k).text) for k in ("xmin", "ymin", "xmax", "ymax")])
        b = np.asarray(boxes)
        # VOC box corners are pixel-edge coordinates: centre col = (xmin + xmax) / 2 - 0.5.
        centres = ortho.pixel_to_world(np.stack([(b[:, 0] + b[:, 2]) / 2 - 0.5, (b[:, 1] + b[:, 3]) / 2 - 0.5], 1))
        return ortho, centres, None
    if name == "spacenet":
        folder = DATA / "solaris_spacenet"
        ortho = read_orthophoto(folder / "sample_geotiff.tif")
        gj = json.loads((folder / "geotiff_labels.geojson").read_text())
        lines = []
        for feat in gj["features"]:
            geom = feat["geometry"]
            polys = [geom["coordinates"]] if geom["type"] == "Polygon" else geom["coordinates"]
            for poly in polys:
                for ring in poly:  # exterior and holes
                    lines.append(polygon_ring(np.asarray(ring, dtype=np.float64)[:, :2]))
        return ortho, None, lines
    if name == "kitti0":
        return _kitti0_world()
    raise ValueError(f"unknown dataset {name!r}")


def _kitti0_world():
    from meridian_torch.config.sim import ClassRasterConfig, OrthoRenderConfig, WorldConfig
    from meridian_torch.sim.from_raster import world_from_class_raster
    from meridian_torch.sim.ortho_render import render_orthophoto

    raster = ClassRasterConfig(path=str(DATA / "cross_view_slam_maps" / "kitti0"), meters_per_pixel=1 / 3.0671,
                               flip_vertical=True, object_spacing_m=10.0,
                               classes={0: "grass", 1: "road", 3: "building", 4: "tree"})
    world = world_from_class_raster(WorldConfig(kind="class_raster", class_raster=raster, resolution_m=0.5), seed=0)
    ortho = render_orthophoto(world, OrthoRenderConfig(meters_per_pixel=0.3), seed=0)
    points, lines = world_ground_truth(world)
    return ortho, points, lines


# ------------------------------------------------------------------------------ evaluation


def evaluate(name: str, mapper: AerialMapper, crop_m: float | None, margin_m: float, args) -> dict:
    t0 = time.perf_counter()
    ortho, gt_points, gt_lines = load_dataset(name)
    if name == "sim-tiny":
        crop_m = None  # the tiny world is the crop
    ortho = crop_orthophoto(ortho, crop_m)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    amap = build_aerial_map(ortho, mapper)
    t_map = time.perf_counter() - t0
    points, segments, n_unbounded = batch_primitives(amap.primitives)
    points, segments = points + amap.local_origin_xy, segments + amap.local_origin_xy  # map frame -> world
    region = extent(ortho)
    row = {"dataset": name, "size_m": f"{region[1] - region[0]:.0f}x{region[3] - region[2]:.0f}",
           "patches": len(amap.patches), "load_s": t_load, "map_s": t_map, "unbounded_lines": n_unbounded}
    if gt_points is not None:
        row["points"] = point_metrics(points, gt_points, args.point_radius, region=region, margin=margin_m)
    if gt_lines is not None:
        row["lines"] = line_metrics(segments, gt_lines, args.line_dist, args.line_angle, args.sample_step,
                                    region=region, margin=margin_m)
    return row


def _f(v: float) -> str:
    return "  n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:5.2f}"


def print_table(rows: list[dict], args) -> None:
    head = (f"{'dataset':<13} {'area m':>8} {'patch':>5} | {'pt P':>5} {'pt R':>5} {'#pred':>6} {'#gt':>5} | "
            f"{'ln P':>5} {'ln R':>5} {'pred m':>7} {'gt m':>7} | {'map s':>6} {'load s':>6}")
    print(f"points: {args.point_radius} m one-to-one (Hungarian); lines: {args.line_dist} m, {args.line_angle} deg, "
          f"by length (union); margin {args.margin_m} m")
    print(head)
    print("-" * len(head))
    for r in rows:
        p, ln = r.get("points"), r.get("lines")
        pt = (f"{_f(p['precision'])} {_f(p['recall'])} {p['n_pred']:6d} {p['n_gt']:5d}" if p
              else f"{'n/a':>5} {'n/a':>5} {'':>6} {'':>5}")
        li = (f"{_f(ln['precision'])} {_f(ln['recall'])} {ln['pred_length']:7.0f} {ln['gt_length']:7.0f}" if ln
              else f"{'n/a':>5} {'n/a':>5} {'':>7} {'':>7}")
        print(f"{r['dataset']:<13} {r['size_m']:>8} {r['patches']:5d} | {pt} | {li} | {r['map_s']:6.1f} {r['load_s']:6.1f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", nargs="+", choices=DATASETS, default=list(DATASETS))
    ap.add_argument("--crop-m", type=float, default=120.0,
                    help="evaluate a centred square crop of this size (m); 0 = whole image (slow)")
    ap.add_argument("--margin-m", type=float, default=3.0, help="ignore this border of the crop (m)")
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "default.yaml",
                    help="config whose perception / primitives / aerial_map blocks build the map")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    ap.add_argument("--point-radius", type=float, default=2.0)
    ap.add_argument("--line-dist", type=float, default=1.0)
    ap.add_argument("--line-angle", type=float, default=10.0)
    ap.add_argument("--sample-step", type=float, default=0.25)
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--json", type=Path, help="also write the rows as JSON")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config, args.set)
    mapper = AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives)
    rows = []
    for name in args.datasets:
        rows.append(evaluate(name, mapper, args.crop_m or None, args.margin_m, args))
        print(f"done {name}: {rows[-1]['map_s']:.1f} s", file=sys.stderr, flush=True)
    print_table(rows, args)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())

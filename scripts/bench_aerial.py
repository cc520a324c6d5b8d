#!/usr/bin/env python
"""Aerial-map build throughput: km^2 per minute, peak memory and per-stage time of build_aerial_map.

Builds a procedural world of --size-m x --size-m (default 1000 m = 1 km^2; configs/default.yaml
world settings), renders its orthophoto at --mpp (0.3 m/px) and times `build_aerial_map` with
torch limited to --threads (2) threads. With a smaller --size-m (e.g. 300) the time per patch is
extrapolated to 1 km^2 (patch count of the same tiling of a 1000 m image: 33 x 33 = 1089).

Stages are timed from this script without touching library code: the mapper's segmenter,
segment describer and global describer are wrapped in timing proxies, and
`segments_to_primitives` (conversion) is wrapped where aerial_map looks it up. "other" is the
rest (patch cropping, mask -> world points, bookkeeping, stacking).
Memory: ru_maxrss (peak resident set, MiB) after the world/orthophoto and after the map build.
With --workers N > 1 the same map is then built again with `aerial_map.workers` = N (worker
processes, no stage breakdown), checked identical, and the speed-up printed. Worker start-up
(a fresh interpreter importing torch, about 3 s) is included, so small images gain less.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

import meridian_torch.mapping.aerial_map as aerial_map_module
from meridian_torch.config import load_config
from meridian_torch.mapping.aerial_map import AerialMapper, build_aerial_map
from meridian_torch.mapping.tiling import tile_image
from meridian_torch.runtime import peak_rss_mib

REPO = Path(__file__).resolve().parents[1]


class StageTimer:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}

    def wrap(self, name: str, fn):
        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0
                self.calls[name] = self.calls.get(name, 0) + 1

        return timed


class _Proxy:
    """Forwards every attribute to `inner`, with one method replaced by a timed version."""

    def __init__(self, inner, method: str, timed) -> None:
        self._inner = inner
        setattr(self, method, timed)

    def __getattr__(self, name: str):
        return getattr(self._inner, name)


def _patch_count(size_m: float, mpp: float, patch_m: float, overlap: float) -> int:
    n = int(round(size_m / mpp))
    return len(tile_image(n, n, mpp, (0.0, 0.0), patch_m, overlap))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size-m", type=float, default=1000.0, help="world side length (m); < 1000 extrapolates")
    ap.add_argument("--mpp", type=float, default=0.3, help="orthophoto metres per pixel")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "default.yaml")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    ap.add_argument("--max-patches", type=int, default=None,
                    help="build only the first N patches of the tiling (time per patch is extrapolated)")
    ap.add_argument("--workers", type=int, default=2,
                    help="also build with this many worker processes and compare (1: skip)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    from meridian_torch.sim.ortho_render import render_orthophoto
    from meridian_torch.sim.simulate import _stage_seeds, build_world

    overrides = [f"sim.world.size_m=[{args.size_m},{args.size_m}]", f"sim.ortho.meters_per_pixel={args.mpp}", *args.set]
    cfg = load_config(args.config, overrides)
    t0 = time.perf_counter()
    world = build_world(cfg.sim)
    ortho = render_orthophoto(world, cfg.sim.ortho, _stage_seeds(cfg.sim.seed)["ortho"])
    del world
    t_world = time.perf_counter() - t0
    if args.max_patches is not None:  # a north-west crop holding about that many patches
        from meridian_torch.io.ortho import Orthophoto

        side_patches = max(1, int(np.ceil(np.sqrt(args.max_patches))))
        stride = cfg.aerial_map.patch_size_m * (1 - cfg.aerial_map.patch_overlap)
        side_px = int(round((cfg.aerial_map.patch_size_m + (side_patches - 1) * stride) / args.mpp))
        ortho = Orthophoto(np.ascontiguousarray(ortho.image[:side_px, :side_px]), ortho.meters_per_pixel,
                           ortho.origin_xy, ortho.crs)
    rss_before = peak_rss_mib()
    w, h = ortho.size_px
    area_km2 = w * h * args.mpp**2 / 1e6
    print(f"world + orthophoto: {t_world:.1f} s; image {w}x{h} px = {area_km2:.3f} km^2; "
          f"peak RSS so far {rss_before:.0f} MiB", flush=True)

    mapper = AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives)
    timer = StageTimer()
    mapper.segmenter = _Proxy(mapper.segmenter, "segment", timer.wrap("segmentation", mapper.segmenter.segment))
    mapper.describer = _Proxy(mapper.describer, "describe", timer.wrap("description", mapper.describer.describe))
    mapper.global_describer = _Proxy(mapper.global_describer, "describe",
                                     timer.wrap("global description", mapper.global_describer.describe))
    original = aerial_map_module.segments_to_primitives
    aerial_map_module.segments_to_primitives = timer.wrap("conversion", original)
    try:
        done = [0]

        def progress(k: int, n: int) -> None:
            if k and k != done[0]:
                print(f"  {k}/{n} patches, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
            done[0] = k

        t0 = time.perf_counter()
        amap = build_aerial_map(ortho, mapper, progress=progress)
        total = time.perf_counter() - t0
    finally:
        aerial_map_module.segments_to_primitives = original
    rss_after = peak_rss_mib()

    n_patches = len(amap.patches)
    per_patch = total / n_patches
    n_km2 = _patch_count(1000.0, args.mpp, cfg.aerial_map.patch_size_m, cfg.aerial_map.patch_overlap)
    minutes_km2 = per_patch * n_km2 / 60.0
    n_points = int(amap.primitives.point_valid.sum())
    n_lines = int(amap.primitives.line_valid.sum())
    print(f"\nbuild_aerial_map: {n_patches} patches in {total:.1f} s = {per_patch:.2f} s/patch "
          f"({torch.get_num_threads()} torch threads); {n_points} points, {n_lines} lines")
    print(f"{'stage':<20} {'seconds':>8} {'share':>6} {'s/patch':>8} {'calls':>6}")
    stages = dict(timer.seconds)
    stages["other"] = total - sum(stages.values())
    for name, sec in stages.items():
        print(f"{name:<20} {sec:8.1f} {sec / total:6.1%} {sec / n_patches:8.2f} {timer.calls.get(name, ''):>6}")
    print(f"\nthroughput: {area_km2 / (total / 60):.4f} km^2/min measured on {area_km2:.3f} km^2 "
          f"(edge patches of a small image overlap more)")
    print(f"1 km^2 at {args.mpp} m/px = {n_km2} patches -> {minutes_km2:.1f} min "
          f"= {1 / minutes_km2:.4f} km^2/min (extrapolated from s/patch)")
    print(f"peak RSS: {rss_before:.0f} MiB after world + orthophoto, {rss_after:.0f} MiB after the map build "
          f"(+{rss_after - rss_before:.0f} MiB)")
    if args.workers > 1:
        cfg_w = load_config(args.config, [*overrides, f"aerial_map.workers={args.workers}"])
        mapper_w = AerialMapper.from_config(cfg_w.aerial_map, cfg_w.perception, cfg_w.primitives)
        t0 = time.perf_counter()
        amap_w = build_aerial_map(ortho, mapper_w)
        total_w = time.perf_counter() - t0
        same = all(
            torch.equal(getattr(amap.primitives, k), getattr(amap_w.primitives, k))
            for k in ("points_xy", "point_valid", "line_endpoints", "line_valid", "line_descriptors")
        )
        minutes_w = total_w / n_patches * n_km2 / 60.0
        print(f"\n{args.workers} worker processes: {total_w:.1f} s = {total_w / n_patches:.2f} s/patch, "
              f"{total / total_w:.2f}x the single process; identical map: {same}")
        print(f"1 km^2 -> {minutes_w:.1f} min = {1 / minutes_w:.4f} km^2/min "
              f"(each worker holds its own copy of the orthophoto and the back ends)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Cost of opening a large aerial map for `localize` (issue 18, item 4): open time and memory.

Large maps are made by tiling a real map's patches on a k x k grid of shifted copies (the copies
keep every array's content; only positions, pixel boxes and grid indices move), written with the
package's current map format, then opened in a fresh process each, which reports:
- open: `load_aerial_map` (what `pipeline.prepare.open_aerial_map` does, without the config check);
- start: `AerialMap.to(device)` and the `Localizer` (what `LiveLocalizer` does before any frame);
- coarse (with --coarse): the coarse-search map, built on the first submap in 'auto' mode on maps
  of more than `exhaustive_max_patches` patches (rasterises every patch's primitives).
Memory is /proc/self/status after each step: RssAnon (the process's own memory), RssFile (mapped
file pages, clean: the kernel can drop them) and VmHWM (peak resident set).

    python scripts/bench_map_open.py --map runs/kitti09-7hz/aerial.mtm --sides 1 4 7 --out maps-bench
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch


def tiled_map(source, side: int):
    """`side` x `side` copies of `source`, shifted by its extent rounded up to the patch stride."""
    from meridian_torch.types import PatchGrid, PrimitiveBatch

    p = source.patches
    grid = p.grid_index.max(0) + 1  # (columns, rows)
    stride_m = np.diff(np.unique(p.centres_xy[:, 0]))[0]
    step_m = grid * stride_m + stride_m  # one empty column/row between copies
    step_px = np.round(step_m / source.meters_per_pixel).astype(np.int64)
    copies = [(i, j) for j in range(side) for i in range(side)]
    shift = lambda a, per_copy: np.concatenate([a + np.asarray(per_copy(i, j)) for i, j in copies])  # noqa: E731
    patches = PatchGrid(
        pixel_boxes=shift(p.pixel_boxes, lambda i, j: [i * step_px[0], j * step_px[1]] * 2),
        grid_index=shift(p.grid_index, lambda i, j: [i * (grid[0] + 1), j * (grid[1] + 1)]),
        bounds_xy=shift(p.bounds_xy, lambda i, j: [i * step_m[0], i * step_m[0], j * step_m[1], j * step_m[1]]),
        centres_xy=shift(p.centres_xy, lambda i, j: [i * step_m[0], j * step_m[1]]),
    )
    prims = source.primitives
    offsets = torch.tensor([[i * step_m[0], j * step_m[1]] for i, j in copies], dtype=prims.points_xy.dtype)
    n = len(copies)
    rep = lambda t: t.repeat(n, *([1] * (t.dim() - 1)))  # noqa: E731
    offset_per_patch = offsets.repeat_interleave(len(prims), 0)
    primitives = PrimitiveBatch(
        points_xy=(rep(prims.points_xy) + offset_per_patch[:, None]) * rep(prims.point_valid)[..., None],
        point_descriptors=rep(prims.point_descriptors),
        point_valid=rep(prims.point_valid),
        line_endpoints=(rep(prims.line_endpoints) + offset_per_patch[:, None, None]) * rep(prims.line_valid)[..., None, None],
        line_kinds=rep(prims.line_kinds),
        line_descriptors=rep(prims.line_descriptors),
        line_valid=rep(prims.line_valid),
    )
    size = (int(source.image_size[0] + (side - 1) * step_px[0]), int(source.image_size[1] + (side - 1) * step_px[1]))
    return dataclasses.replace(
        source, patches=patches, primitives=primitives, global_descriptors=rep(source.global_descriptors),
        image_size=size, content_hash="",
    )


def memory_mib() -> dict[str, float]:
    status = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines() if ":" in line)
    return {k: round(int(status[k].split()[0]) / 1024, 1) for k in ("RssAnon", "RssFile", "VmHWM")}


def measure(path: Path, coarse: bool) -> dict:
    """One map opened as `localize` opens it (run in a fresh process)."""
    from meridian_torch.backend.localizer import Localizer
    from meridian_torch.config import load_config
    from meridian_torch.io.map_file import load_aerial_map
    from meridian_torch.matching.place_recognition import CoarseSearch

    cfg = load_config(None)
    out = {"baseline": memory_mib()}
    start = time.perf_counter()
    aerial_map = load_aerial_map(path)
    out["open_s"] = round(time.perf_counter() - start, 2)
    out["open"] = memory_mib()
    start = time.perf_counter()
    localizer = Localizer(aerial_map.to("cpu"), cfg, seed=0)
    out["start_s"] = round(time.perf_counter() - start, 2)
    out["start"] = memory_mib()
    if not coarse:
        return out
    start = time.perf_counter()
    bounds = torch.as_tensor(localizer.aerial_map.patches.bounds_xy, dtype=torch.float64)
    CoarseSearch(localizer.aerial_map.primitives, bounds, cfg.matching.place_recognition.coarse)
    out["coarse_s"] = round(time.perf_counter() - start, 2)
    out["coarse"] = memory_mib()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--map", type=Path, help="the map whose patches are tiled")
    parser.add_argument("--sides", type=int, nargs="+", default=[1, 4, 7], help="copies per side of each map")
    parser.add_argument("--out", type=Path, default=Path.home() / ".cache" / "meridian-torch" / "bench_map_open",
                        help="folder for the tiled maps (default: ~/.cache/meridian-torch/bench_map_open)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--coarse", action="store_true", help="also build the coarse-search map (slow on large maps)")
    parser.add_argument("--measure", type=Path, help="measure this map file only (in this process)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.measure:
        print(json.dumps(measure(args.measure, args.coarse)))
        return
    from meridian_torch.io.map_file import load_aerial_map, save_aerial_map

    source = load_aerial_map(args.map)
    args.out.mkdir(parents=True, exist_ok=True)
    for side in args.sides:
        big = tiled_map(source, side)
        path = args.out / f"map_{len(big)}.mtm"
        start = time.perf_counter()
        save_aerial_map(big, path)
        write_s = time.perf_counter() - start
        del big
        child = subprocess.run([sys.executable, __file__, "--measure", str(path), "--threads", str(args.threads)]
                               + ["--coarse"] * args.coarse, check=True, capture_output=True, text=True)
        row = {"patches": len(source) * side * side, "file_mib": round(path.stat().st_size / 2**20, 1),
               "write_s": round(write_s, 2), **json.loads(child.stdout), "loadavg": os.getloadavg()[0]}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Aerial-map build throughput and memory: km^2 per minute, peak RSS and per-stage time, per engine.

Builds a procedural world of --size-m x --size-m (default 1000 m = 1 km^2; configs/default.yaml
world settings), renders its orthophoto at --mpp (0.3 m/px), writes it as a tiled GeoTIFF under a
temporary folder and builds its map from the file read box by box (io/ortho_source.py, as
build-map does), with torch limited to --threads (2) threads in this process. With a smaller
--size-m (e.g. 300) the time per patch is extrapolated to 1 km^2 (patch count of the same tiling
of a 1000 m image: 33 x 33 = 1089). --geotiff PATH builds from that file instead (no world);
--max-patches N builds only a north-west crop of about N patches (read from the same file), e.g.
to measure the memory of reading a large orthophoto without building all of it.
--write-geotiff PATH --tile-km SIDE only writes a SIDE x SIDE km tiled GeoTIFF made by repeating
the rendered orthophoto (written one strip at a time), for those memory measurements.
--assembly KM2 [KM2 ...] measures the last step of build-map, writing the map file from the part
files, without building large maps: the (--size-m) map is built once keeping its part files, and
for each area a part folder of that area's patch count is made by hard-linking them cyclically
(patch i is part i mod n: as many distinct patches, each a real one), keyed to the same GeoTIFF
with the area's image size; then, each in a fresh process, the in-memory writer (all parts loaded,
stacked, `save_aerial_map`: build-map before issue 18's streaming) and build-map's own
(`write_aerial_map`: the file written patch by patch, then opened memory mapped) write that map;
their peak RSS (VmHWM), time and whether the two files are byte for byte the same are printed.

Stages of the single-process build are timed from this script without touching library code: the
mapper's segmenter, segment describer and global describer are wrapped in timing proxies, and
`segments_to_primitives` (conversion) is wrapped where aerial_map looks it up. "other" is the
rest (reading patches, mask -> world points, bookkeeping, stacking). --profile FILE also runs
cProfile over the single-process build, timed by this process's CPU time (wall time on a shared
machine charges other processes' load to whatever function was running), writes its stats to
FILE and prints the functions taking most of it.
--baseline-src DIR [--rounds N] compares source trees side by side: the orthophoto is made once,
then this tree and DIR (e.g. a git worktree of an older commit) build it alternately, N times
each, single process, each build in a fresh interpreter importing its tree; it prints each tree's
CPU s/patch (median and range), stage times, km^2/min per core and whether the maps are
identical (sha256 over every map array).
With --workers N > 1 the same map is then built with N local worker processes, and with
--engine ray also on a local Ray cluster with N CPUs (N actors); each is checked identical.
Worker and cluster start-up (fresh interpreters importing torch, about 3 s; Ray's own services)
is included, so small images gain less. With both, it prints how far Ray is behind the workers and
how long a bare local cluster (no actors) takes to start and to stop: Ray's fixed cost.

Memory, MiB: this process's peak (VmHWM); the largest finished child process's peak
(RUSAGE_CHILDREN: local workers once the pool is shut down, and Ray's services started by this
process if they have been waited for); and the peak of the summed current RSS of this process and
all its descendants, sampled every 0.2 s (counts Ray's raylet, GCS and worker processes, which
are descendants of a cluster started here; shared pages are counted once per process; short
peaks between samples are missed). Ray's object store is shared memory, counted in the processes
that map it.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import filecmp
import hashlib
import json
import os
import pstats
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch
from _tree_child import config_in_tree, run_in_tree  # scripts/ is on sys.path when a script runs

import meridian_torch.mapping.aerial_map as aerial_map_module
from meridian_torch.config import load_config
from meridian_torch.io.map_file import save_aerial_map
from meridian_torch.io.ortho_source import OrthophotoSource, open_orthophoto
from meridian_torch.mapping.aerial_map import AerialMapper, build_aerial_map, write_aerial_map
from meridian_torch.mapping.tiling import tile_image
from meridian_torch.runtime import peak_rss_mib

REPO = Path(__file__).resolve().parents[1]
RESULT_TAG = "BENCH_AERIAL_RESULT "


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


def _children_peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0


def _tree_rss_mib(root: int) -> float:
    """Summed VmRSS of `root` and its descendants (from /proc), MiB."""
    parents, rss = {}, {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/status") as f:
                fields = dict(line.split(":", 1) for line in f if ":" in line)
            parents[int(entry.name)] = int(fields["PPid"])
            rss[int(entry.name)] = int(fields.get("VmRSS", "0 kB").split()[0]) / 1024.0
        except (OSError, KeyError, ValueError):
            continue
    tree, grew = {root}, True
    while grew:
        added = {pid for pid, ppid in parents.items() if ppid in tree and pid not in tree}
        tree |= added
        grew = bool(added)
    return sum(rss.get(pid, 0.0) for pid in tree)


class TreePeak:
    """Peak of the summed RSS of this process and its descendants, sampled in a thread."""

    def __init__(self, interval_s: float = 0.2) -> None:
        self.peak_mib = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(interval_s,), daemon=True)

    def _run(self, interval_s: float) -> None:
        while not self._stop.is_set():
            self.peak_mib = max(self.peak_mib, _tree_rss_mib(os.getpid()))
            self._stop.wait(interval_s)

    def __enter__(self) -> "TreePeak":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def _write_tiled_geotiff(path: Path, image: np.ndarray, mpp: float, width_px: int, height_px: int) -> None:
    """A tiled RGB GeoTIFF of width_px x height_px repeating `image`, written one strip at a time."""
    import rasterio
    from rasterio.transform import from_origin
    from rasterio.windows import Window

    h, w = image.shape[:2]
    strip_rows = 512
    with rasterio.open(path, "w", driver="GTiff", width=width_px, height=height_px, count=3, dtype="uint8",
                       crs="EPSG:32632", transform=from_origin(458_000.0, 5_429_000.0, mpp, mpp),
                       photometric="RGB", compress="deflate", tiled=True, blockxsize=512, blockysize=512) as ds:
        for r0 in range(0, height_px, strip_rows):
            rows = (np.arange(r0, min(r0 + strip_rows, height_px)) % h)[:, None]
            cols = (np.arange(width_px) % w)[None, :]
            ds.write(np.moveaxis(image[rows, cols], -1, 0), window=Window(0, r0, width_px, rows.shape[0]))


def _identical(a, b) -> bool:
    return all(torch.equal(v, getattr(b.primitives, k)) for k, v in vars(a.primitives).items()) and torch.equal(
        a.global_descriptors, b.global_descriptors)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size-m", type=float, default=1000.0, help="world side length (m); < 1000 extrapolates")
    ap.add_argument("--mpp", type=float, default=0.3, help="orthophoto metres per pixel")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads of this process")
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "default.yaml")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    ap.add_argument("--max-patches", type=int, default=None,
                    help="build only a north-west crop of about N patches (time per patch is extrapolated)")
    ap.add_argument("--workers", type=int, default=2,
                    help="also build with this many local worker processes and compare (1: skip)")
    ap.add_argument("--engine", choices=["local", "ray"], default="local",
                    help="ray: also build on a local Ray cluster with --workers CPUs and compare")
    ap.add_argument("--geotiff", type=Path, default=None, help="build from this orthophoto file (no world)")
    ap.add_argument("--read-only", action="store_true",
                    help="only read every patch box of the tiling through the file (no description): the reader's "
                         "time and peak memory over the whole orthophoto")
    ap.add_argument("--write-geotiff", type=Path, default=None, help="only write a tiled GeoTIFF (--tile-km)")
    ap.add_argument("--tile-km", type=float, default=2.0, help="side of the --write-geotiff image, km")
    ap.add_argument("--assembly", type=float, nargs="+", default=None, metavar="KM2",
                    help="measure writing the map file from the part files of maps of these areas (km^2)")
    ap.add_argument("--profile", type=Path, default=None,
                    help="cProfile (CPU time) of the single-process build: stats to this file, top functions printed")
    ap.add_argument("--baseline-src", type=Path, default=None,
                    help="also build with the source tree DIR, alternating (single process, fresh interpreters)")
    ap.add_argument("--rounds", type=int, default=2, help="builds of each tree with --baseline-src")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)  # one build; prints a JSON line
    ap.add_argument("--assembly-run", choices=["memory", "patchwise"], default=None,
                    help=argparse.SUPPRESS)  # one --assembly measurement, in a fresh process
    ap.add_argument("--assembly-out", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.baseline_src is not None and (args.profile or args.read_only or args.assembly or args.write_geotiff):
        ap.error("--baseline-src compares builds: not with --profile, --read-only, --assembly or --write-geotiff")
    if args.rounds < 1:
        ap.error(f"--rounds must be >= 1, got {args.rounds}")
    torch.set_num_threads(args.threads)
    if args.assembly_run is not None:
        return _assembly_run(args, load_config(args.config, args.set))

    overrides = [f"sim.world.size_m=[{args.size_m},{args.size_m}]", f"sim.ortho.meters_per_pixel={args.mpp}", *args.set]
    cfg = load_config(args.config, overrides)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_aerial_") as tmp:
        ortho_path = args.geotiff
        if ortho_path is None or args.write_geotiff is not None:
            from meridian_torch.sim.ortho_render import render_orthophoto
            from meridian_torch.sim.simulate import _stage_seeds, build_world

            world = build_world(cfg.sim)
            rendered = render_orthophoto(world, cfg.sim.ortho, _stage_seeds(cfg.sim.seed)["ortho"])
            del world
            height_px, width_px = rendered.image.shape[:2]
            if args.write_geotiff is not None:
                width_px = height_px = side_px = int(round(args.tile_km * 1000.0 / args.mpp))
            ortho_path = args.write_geotiff or Path(tmp) / "ortho.tif"
            _write_tiled_geotiff(ortho_path, rendered.image, rendered.meters_per_pixel, width_px, height_px)
            del rendered
            if args.write_geotiff is not None:
                print(f"wrote {ortho_path}: {side_px}x{side_px} px = {(side_px * args.mpp / 1000) ** 2:.2f} km^2, "
                      f"{ortho_path.stat().st_size / 2**20:.0f} MiB ({time.perf_counter() - t0:.0f} s)")
                return 0
        if args.assembly is not None:
            return _assembly(args, cfg, ortho_path, Path(tmp))
        if args.baseline_src is not None:
            return _compare_trees(args, cfg, ortho_path)
        return _bench(args, cfg, overrides, ortho_path, time.perf_counter() - t0)


def _map_digest(amap) -> str:
    """sha256 over every array of the map (primitives by name, then the global descriptors)."""
    digest = hashlib.sha256()
    for name, value in [*sorted(vars(amap.primitives).items()), ("global_descriptors", amap.global_descriptors)]:
        digest.update(name.encode())
        digest.update(value.contiguous().numpy().tobytes())
    return digest.hexdigest()


def _compare_trees(args: argparse.Namespace, cfg, ortho_path: Path) -> int:
    """--baseline-src: the same orthophoto built by this tree and the baseline, alternately."""
    trees = [("this tree", REPO), ("baseline", args.baseline_src.resolve())]
    runs: dict[str, list[dict]] = {label: [] for label, _ in trees}
    for k in range(args.rounds):
        for label, source in trees:
            argv = ["--child", "--geotiff", str(ortho_path), "--mpp", str(args.mpp), "--threads", str(args.threads),
                    "--workers", "1", "--config", str(config_in_tree(args.config, source)),
                    *[a for item in args.set for a in ("--set", item)]]
            if args.max_patches is not None:
                argv += ["--max-patches", str(args.max_patches)]
            result = run_in_tree(__file__, argv, source, RESULT_TAG)
            runs[label].append(result)
            print(f"round {k + 1} {label:<9} {result['cpu_s'] / result['patches']:.3f} CPU s/patch "
                  f"({result['patches']} patches, wall {result['wall_s']:.1f} s, load {result['load']:.1f})",
                  flush=True)
    n_km2 = _patch_count(1000.0, args.mpp, cfg.aerial_map.patch_size_m, cfg.aerial_map.patch_overlap)
    print(f"\n{'tree':<10} {'CPU s/patch median':>19} {'range':>14} {'km^2/min/core':>14}  stages, s/patch (median)")
    medians = {}
    for label, results in runs.items():
        per_patch = sorted(r["cpu_s"] / r["patches"] for r in results)
        medians[label] = float(np.median(per_patch))
        stage_names = results[0]["stages"]
        stages = ", ".join(f"{name} {np.median([r['stages'][name] / r['patches'] for r in results]):.3f}"
                           for name in stage_names)
        print(f"{label:<10} {medians[label]:19.3f} {per_patch[0]:6.3f}-{per_patch[-1]:.3f} "
              f"{60.0 / (medians[label] * n_km2):14.3f}  {stages}")
    digests = {r["digest"] for results in runs.values() for r in results}
    print(f"baseline / this tree: {medians['baseline'] / medians['this tree']:.2f}x CPU per patch; "
          f"identical maps: {len(digests) == 1}")
    return 0


def _assembly(args: argparse.Namespace, cfg, ortho_path: Path, tmp: Path) -> int:
    """--assembly: the part files of a small map, replicated to each area, written by both writers."""
    mapper = AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives)
    t0 = time.perf_counter()
    with open_orthophoto(ortho_path) as ortho:
        built = build_aerial_map(ortho, mapper, work_dir=tmp / "small.parts")
    parts = sorted((tmp / "small.parts").glob("patch_*.npz"))
    part_kib = sum(p.stat().st_size for p in parts) / len(parts) / 1024
    map_kib = (sum(v.nbytes for v in vars(built.primitives).values()) + built.global_descriptors.nbytes) / 1024
    print(f"built {len(parts)} patches of {ortho_path.name} in {time.perf_counter() - t0:.0f} s: "
          f"{part_kib:.0f} KiB per part file, {map_kib / len(parts):.0f} KiB of map arrays per patch", flush=True)
    del built
    for km2 in args.assembly:
        side_px = int(round(np.sqrt(km2) * 1000.0 / args.mpp))
        run_dir = tmp / f"{km2:g}km2"
        work_dir = run_dir / "patchwise.mtm.parts"  # where write_aerial_map looks for them
        work_dir.mkdir(parents=True)
        with open_orthophoto(ortho_path) as ortho:
            key = aerial_map_module._work_key(dataclasses.replace(ortho, size_px=(side_px, side_px)), mapper.config)
        (work_dir / "key.txt").write_text(key)
        n = len(tile_image(side_px, side_px, args.mpp, (0.0, 0.0), cfg.aerial_map.patch_size_m,
                           cfg.aerial_map.patch_overlap))
        for i in range(n):
            os.link(parts[i % len(parts)], work_dir / f"patch_{i:06d}.npz")
        rows = {}
        for writer in ("memory", "patchwise"):  # patchwise last: it removes the parts
            command = [sys.executable, str(Path(__file__).resolve()), "--geotiff", str(ortho_path), "--mpp",
                       str(args.mpp), "--config", str(args.config), *[a for s in args.set for a in ("--set", s)],
                       "--threads", "1", "--tile-km", str(side_px * args.mpp / 1000.0), "--assembly-run", writer,
                       "--assembly-out", str(run_dir / f"{writer}.mtm")]
            done = subprocess.run(command, capture_output=True, text=True)
            if done.returncode != 0:
                print(done.stderr, file=sys.stderr)
                return done.returncode
            rows[writer] = json.loads(done.stdout.splitlines()[-1])
        same = filecmp.cmp(run_dir / "memory.mtm", run_dir / "patchwise.mtm", shallow=False)
        print(f"\n{km2:g} km^2, {n} patches, map file {rows['memory']['file_mib']:.0f} MiB; files identical: {same}")
        for writer, row in rows.items():
            print(f"  {writer:<9} peak RSS {row['peak_mib']:6.0f} MiB ({row['before_mib']:.0f} before the "
                  f"write: imports, mapper), {row['seconds']:5.1f} s, load average {row['load']:.1f}")
        shutil.rmtree(run_dir)
    return 0


def _assembly_run(args: argparse.Namespace, cfg) -> int:
    """One --assembly writer in this (fresh) process; prints a JSON line."""
    mapper = AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives)
    out: Path = args.assembly_out
    side_px = int(round(args.tile_km * 1000.0 / args.mpp))
    with open_orthophoto(args.geotiff) as ortho:
        enlarged = dataclasses.replace(ortho, size_px=(side_px, side_px))
        source = {"orthophoto": str(args.geotiff.resolve())}
        before, t0 = peak_rss_mib(), time.perf_counter()
        if args.assembly_run == "memory":
            work_dir = out.with_name("patchwise.mtm.parts")
            save_aerial_map(build_aerial_map(enlarged, mapper, work_dir=work_dir, source=source), out)
        else:
            write_aerial_map(enlarged, mapper, out, source=source)
        seconds = time.perf_counter() - t0
    print(json.dumps({"before_mib": before, "peak_mib": peak_rss_mib(), "seconds": seconds,
                      "file_mib": out.stat().st_size / 2**20, "load": os.getloadavg()[0]}))
    return 0


def _bench(args: argparse.Namespace, cfg, overrides: list[str], ortho_path: Path, t_world: float) -> int:
    ortho: OrthophotoSource = open_orthophoto(ortho_path)
    full_w, full_h = ortho.size_px
    if args.max_patches is not None:  # a north-west crop holding about that many patches, read from the file
        side_patches = max(1, int(np.ceil(np.sqrt(args.max_patches))))
        stride = cfg.aerial_map.patch_size_m * (1 - cfg.aerial_map.patch_overlap)
        side_px = int(round((cfg.aerial_map.patch_size_m + (side_patches - 1) * stride) / args.mpp))
        ortho = dataclasses.replace(ortho, size_px=(min(side_px, full_w), min(side_px, full_h)))
    rss_before = peak_rss_mib()
    w, h = ortho.size_px
    area_km2 = w * h * args.mpp**2 / 1e6
    print(f"orthophoto {ortho_path.name}: {full_w}x{full_h} px = {full_w * full_h * args.mpp**2 / 1e6:.3f} km^2 "
          f"({ortho_path.stat().st_size / 2**20:.0f} MiB file; whole in memory would be "
          f"{full_w * full_h * 3 / 2**20:.0f} MiB); building {w}x{h} px = {area_km2:.3f} km^2; "
          f"world + file {t_world:.1f} s; peak RSS so far {rss_before:.0f} MiB", flush=True)

    if args.read_only:
        grid = tile_image(w, h, args.mpp, (0.0, 0.0), cfg.aerial_map.patch_size_m, cfg.aerial_map.patch_overlap)
        t0 = time.perf_counter()
        for box in grid.pixel_boxes:
            ortho.read_box(box)
        seconds = time.perf_counter() - t0
        print(f"read {len(grid)} patch boxes in {seconds:.1f} s ({seconds / len(grid) * 1e3:.1f} ms each); "
              f"peak RSS {peak_rss_mib():.0f} MiB (+{peak_rss_mib() - rss_before:.0f} MiB)")
        return 0
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

        profiler = cProfile.Profile(time.process_time) if args.profile is not None else None
        t0, cpu0 = time.perf_counter(), time.process_time()
        with TreePeak() as tree:
            if profiler is not None:
                profiler.enable()
            amap = build_aerial_map(ortho, mapper, progress=None if args.child else progress)
            if profiler is not None:
                profiler.disable()
        total, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    finally:
        aerial_map_module.segments_to_primitives = original
    rss_after = peak_rss_mib()
    if args.child:
        stages = dict(timer.seconds)
        stages["other"] = total - sum(stages.values())
        print(RESULT_TAG + json.dumps({"patches": len(amap.patches), "cpu_s": cpu, "wall_s": total, "stages": stages,
                                       "digest": _map_digest(amap), "load": os.getloadavg()[0]}), flush=True)
        return 0
    if profiler is not None:
        profiler.dump_stats(args.profile)
        print(f"\ncProfile (CPU time, profiler overhead included) written to {args.profile}; by own time:")
        pstats.Stats(str(args.profile)).sort_stats("tottime").print_stats(20)

    n_patches = len(amap.patches)
    per_patch = total / n_patches
    n_km2 = _patch_count(1000.0, args.mpp, cfg.aerial_map.patch_size_m, cfg.aerial_map.patch_overlap)
    minutes_km2 = per_patch * n_km2 / 60.0
    n_points = int(amap.primitives.point_valid.sum())
    n_lines = int(amap.primitives.line_valid.sum())
    map_mib = (sum(v.nbytes for v in vars(amap.primitives).values()) + amap.global_descriptors.nbytes) / 2**20
    print(f"\nbuild_aerial_map: {n_patches} patches in {total:.1f} s = {per_patch:.2f} s/patch "
          f"({torch.get_num_threads()} torch threads); {n_points} points, {n_lines} lines; map arrays "
          f"{map_mib:.1f} MiB ({map_mib * 1024 / n_patches:.0f} KiB per patch)")
    print(f"CPU time of this process: {cpu:.1f} s = {cpu / n_patches:.3f} s/patch (all its threads; less "
          f"sensitive than the wall time to other processes on a shared machine)")
    print(f"{'stage':<20} {'seconds':>8} {'share':>6} {'s/patch':>8} {'calls':>6}")
    stages = dict(timer.seconds)
    stages["other"] = total - sum(stages.values())
    for name, sec in stages.items():
        print(f"{name:<20} {sec:8.1f} {sec / total:6.1%} {sec / n_patches:8.2f} {timer.calls.get(name, ''):>6}")
    print(f"\nthroughput: {area_km2 / (total / 60):.4f} km^2/min measured on {area_km2:.3f} km^2 "
          f"(edge patches of a small image overlap more)")
    print(f"1 km^2 at {args.mpp} m/px = {n_km2} patches -> {minutes_km2:.1f} min "
          f"= {1 / minutes_km2:.4f} km^2/min (extrapolated from s/patch)")
    print(f"peak RSS: {rss_before:.0f} MiB before the build, {rss_after:.0f} MiB after it "
          f"(+{rss_after - rss_before:.0f} MiB); process tree sampled {tree.peak_mib:.0f} MiB")

    runs = []
    if args.workers > 1:
        runs.append((f"{args.workers} local worker processes", [f"aerial_map.workers={args.workers}"]))
    if args.engine == "ray":
        runs.append((f"Ray, local cluster of {args.workers} CPUs",
                     [f"aerial_map.workers={args.workers}", "aerial_map.engine=ray"]))
    seconds: dict[str, float] = {}  # per run, in order: the local workers, then Ray
    for name, run_overrides in runs:
        cfg_w = load_config(args.config, [*overrides, *run_overrides])
        mapper_w = AerialMapper.from_config(cfg_w.aerial_map, cfg_w.perception, cfg_w.primitives)
        t0 = time.perf_counter()
        with TreePeak() as tree:
            amap_w = build_aerial_map(ortho, mapper_w)
        total_w = seconds[name] = time.perf_counter() - t0
        minutes_w = total_w / n_patches * n_km2 / 60.0
        print(f"\n{name}: {total_w:.1f} s = {total_w / n_patches:.2f} s/patch, {total / total_w:.2f}x the "
              f"single process; identical map: {_identical(amap, amap_w)}")
        print(f"1 km^2 -> {minutes_w:.1f} min = {1 / minutes_w:.4f} km^2/min; {area_km2 / (total_w / 60):.4f} "
              f"km^2/min measured. Peak RSS, MiB: this process {peak_rss_mib():.0f}, largest finished child "
              f"{_children_peak_mib():.0f}, process tree sampled {tree.peak_mib:.0f}")
    if len(seconds) == 2:
        local, ray_total = seconds.values()
        start, stop = _bare_cluster_seconds(args.workers)
        print(f"\nRay behind the local workers: {ray_total / local - 1:+.1%}. A bare local cluster of "
              f"{args.workers} CPUs (no actors), started and stopped as the engine does: {start:.1f} + {stop:.1f} s, "
              f"{(start + stop) / local:.0%} of the workers' time")
    return 0


def _bare_cluster_seconds(cpus: int) -> tuple[float, float]:
    """Seconds to start and to stop the engine's local Ray cluster: the fixed part of a Ray build
    that local workers do not pay."""
    import ray

    from meridian_torch.mapping.aerial_engines import start_local_ray_cluster

    t0 = time.perf_counter()
    start_local_ray_cluster(cpus)
    t1 = time.perf_counter()
    ray.shutdown()
    return t1 - t0, time.perf_counter() - t1


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python
"""Simulator rendering throughput: ground RGB-D frames per second, peak memory, orthophoto seconds per km^2.

Builds a procedural world (default WorldConfig, --seed), renders --frames ground frames at
--width x --height in batches of --batch along a circle of poses through the world's centre
(after --warmup batches, so one-off allocations are not timed), and renders the orthophoto
once with the default OrthoRenderConfig. Torch is limited to --threads (2) threads.
Memory is ru_maxrss (peak resident set of the process, MiB) after each stage.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch

from meridian_torch.config.sim import CameraConfig, GroundRenderConfig, OrthoRenderConfig, WorldConfig
from meridian_torch.geometry.se3 import pose_from_xyz_yaw
from meridian_torch.runtime import peak_rss_mib
from meridian_torch.sim.camera import camera_model_from_config
from meridian_torch.sim.ground_render import GroundRenderer
from meridian_torch.sim.ortho_render import render_orthophoto
from meridian_torch.sim.procedural import generate_world


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--frames", type=int, default=48, help="timed frames")
    parser.add_argument("--batch", type=int, default=8, help="frames per render call")
    parser.add_argument("--warmup", type=int, default=1, help="untimed batches first")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--size-m", type=float, default=None, help="world edge length (default: WorldConfig's)")
    parser.add_argument("--skip-ortho", action="store_true")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    world_cfg = WorldConfig() if args.size_m is None else WorldConfig(size_m=(args.size_m, args.size_m))
    t0 = time.perf_counter()
    world = generate_world(world_cfg, args.seed)
    print(f"world {world.shape[1]}x{world.shape[0]} cells at {world.resolution_m} m: "
          f"{time.perf_counter() - t0:.1f} s, peak {peak_rss_mib():.0f} MiB")

    cam_cfg = CameraConfig(width=args.width, height=args.height)
    camera = camera_model_from_config(cam_cfg)
    render_cfg = GroundRenderConfig(batch_size=args.batch)
    renderer = GroundRenderer(world, camera, render_cfg, device=args.device)

    # Poses on a circle around the world's centre, heading along it: varied views of buildings and trees.
    x_min, x_max, y_min, y_max = world.extent_m
    centre = np.array([(x_min + x_max) / 2, (y_min + y_max) / 2])
    radius = 0.3 * min(x_max - x_min, y_max - y_min)
    n_total = args.frames + args.warmup * args.batch
    angle = np.linspace(0.0, 2 * np.pi, n_total, endpoint=False)
    xyz = np.stack([centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle), np.zeros_like(angle)], -1)
    T_world_camera = pose_from_xyz_yaw(xyz, angle + np.pi / 2) @ camera.T_base_camera

    batches = [T_world_camera[s : s + args.batch] for s in range(0, n_total, args.batch)]
    for T in batches[: args.warmup]:
        renderer.render(T, seed=args.seed)
    t0 = time.perf_counter()
    n = 0
    for k, T in enumerate(batches[args.warmup :]):
        rgb, depth = renderer.render(T, seed=args.seed + k)
        n += len(rgb)
    dt = time.perf_counter() - t0
    valid = float((depth > 0).mean())
    print(f"ground frames {args.width}x{args.height}, batch {args.batch}, {args.threads} threads: "
          f"{n / dt:.1f} frames/s ({1000 * dt / n:.1f} ms/frame), valid depth {100 * valid:.0f} %, "
          f"peak {peak_rss_mib():.0f} MiB")

    if not args.skip_ortho:
        t0 = time.perf_counter()
        ortho = render_orthophoto(world, OrthoRenderConfig(), args.seed)
        dt = time.perf_counter() - t0
        area_km2 = (x_max - x_min) * (y_max - y_min) / 1e6
        h, w = ortho.image.shape[:2]
        print(f"orthophoto {w}x{h} px over {area_km2:.3f} km^2: {dt:.2f} s = {dt / area_km2:.1f} s/km^2, "
              f"peak {peak_rss_mib():.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())

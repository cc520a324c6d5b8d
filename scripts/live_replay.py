#!/usr/bin/env python
"""Replay a sequence folder through the live API, one frame at a time, as a robot would feed it.

What a ROS node would do in its image callback: hand each frame (RGB, depth, the odometry pose at
the frame's time, the timestamp) to `meridian_torch.pipeline.LiveLocalizer.add_frame` and publish
the estimate it returns. This script prints one line per localized submap (the state, the pose in
the orthophoto's CRS with its 1-sigma uncertainty, the time the frame took) and, at the end, the
per-frame latency and how far the online estimate was from the ground truth, when the folder has one.

Example:
    python scripts/live_replay.py runs/demo/sequence --map runs/demo/aerial.mtm -c configs/demo.yaml
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequence", type=Path, help="sequence folder (README, Formats)")
    p.add_argument("--map", type=Path, required=True, help="aerial map of the area (meridian-torch build-map)")
    p.add_argument("-c", "--config", type=Path, default=None, help="config YAML (default: the shipped default)")
    p.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    p.add_argument("--frames", type=int, default=None, help="only the first N frames")
    args = p.parse_args()

    from meridian_torch.config import CONFIG_DIR, load_config
    from meridian_torch.geometry.planar import scalar_yaw_of
    from meridian_torch.io.map_file import load_aerial_map
    from meridian_torch.io.sequence import SequenceReader
    from meridian_torch.pipeline import LiveLocalizer
    from meridian_torch.runtime import resolve_runtime

    cfg = load_config(args.config or CONFIG_DIR / "default.yaml", args.overrides)
    reader = SequenceReader(args.sequence)
    live = LiveLocalizer(load_aerial_map(args.map), cfg, reader.camera, resolve_runtime(cfg.runtime))
    n = len(reader) if args.frames is None else min(args.frames, len(reader))
    gt = reader.groundtruth
    latency, errors = [], []
    for i in range(n):
        frame = reader[i]
        started = time.perf_counter()
        estimate = live.add_frame(frame.rgb, frame.depth, frame.T_odom_base, frame.timestamp)
        latency.append(time.perf_counter() - started)
        if estimate.localized and gt is not None and gt.covers(np.array([frame.timestamp])):
            truth = gt.interpolate(np.array([frame.timestamp]))[0]
            errors.append(float(np.linalg.norm(estimate.T_world_base[:2, 3] - truth[:2, 3])))
        for event in estimate.events:
            where = "not localized yet"
            if estimate.localized:
                x, y = estimate.T_world_base[:2, 3]
                yaw = math.degrees(scalar_yaw_of(estimate.T_world_base))
                sigma = "" if estimate.covariance is None else (
                    f" +- {math.sqrt(estimate.covariance[0, 0]):.1f}/{math.sqrt(estimate.covariance[1, 1]):.1f} m, "
                    f"{math.degrees(math.sqrt(estimate.covariance[2, 2])):.1f} deg")
                where = f"x {x:.1f} y {y:.1f} yaw {yaw:.1f} deg{sigma}"
            print(f"frame {i:5d} t {frame.timestamp:.2f}: submap {event.submap_index} state {estimate.state}"
                  f"{' (fix)' if event.fix_committed else ''}: {where}  [{latency[-1]:.2f} s]")
    result = live.finish()
    lat = np.array(latency)
    print(f"{n} frames: latency median {np.median(lat) * 1000:.0f} ms, 95th percentile "
          f"{np.percentile(lat, 95) * 1000:.0f} ms, max {lat.max():.2f} s; final pass: localized "
          f"{'yes' if result.localized else 'no'}")
    if errors:
        print(f"online position error over {len(errors)} localized frames: median {np.median(errors):.2f} m, "
              f"max {max(errors):.2f} m")


if __name__ == "__main__":
    main()

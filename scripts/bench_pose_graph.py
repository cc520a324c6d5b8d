#!/usr/bin/env python
"""The online pose graph over a long drive: a batch re-solve per update against iSAM2.

A synthetic drive of `--frames` frames (1 m steps along a winding road, odometry with a yaw
drift), a loop closure every `--every` frames (measured with 1 m / 3 deg noise), and one online
update per loop closure, as the localizer makes them after the fix: the graph grows to the new
frame and takes the loop closures accepted so far; at every `--withdraw`-th update one of the
five latest is withdrawn for good (CLIPPER changed its mind about it). Each update is solved both ways, side by side:
- batch: `optimize_pose_graph` over every frame (Levenberg-Marquardt from the aligned odometry),
  what the localizer did before iSAM2;
- incremental: `IncrementalPoseGraph.update` (iSAM2: the new frames and the changed loop
  closures only).
Both with the last pose's marginal covariance (the online estimate's). Prints milliseconds per
update over the first, middle and last tenth of the drive, the totals, and the largest
difference between the two last poses over all updates.

    python scripts/bench_pose_graph.py --frames 7000 --every 40
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

from meridian_torch.backend.pose_graph import IncrementalPoseGraph, optimize_pose_graph
from meridian_torch.config import BackendConfig
from meridian_torch.geometry.planar import se2_from_xy_yaw


def drive(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(truth, odometry) (n, 3, 3): 1 m steps along a winding road; odometry drifts in yaw."""
    turn = 0.03 * np.sin(np.arange(n) / 60.0) + rng.normal(0.0, 0.002, n)
    step = se2_from_xy_yaw(np.ones(n - 1), np.zeros(n - 1), turn[1:])
    drift = se2_from_xy_yaw(np.zeros(n - 1), np.zeros(n - 1), rng.normal(0.0, math.radians(0.05), n - 1))
    truth, odom = np.empty((n, 3, 3)), np.empty((n, 3, 3))
    truth[0] = se2_from_xy_yaw(500.0, 200.0, np.array(0.3))
    odom[0] = np.eye(3)
    for k in range(n - 1):
        truth[k + 1] = truth[k] @ step[k]
        odom[k + 1] = odom[k] @ step[k] @ drift[k]
    return truth, odom


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--frames", type=int, default=7000, help="frames (pose-graph nodes) of the drive")
    parser.add_argument("--every", type=int, default=40, help="frames between loop closures (one update each)")
    parser.add_argument("--withdraw", type=int, default=7, help="every N-th update withdraws a recent loop closure")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.frames < 4 * args.every or args.every < 1 or args.withdraw < 2:
        parser.error("need --frames >= 4 * --every, --every >= 1 and --withdraw >= 2")

    rng = np.random.default_rng(args.seed)
    truth, odom = drive(args.frames, rng)
    nodes = np.arange(args.every // 2, args.frames, args.every)
    noise = se2_from_xy_yaw(rng.normal(0, 1.0, len(nodes)), rng.normal(0, 1.0, len(nodes)),
                            rng.normal(0, math.radians(3.0), len(nodes)))
    measured = truth[nodes] @ noise
    cfg = BackendConfig()
    graph = IncrementalPoseGraph(cfg)
    batch_s, incremental_s, worst_m = [], [], 0.0
    accepted = [0]
    for j in range(1, len(nodes)):
        n = min(int(nodes[j]) + args.every // 2, args.frames)
        accepted.append(j)
        if j % args.withdraw == 0:
            accepted.pop(len(accepted) - 1 - int(rng.integers(0, min(5, len(accepted) - 1))))
        given = np.array(accepted)
        start = time.perf_counter()
        batch = optimize_pose_graph(odom[:n], nodes[given], measured[given], cfg, covariance="last")
        batch_s.append(time.perf_counter() - start)
        start = time.perf_counter()
        T_last, _ = graph.update(odom[:n], nodes[given], measured[given], covariance=True)
        incremental_s.append(time.perf_counter() - start)
        worst_m = max(worst_m, float(np.linalg.norm(T_last[:2, 2] - batch.T_world_base[-1, :2, 2])))

    def tenth(values: list[float], part: str) -> float:
        k = max(1, len(values) // 10)
        chunk = {"first": values[:k], "middle": values[len(values) // 2 - k // 2:][:k], "last": values[-k:]}[part]
        return 1e3 * float(np.mean(chunk))

    print(f"{args.frames} frames, {len(batch_s)} updates, load average {os.getloadavg()[0]:.2f}")
    print("| ms per update | first tenth | middle tenth | last tenth | total s |")
    print("|---|---|---|---|---|")
    for name, values in (("batch (LM, every frame)", batch_s), ("incremental (iSAM2)", incremental_s)):
        print(f"| {name} | {tenth(values, 'first'):.1f} | {tenth(values, 'middle'):.1f} | "
              f"{tenth(values, 'last'):.1f} | {sum(values):.1f} |")
    print(f"largest difference of the last pose, batch vs incremental: {100 * worst_m:.2f} cm")
    return 0


if __name__ == "__main__":
    sys.exit(main())

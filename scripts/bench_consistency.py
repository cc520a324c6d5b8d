"""Benchmark the loop-closure consistency graph: radius-query pairs vs scoring every pair.

Before a global fix every submap adds its hypotheses from all matched patches to the pool
(KITTI 09 matched exhaustively: about 15 000 per submap), and each new submap's candidates are
scored against the whole pool (`sparse_affinity(..., first_new=...)`). This builds such a pool:
`--submaps` submaps along a winding path, each with one candidate near its true world pose and
`--per-submap - 1` wrong ones spread uniformly over a `--area-m` square map with random yaw. It
times, side by side in one run, the shipped `sparse_affinity` (radius queries find the pairs
that can be consistent) and the earlier implementation (every pair scored, in row blocks of
512), checks that both give the same edges (values equal up to rounding), and prints the time
per submap, the total and the ratio, and the process's peak memory after each.

    python scripts/bench_consistency.py --submaps 5 --per-submap 15000   # before a fix, every patch matched
    python scripts/bench_consistency.py --submaps 82 --per-submap 50     # a final pass: many small submaps
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from meridian_torch.backend.candidates import LoopClosureCandidates
from meridian_torch.backend.consistency import Edges, _affinity, _features, sparse_affinity
from meridian_torch.config import BackendConfig
from meridian_torch.geometry.planar import scalar_yaw_of
from meridian_torch.geometry.se2 import se2_matrix
from meridian_torch.runtime import peak_rss_mib


def synthetic_pool(n_submaps: int, per_submap: int, area_m: float, seed: int) -> LoopClosureCandidates:
    """Candidates in submap order: one true (0.5 m noise) and per_submap - 1 uniform wrong ones each."""
    rng = np.random.default_rng(seed)
    T_world_odom = se2_matrix(torch.tensor(0.7, dtype=torch.float64), torch.tensor([area_m / 2, area_m / 2], dtype=torch.float64))
    parts, x, y, yaw, length = [], 0.0, 0.0, 0.0, 0.0
    for s in range(n_submaps):
        step = float(rng.uniform(30.0, 70.0))
        yaw += float(rng.normal(0.0, 0.4))
        x, y, length = x + step * math.cos(yaw), y + step * math.sin(yaw), length + step
        T_odom_base = se2_matrix(torch.tensor(yaw, dtype=torch.float64), torch.tensor([x, y], dtype=torch.float64))
        true = T_world_odom @ T_odom_base
        world_yaw = torch.from_numpy(rng.uniform(-math.pi, math.pi, per_submap))
        world_xy = torch.from_numpy(rng.uniform(0.0, area_m, (per_submap, 2)))
        world_yaw[0] = scalar_yaw_of(true)
        world_xy[0] = true[:2, 2] + torch.from_numpy(rng.normal(0.0, 0.5, 2))
        n = per_submap
        parts.append(LoopClosureCandidates(
            submap_index=torch.full((n,), s, dtype=torch.int64),
            patch_index=torch.zeros(n, dtype=torch.int64),
            time=torch.full((n,), float(s), dtype=torch.float64),
            path_length_m=torch.full((n,), length, dtype=torch.float64),
            T_odom_base=T_odom_base.expand(n, 3, 3).clone(),
            T_world_base=se2_matrix(world_yaw, world_xy),
            probability=torch.full((n,), 1.0 / n, dtype=torch.float64),
            quality=torch.from_numpy(rng.uniform(0.05, 1.0, n)),
            n_associations=torch.full((n,), 4, dtype=torch.int64),
        ))
    return LoopClosureCandidates.concat(parts)


def all_pairs_affinity(c: LoopClosureCandidates, cfg: BackendConfig, first_new: int, block_rows: int = 512) -> Edges:
    """The earlier implementation: every pair (i < j, j >= first_new) scored, in row blocks."""
    n = len(c)
    features = _features(c)
    found: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
    for a in range(0, n, block_rows):
        b = min(a + block_rows, n)
        col0 = max(a, first_new)
        if col0 >= n:
            continue
        M = _affinity(features[:, a:b, None], features[:, None, col0:n], cfg)
        M = M.triu(a - col0 + 1)
        i, j = torch.nonzero(M, as_tuple=True)
        found.append((i + a, j + col0, M[i, j]))
    if not found:
        return torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.float64)
    return tuple(torch.cat(parts) for parts in zip(*found))  # type: ignore[return-value]


def _grow(c: LoopClosureCandidates, per_submap: int, score, cfg: BackendConfig) -> tuple[list[float], list[Edges]]:
    """Score the pool as the localizer does: after each submap, its candidates against the pool."""
    seconds, edges = [], []
    for end in range(per_submap, len(c) + 1, per_submap):
        start = time.perf_counter()
        edges.append(score(c.select(torch.arange(end)), cfg, first_new=end - per_submap))
        seconds.append(time.perf_counter() - start)
    return seconds, edges


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--submaps", type=int, default=5, help="submaps in the pool (default 5)")
    parser.add_argument("--per-submap", type=int, default=15000, help="candidates per submap (default 15000)")
    parser.add_argument("--area-m", type=float, default=1500.0, help="side of the square map, metres")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = BackendConfig()
    pool = synthetic_pool(args.submaps, args.per_submap, args.area_m, args.seed)
    print(f"pool: {args.submaps} submaps x {args.per_submap} candidates over {args.area_m:.0f} m x "
          f"{args.area_m:.0f} m, {args.threads} threads; peak memory {peak_rss_mib():.0f} MiB before")
    fast_s, fast_edges = _grow(pool, args.per_submap, sparse_affinity, cfg)
    fast_peak = peak_rss_mib()
    slow_s, slow_edges = _grow(pool, args.per_submap, all_pairs_affinity, cfg)
    slow_peak = peak_rss_mib()
    same, value_gap = True, 0.0
    for (fi, fj, fv), (si, sj, sv) in zip(fast_edges, slow_edges):
        fo, so = torch.argsort(fi * len(pool) + fj), torch.argsort(si * len(pool) + sj)
        same &= torch.equal(fi[fo], si[so]) and torch.equal(fj[fo], sj[so])
        if same and len(fv):
            value_gap = max(value_gap, float((fv[fo] - sv[so]).abs().max()))
    print("| submap | new pairs scored, all pairs | edges | radius query s | all pairs s |")
    print("|---|---|---|---|---|")
    for k, (f, s, e) in enumerate(zip(fast_s, slow_s, fast_edges)):
        n_new = args.per_submap
        scored = n_new * (n_new * k) + n_new * (n_new - 1) // 2
        print(f"| {k} | {scored:.2e} | {len(e[0])} | {f:.2f} | {s:.2f} |")
    print(f"total: radius query {sum(fast_s):.2f} s (peak {fast_peak:.0f} MiB), all pairs {sum(slow_s):.2f} s "
          f"(peak {slow_peak:.0f} MiB), {sum(slow_s) / max(sum(fast_s), 1e-9):.1f}x; same edges: {same}, "
          f"largest value difference {value_gap:.1e}")


if __name__ == "__main__":
    main()

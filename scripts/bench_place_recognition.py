"""Recall and cost of the coarse global search (issue 16) against maps of growing size.

For every ground submap of a sequence: the rank of the true patch (the patch containing the true
position whose centre is nearest) among all patches, for single submaps and for the odometry chain,
the yaw error of the best cell of the true patch, and the time per submap. Larger maps are made of
the real map plus decoy copies of it, mirrored (a mirror image cannot be matched by a rotation),
tiled beside it on a square grid (`--decoys 3` = x-, y- and xy-mirrored copies, four times the
patches; more decoys repeat the three mirrors at other places).

    python scripts/bench_place_recognition.py runs/kitti02 \\
        -c configs/kitti02.yaml --submaps runs/kitti02/submaps.pt --threads 1

Submaps are built with the config's ground mapping on the first run and cached (`--submaps`).

When the submaps carry frame global descriptors (as `map-ground` and this script build them),
two more rankings are scored: "global", the map's global descriptors alone (the paper's place
recognition, `mode: global`), and "fused", the chain's ranking fused with it by reciprocal rank
fusion (`mode: coarse` with `global_fusion`, which 'auto' turns on for neural descriptors only).
Decoy patches carry the global descriptor of the patch they copy (for the descriptors, a decoy is
then as likely as its original: the worst case).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from exp_registration import containing_patch, true_T_world_odom  # noqa: E402

from meridian_torch.config import load_config  # noqa: E402
from meridian_torch.geometry.planar import scalar_yaw_of, wrap_angle  # noqa: E402
from meridian_torch.geometry.se3 import interpolate_poses  # noqa: E402
from meridian_torch.io.map_file import load_aerial_map  # noqa: E402
from meridian_torch.io.sequence import SequenceReader  # noqa: E402
from meridian_torch.matching.place_recognition import (  # noqa: E402
    build_coarse_map,
    chain_scores,
    patch_priors,
    rank_fusion,
    stack_similarity,
    submap_scores,
)
from meridian_torch.types import PrimitiveBatch  # noqa: E402


def load_submaps(seq: Path, cfg, cache: Path | None, max_frames: int | None):
    if cache is not None and cache.exists():
        return torch.load(cache, weights_only=False)
    from meridian_torch.mapping.ground_map import map_ground
    from meridian_torch.runtime import resolve_runtime

    reader = SequenceReader(seq)

    submaps = map_ground(reader, cfg, resolve_runtime(cfg.runtime), n_frames=max_frames)
    if cache is not None:
        torch.save(submaps, cache)
    return submaps


def _pad(x: torch.Tensor, n: int) -> torch.Tensor:
    pad = [0, 0] * (x.dim() - 2) + [0, n - x.shape[1]]
    return torch.nn.functional.pad(x, pad)


def with_decoys(batch: PrimitiveBatch, bounds: np.ndarray, n_decoys: int) -> tuple[PrimitiveBatch, np.ndarray]:
    """The map plus `n_decoys` mirrored copies placed beside it (x-, y-, xy-mirrored, then repeats)."""
    x0, x1, y0, y1 = bounds[:, 0].min(), bounds[:, 1].max(), bounds[:, 2].min(), bounds[:, 3].max()
    span = np.array([x1 - x0, y1 - y0]) + 200.0
    parts, part_bounds = [batch], [bounds]
    flips = [(-1, 1), (1, -1), (-1, -1)]
    for d in range(n_decoys):
        fx, fy = flips[d % 3]
        side = math.ceil(math.sqrt(n_decoys + 1))  # tiles on a square grid, the real map at (0, 0)
        offset = np.array([(d + 1) % side, (d + 1) // side]) * span
        scale = torch.tensor([fx, fy], dtype=batch.points_xy.dtype)
        centre = torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2], dtype=batch.points_xy.dtype)
        shift = torch.as_tensor(offset, dtype=batch.points_xy.dtype)

        def move(p, centre=centre, scale=scale, shift=shift):
            return (p - centre) * scale + centre + shift

        parts.append(PrimitiveBatch(**{
            **{f.name: getattr(batch, f.name) for f in fields(batch)},
            "points_xy": move(batch.points_xy), "line_endpoints": move(batch.line_endpoints),
        }))
        b = bounds.copy()
        bx = (np.stack([b[:, 0], b[:, 1]], 1) - (x0 + x1) / 2) * fx + (x0 + x1) / 2 + offset[0]
        by = (np.stack([b[:, 2], b[:, 3]], 1) - (y0 + y1) / 2) * fy + (y0 + y1) / 2 + offset[1]
        part_bounds.append(np.stack([bx.min(1), bx.max(1), by.min(1), by.max(1)], 1))
    n_points = max(p.points_xy.shape[1] for p in parts)
    n_lines = max(p.line_endpoints.shape[1] for p in parts)
    merged = {}
    for f in fields(batch):
        n = n_points if f.name.startswith("point") else n_lines
        merged[f.name] = torch.cat([_pad(getattr(p, f.name), n) for p in parts])
    return PrimitiveBatch(**merged), np.concatenate(part_bounds)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("-c", "--config", type=Path, required=True)
    ap.add_argument("--map", type=Path, help="aerial map (default SEQUENCE/aerial.mtm)")
    ap.add_argument("--submaps", type=Path, help="cache file of the ground submaps")
    ap.add_argument("--max-frames", type=int)
    ap.add_argument("--limit", type=int, help="only the first LIMIT submaps (cost on very large maps)")
    ap.add_argument("--decoys", type=int, nargs="+", default=[0], help="mirrored decoy copies, one run each")
    ap.add_argument("--set", action="append", default=[], help="config override, e.g. "
                    "matching.place_recognition.coarse.classes=4")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, help="append one JSON line per run")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config, args.set)
    pr_cfg = cfg.matching.place_recognition
    ccfg = pr_cfg.coarse
    amap = load_aerial_map(args.map or args.sequence / "aerial.mtm")
    reader = SequenceReader(args.sequence)
    submaps = load_submaps(args.sequence, cfg, args.submaps, args.max_frames)[: args.limit]
    gt = reader.groundtruth
    origin = np.asarray(getattr(amap, "local_origin_xy", (0.0, 0.0)), dtype=np.float64)
    truth = []
    for sm in submaps:
        T_wb = interpolate_poses(gt.timestamps, gt.poses, np.array([sm.time]))[0]
        T_wb[:2, 3] -= origin
        T_true = true_T_world_odom(T_wb, sm.T_odom_base)
        patch = containing_patch(amap.patches.centres_xy, amap.patches.bounds_xy, T_wb[:2, 3])
        truth.append((patch, scalar_yaw_of(T_true)))
    for n_decoys in args.decoys:
        batch, bounds = with_decoys(amap.primitives, np.asarray(amap.patches.bounds_xy), n_decoys)
        t0 = time.perf_counter()
        cmap = build_coarse_map(batch, torch.as_tensor(bounds), ccfg)
        build_s = time.perf_counter() - t0
        ranks = {"single": [], "chain": []}
        patch_descriptors = amap.global_descriptors.repeat(n_decoys + 1, 1)
        yaw_err, seconds = [], []
        chain, previous_centre = None, None
        single_buffer = torch.empty(ccfg.yaws, *cmap.shape)  # reused as the localizer's CoarseSearch does
        chain_buffer = torch.empty_like(single_buffer)
        for sm, (true_patch, true_yaw) in zip(submaps, truth):
            t1 = time.perf_counter()
            centre = torch.as_tensor(sm.T_odom_base[:2, 3])
            single = submap_scores(cmap, sm.primitives, centre, ccfg, out=single_buffer)
            step = centre - previous_centre if previous_centre is not None else centre * 0
            chain = chain_scores(chain, single, step, cmap, ccfg, out=chain_buffer)
            priors = {"single": patch_priors(cmap, single, ccfg), "chain": patch_priors(cmap, chain, ccfg)}
            seconds.append(time.perf_counter() - t1)
            previous_centre = centre
            if true_patch is None:
                continue
            scores = {name: pr.score for name, pr in priors.items()}
            if len(sm.frame_descriptors):
                frames = sm.frame_descriptors.to(patch_descriptors)
                similarity = stack_similarity(frames[None], torch.ones(1, len(frames), dtype=torch.bool),
                                              patch_descriptors)
                scores["global"] = similarity[0]
                scores["fused"] = rank_fusion([scores["chain"][None], similarity], pr_cfg.fusion_rank_constant)[0]
            for name, score in scores.items():
                better = (score > score[true_patch]).sum()
                ranks.setdefault(name, []).append(int(better) + 1)
            err = float(priors["chain"].yaw[true_patch]) - true_yaw
            yaw_err.append(abs(math.degrees(wrap_angle(err))))
        row = {
            "patches": cmap.n_patches, "raster": list(cmap.shape), "build_s": round(build_s, 2),
            "s_per_submap": round(float(np.median(seconds)), 3), "submaps": len(ranks["chain"]),
            **{f"{name}_recall@{k}": round(float(np.mean(np.array(r) <= k)), 3)
               for name, r in ranks.items() for k in (1, 5, 25)},
            **{f"{name}_ranks": r for name, r in ranks.items()},
            "chain_yaw_err_deg_median": round(float(np.median(yaw_err)), 1),
            "overrides": args.set, "threads": args.threads,
        }
        print(json.dumps(row), flush=True)
        if args.json:
            with args.json.open("a") as fh:
                fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()

"""Submap registration experiment (paper section IV, Table "Registration Success Rate").

Every ground submap of a sequence is matched against the one 60 m x 60 m aerial patch that
contains it (the paper's protocol: "evaluate registration success on each ground submap in a
60 m x 60 m aerial patch"), in four variants: {known, unknown} rotation x {points and lines,
points only}. A hypothesis is a success if it is within 5 m and 5 deg (also reported: 10 deg) of
the truth; top-L success means one of the L heaviest hypotheses is (L = 1, 5, 10, 25).

Truth: T_world_odom at the submap time = T_world_base_gt(t) * inverse(T_odom_base(t)), taken in
SE(2) (x, y, yaw) from the sequence's groundtruth.tum. Known rotation = the true yaw of
T_world_odom is given to the matcher as its rotation prior. The true patch is the patch whose
centre is nearest to the true base position among those containing it.

Harder cases: `--perturb missing=0.4,spurious=0.2,noise_m=1.0` degrades every submap's
primitives first (seeded, `meridian_torch.evaluation.perturbation`). Across patches
(`--decoys N`, e.g. 24; default 0, the paper's one patch): the submap is matched in one call
against its true patch and N seeded random patches that do not overlap it (as place recognition
would propose them); per patch = the true patch's own ranking, across = all hypotheses of all
patches ranked by their probability (ties ranked against the truth), as the localizer compares
them.

Seeds: `--seeds N` matches every submap with the seeds --seed .. --seed + N - 1 (the particles,
and with --perturb / --decoys the perturbation and the decoys) and counts every (submap, seed)
case in one table. One seed's table moves by several points between seeds (README, "Stop 55"), so
compare settings at 10 or more, side by side on the same cached submaps (`--cache`).

Inputs: a sequence folder with groundtruth.tum (e.g. written by `meridian-torch simulate`) and
its aerial map (.mtm, from `meridian-torch build-map`), or `--simulate CONFIG` to write both
first into `--work` (short drives via `--drive-m`).

    python scripts/exp_registration.py --sequence runs/kitti09 --map runs/kitti09/aerial.mtm \
        -c configs/kitti09.yaml --max-submaps 20 --perturb missing=0.4,spurious=0.2,noise_m=1.0
    python scripts/exp_registration.py --simulate configs/kitti00.yaml --work runs/exp00 --max-frames 300
    python scripts/exp_registration.py --simulate configs/demo.yaml --work runs/exp_demo --drive-m 600
    python scripts/exp_registration.py --sequence runs/kitti09-7hz --map runs/kitti09-7hz/MAP.mtm \
        -c configs/kitti09.yaml --max-frames 600 --cache runs/k09.pt --seeds 10 --threads 1
"""

from __future__ import annotations

import argparse
import itertools
import math
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meridian_torch.evaluation.perturbation import Perturbation, parse_perturbation, perturb_primitives
from meridian_torch.geometry.planar import scalar_yaw_of, se2_from_se3, wrap_angle, yaw_of

THRESHOLDS = ((5.0, 5.0), (5.0, 10.0))  # (metres, degrees)
TOP_L = (1, 5, 10, 25)
ACROSS_TOP_L = (1, 5)
VARIANTS = (("Meridian", True), ("Meridian w/o Lines", False))

# Paper Table (KITTI Seq. 00; the paper has no other KITTI sequence), percent < 5 m, < 5 deg:
# known rotation top-1/5/10/25, then unknown rotation top-1/5/10/25.
PAPER_KITTI00 = {
    "Meridian": (38.3, 71.3, 82.4, 92.7, 23.0, 44.1, 53.6, 62.8),
    "Meridian w/o Lines": (41.8, 70.1, 76.6, 80.1, 22.2, 36.0, 43.7, 56.3),
}


# --------------------------------------------------------------------------------------------
# Evaluation logic (pure functions, tested in tests/test_exp_registration.py)
# --------------------------------------------------------------------------------------------


def true_T_world_odom(T_world_base_gt: np.ndarray, T_odom_base: np.ndarray) -> np.ndarray:
    """(3, 3) SE(2) truth of the matcher's output: T_world_base_gt * inverse(T_odom_base)."""
    world_base, odom_base = se2_from_se3(T_world_base_gt), se2_from_se3(T_odom_base)
    return world_base @ np.linalg.inv(odom_base)


def pose_errors(T_hyp: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and absolute yaw (deg) errors of hypotheses (..., 3, 3) against a truth (3, 3)."""
    dt = np.linalg.norm(T_hyp[..., :2, 2] - T_true[:2, 2], axis=-1)
    dyaw = np.abs(wrap_angle(yaw_of(T_hyp) - scalar_yaw_of(T_true)))
    return dt, np.degrees(dyaw)


def top_l_success(T_hyp: np.ndarray, valid: np.ndarray, T_true: np.ndarray, max_t_m: float, max_yaw_deg: float,
                  top_l: tuple[int, ...] = TOP_L) -> dict[int, bool]:
    """For hypotheses (L, 3, 3) ordered heaviest first with a valid mask (L,): is one of the
    first l valid ones within the thresholds, for every l in top_l."""
    dt, dyaw = pose_errors(T_hyp, T_true)
    hit = valid & (dt < max_t_m) & (dyaw < max_yaw_deg)
    rank = np.cumsum(valid) - 1  # position among the valid hypotheses
    return {top: bool((hit & (rank < top)).any()) for top in top_l}


def across_patch_success(T_hyp: np.ndarray, probability: np.ndarray, valid: np.ndarray, T_true: np.ndarray,
                         max_t_m: float, max_yaw_deg: float, top_l: tuple[int, ...] = ACROSS_TOP_L) -> dict[int, bool]:
    """For hypotheses (P, L, 3, 3) of P patches with probabilities and a valid mask (P, L): is one
    of the l most probable valid ones of all patches within the thresholds, for every l in
    top_l. Equal probabilities rank wrong hypotheses first (a tie is not a success)."""
    dt, dyaw = pose_errors(T_hyp.reshape(-1, 3, 3), T_true)
    ok = valid.reshape(-1)
    hit = (dt < max_t_m) & (dyaw < max_yaw_deg)
    order = np.lexsort((hit, -probability.reshape(-1)))  # last key first: probability, then misses
    ranked_hits = hit[order][ok[order]]
    return {top: bool(ranked_hits[:top].any()) for top in top_l}


def decoy_patches(bounds_xy: np.ndarray, true_index: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """n distinct patches (seeded) whose extent (x0, x1, y0, y1) does not overlap the true patch's."""
    b, t = bounds_xy, bounds_xy[true_index]
    apart = (b[:, 1] <= t[0]) | (b[:, 0] >= t[1]) | (b[:, 3] <= t[2]) | (b[:, 2] >= t[3])
    candidates = np.flatnonzero(apart)
    if len(candidates) < n:
        raise ValueError(f"decoys: {n} asked, but only {len(candidates)} patches do not overlap patch {true_index}")
    return rng.choice(candidates, n, replace=False)


def containing_patch(centres_xy: np.ndarray, bounds_xy: np.ndarray, position_xy: np.ndarray) -> int | None:
    """Index of the patch containing `position_xy` whose centre is nearest to it (None if none does)."""
    inside = (
        (bounds_xy[:, 0] <= position_xy[0]) & (position_xy[0] <= bounds_xy[:, 1])
        & (bounds_xy[:, 2] <= position_xy[1]) & (position_xy[1] <= bounds_xy[:, 3])
    )
    if not inside.any():
        return None
    dist = np.linalg.norm(centres_xy - position_xy, axis=1)
    return int(np.where(inside, dist, np.inf).argmin())


@dataclass
class Tally:
    """Success counts per (variant, rotation mode, threshold) and L."""

    n: int = 0

    def __post_init__(self) -> None:
        self.hits: dict[tuple[str, str, tuple[float, float]], dict[int, int]] = {}

    def add(self, variant: str, mode: str, threshold: tuple[float, float], success: dict[int, bool]) -> None:
        row = self.hits.setdefault((variant, mode, threshold), {top: 0 for top in TOP_L})
        for top, ok in success.items():
            row[top] += int(ok)

    def percent(self, variant: str, mode: str, threshold: tuple[float, float],
                top_l: tuple[int, ...] = TOP_L) -> list[float]:
        row = self.hits.get((variant, mode, threshold), {})
        return [100.0 * row.get(top, 0) / max(self.n, 1) for top in top_l]


def format_table(title: str, tally: Tally, threshold: tuple[float, float], paper: dict[str, tuple] | None) -> str:
    """Rows per variant: known rotation top-1/5/10/25 | unknown rotation top-1/5/10/25 (percent)."""
    head = f"{title}: {tally.n} cases (submaps x seeds), success < {threshold[0]:g} m and < {threshold[1]:g} deg (percent)"
    cols = " ".join(f"{'K top-' + str(top):>9}" for top in TOP_L) + " " + " ".join(f"{'U top-' + str(top):>9}" for top in TOP_L)
    lines = [head, f"{'method':<28} {cols}"]
    for name, _ in VARIANTS:
        values = tally.percent(name, "known", threshold) + tally.percent(name, "unknown", threshold)
        lines.append(f"{name:<28} " + " ".join(f"{v:>9.1f}" for v in values))
        if paper is not None and name in paper:
            lines.append(f"{'  paper (KITTI 00)':<28} " + " ".join(f"{v:>9.1f}" for v in paper[name]))
    return "\n".join(lines)


def format_across_table(title: str, tally: Tally, threshold: tuple[float, float], n_decoys: int) -> str:
    """Rows per variant: per rotation mode, per-patch top-1 | across-patch top-1/5 (percent)."""
    head = (f"{title}: {tally.n} cases (submaps x seeds), true patch + {n_decoys} decoys, success < {threshold[0]:g} m and "
            f"< {threshold[1]:g} deg (percent)")
    cols = " ".join(f"{m + ' ' + c:>12}" for m in ("K", "U") for c in ("patch top-1", "all top-1", "all top-5"))
    lines = [head, f"{'method':<28} {cols}"]
    for name, _ in VARIANTS:
        values = [v for mode in ("known", "unknown") for v in
                  tally.percent(name, mode, threshold, (1,)) + tally.percent(name, mode + " across", threshold, ACROSS_TOP_L)]
        lines.append(f"{name:<28} " + " ".join(f"{v:>12.1f}" for v in values))
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------


def _without_lines(primitives):
    from meridian_torch.types import PrimitiveSet

    p = primitives
    return PrimitiveSet(p.points_xy, p.point_descriptors, p.point_segment_ids, p.line_endpoints[:0], p.line_kinds[:0],
                        p.line_descriptors[:0], p.line_segment_ids[:0])


def _patches(aerial_map, indices, lines: bool):
    """Aerial patches `indices` of the map as a batch (lines dropped unless `lines`)."""
    from meridian_torch.types import stack_primitive_sets

    sets = [aerial_map.primitives.unbatch(int(i)) for i in indices]
    return stack_primitive_sets(sets if lines else [_without_lines(s) for s in sets])


def line_agreement(ground_lines: np.ndarray, aerial_lines: np.ndarray, T: np.ndarray, tol_m: float,
                   tol_deg: float) -> np.ndarray:
    """(Ng, Na) bool: ground line (odom, (Ng, 2, 2)) mapped by T (3, 3) lies on aerial line
    (world, (Na, 2, 2)): both mapped endpoints within tol_m of the infinite aerial line and the
    directions within tol_deg (sign-less)."""
    g = ground_lines @ T[:2, :2].T + T[:2, 2]
    d_a = aerial_lines[:, 1] - aerial_lines[:, 0]
    d_a = d_a / np.maximum(np.linalg.norm(d_a, axis=-1, keepdims=True), 1e-9)
    n_a = np.stack([-d_a[:, 1], d_a[:, 0]], -1)
    off = np.abs(np.einsum("gkc,ac->gak", g, n_a) - (aerial_lines[:, 0] * n_a).sum(-1)[None, :, None])
    d_g = g[:, 1] - g[:, 0]
    d_g = d_g / np.maximum(np.linalg.norm(d_g, axis=-1, keepdims=True), 1e-9)
    cos = np.abs(d_g @ d_a.T)
    return (off.max(-1) < tol_m) & (cos > math.cos(math.radians(tol_deg)))


def diagnose(submap, batch, T_true: np.ndarray, match_cfg) -> str:
    """How many ground primitives have a geometric counterpart in the patch under the truth
    (points < 3 m; lines on a line within 3 m and 10 deg), and how many of those counterparts are
    among their K_prim putative associations (i.e. survive the descriptor k-NN)."""
    from meridian_torch.matching.associations import putative_associations

    g, ac = submap.primitives, match_cfg.associations
    a_pts = batch.points_xy[0][batch.point_valid[0]].double().numpy()
    a_lns = batch.line_endpoints[0][batch.line_valid[0]].double().numpy()
    g_pts = g.points_xy.double().numpy() @ T_true[:2, :2].T + T_true[:2, 2]
    pt_ok = np.linalg.norm(g_pts[:, None] - a_pts[None], axis=-1) < 3.0 if len(a_pts) and len(g_pts) else \
        np.zeros((len(g_pts), len(a_pts)), bool)
    ln_ok = line_agreement(g.line_endpoints.double().numpy(), a_lns, T_true, 3.0, 10.0) if len(a_lns) and \
        len(g.line_endpoints) else np.zeros((len(g.line_endpoints), len(a_lns)), bool)
    assoc = putative_associations(g, batch, k_prim=ac.k_prim, direction=ac.direction, min_line_length_m=ac.min_line_length_m)
    pairs = assoc.pairs[0][assoc.valid[0]].numpy()
    n_gp, n_ap = assoc.n_ground_points, assoc.n_aerial_points
    hits = 0
    for gi, ai in pairs:
        if gi < n_gp and ai < n_ap:
            hits += bool(pt_ok[gi, ai])
        elif gi >= n_gp and ai >= n_ap:
            hits += bool(ln_ok[gi - n_gp, ai - n_ap])
    return (f"points with a counterpart {int(pt_ok.any(1).sum())}/{len(g_pts)}, lines "
            f"{int(ln_ok.any(1).sum())}/{len(ln_ok)}; correct putative associations {hits}/{len(pairs)}")


def run(sequence: Path, map_path: Path, config: Path | None, overrides: list[str], max_submaps: int | None,
        max_frames: int | None, seeds: list[int], threads: int, cache: Path | None = None,
        verbose: bool = False, perturbation: Perturbation | None = None, n_decoys: int = 0) -> tuple[Tally, dict[str, float]]:
    import torch

    from meridian_torch.config import load_config
    from meridian_torch.geometry.se3 import interpolate_poses
    from meridian_torch.io.map_file import load_aerial_map
    from meridian_torch.io.sequence import SequenceReader
    from meridian_torch.mapping.ground_map import map_ground
    from meridian_torch.matching.match import match_submap
    from meridian_torch.runtime import resolve_runtime

    torch.set_num_threads(threads)
    cfg = load_config(config, overrides)
    reader = SequenceReader(sequence)
    if reader.groundtruth is None:
        raise SystemExit(f"{sequence}: no groundtruth.tum, cannot score registration")
    aerial_map = load_aerial_map(map_path)
    runtime = resolve_runtime(cfg.runtime)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    def progress(done: int, total: int) -> None:
        print(f"  ground mapping: {done}/{total} frames", flush=True)

    if cache is not None and cache.exists():
        submaps = torch.load(cache, weights_only=False)
    else:
        submaps = map_ground(reader, cfg, runtime, progress, n_frames=max_frames)
        if cache is not None:
            torch.save(submaps, cache)
    seconds["ground mapping"] = time.perf_counter() - t0
    if max_submaps is not None:
        submaps = submaps[:max_submaps]
    gt = reader.groundtruth
    match_cfg = cfg.matching
    perturbation = perturbation or Perturbation()
    tally = Tally()
    t0 = time.perf_counter()
    for seed, submap in itertools.product(seeds, submaps):
        T_map_base = interpolate_poses(gt.timestamps, gt.poses, np.array([submap.time]))[0]
        T_map_base[:2, 3] -= aerial_map.local_origin_xy  # the map's coordinates are relative to it
        T_true = true_T_world_odom(T_map_base, submap.T_odom_base)
        index = containing_patch(aerial_map.patches.centres_xy, aerial_map.patches.bounds_xy, T_map_base[:2, 3])
        if index is None:
            continue
        tally.n += 1
        yaw_true = scalar_yaw_of(T_true)
        # One perturbation and one set of decoys per submap, shared by every variant.
        primitives = perturb_primitives(submap.primitives, perturbation, seed * 100_003 + submap.index)
        rng = np.random.default_rng([seed, submap.index])
        indices = np.concatenate([[index], decoy_patches(aerial_map.patches.bounds_xy, index, n_decoys, rng)])
        for name, lines in VARIANTS:
            ground = primitives if lines else _without_lines(primitives)
            batch = _patches(aerial_map, indices, lines)
            for mode, prior in (("known", yaw_true), ("unknown", None)):
                hyp = match_submap(ground, batch, rotation_prior=prior, config=match_cfg,
                                   generator=torch.Generator().manual_seed(seed + submap.index))
                T_hyp, valid = hyp.T_world_odom.double().numpy(), hyp.valid.numpy()
                probability = hyp.probability.double().numpy()
                for threshold in THRESHOLDS:
                    tally.add(name, mode, threshold, top_l_success(T_hyp[0], valid[0], T_true, *threshold))
                    tally.add(name, mode + " across", threshold,
                              across_patch_success(T_hyp, probability, valid, T_true, *threshold))
        print(f"  seed {seed}, submap {submap.index:3d}: patch {index}, {len(primitives.points_xy)} points, "
              f"{len(primitives.line_endpoints)} lines", flush=True)
        if verbose:
            print("    " + diagnose(submap, _patches(aerial_map, [index], True), T_true, match_cfg), flush=True)
    seconds["matching"] = time.perf_counter() - t0
    return tally, seconds


def simulate(config: Path, work: Path, drive_m: float | None, max_frames: int | None,
             overrides: list[str]) -> tuple[Path, Path]:
    """`meridian-torch simulate` + `build-map` into `work` (skipped when already there)."""
    cli = [str(Path(sys.executable).with_name("meridian-torch"))]
    sets = [a for o in overrides for a in ("--set", o)]
    if drive_m is not None:  # procedural drives
        sets += ["--set", f"sim.trajectory.length_m={drive_m}"]
    if max_frames is not None:  # trajectories read from a file (the KITTI worlds)
        sets += ["--set", f"sim.trajectory.max_frames={max_frames}"]
    sequence, map_path = work / "sequence", work / "aerial.mtm"
    if not (sequence / "groundtruth.tum").exists():
        subprocess.run([*cli, "simulate", "--out", str(sequence), "-c", str(config), *sets], check=True)
    if not map_path.exists():
        subprocess.run([*cli, "build-map", str(sequence), "--out", str(map_path), "-c", str(config), *sets], check=True)
    return sequence, map_path


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sequence", type=Path, help="sequence folder with groundtruth.tum")
    p.add_argument("--map", type=Path, help="aerial map (.mtm) of the sequence's orthophoto")
    p.add_argument("-c", "--config", type=Path, default=None, help="config (default configs/default.yaml)")
    p.add_argument("--set", action="append", default=[], help="config override key=value (repeatable)")
    p.add_argument("--simulate", type=Path, default=None, help="simulate a sequence and build its map from this config")
    p.add_argument("--work", type=Path, default=Path("runs/exp_registration"), help="output folder of --simulate")
    p.add_argument("--drive-m", type=float, default=None, help="with --simulate: drive length (m), procedural worlds")
    p.add_argument("--max-frames", type=int, default=None,
                   help="frames used (3 frames/s); with --simulate also the frames simulated")
    p.add_argument("--max-submaps", type=int, default=None, help="evaluate at most this many submaps")
    p.add_argument("--cache", type=Path, default=None, help="ground submaps: load from / save to this file")
    p.add_argument("--verbose", action="store_true", help="per submap: true counterparts among the associations")
    p.add_argument("--perturb", default="",
                   help="degrade submap primitives first: missing=F,spurious=F,noise_m=M (fractions, metres)")
    p.add_argument("--decoys", type=int, default=0,
                   help="patches matched with the true one, for the across-patch table (default 0: the true one "
                   "alone, the paper's protocol)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", type=int, default=1,
                   help="match every submap with this many consecutive seeds from --seed and count every (submap, "
                   "seed) case in one table (e.g. 10: seeds 0-9; one seed's table moves by several points)")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    if args.seeds < 1:
        p.error(f"--seeds must be at least 1, got {args.seeds}")
    config = args.config
    if args.simulate is not None:
        args.sequence, args.map = simulate(args.simulate, args.work, args.drive_m, args.max_frames, args.set)
        config = config or args.simulate
    if args.sequence is None or args.map is None:
        p.error("give --sequence and --map, or --simulate CONFIG")
    try:
        perturbation = parse_perturbation(args.perturb)
    except ValueError as error:
        p.error(str(error))
    t0 = time.perf_counter()
    seeds = list(range(args.seed, args.seed + args.seeds))
    tally, seconds = run(args.sequence, args.map, config, args.set, args.max_submaps, args.max_frames, seeds,
                         args.threads, args.cache, args.verbose, perturbation, args.decoys)
    name = args.sequence.name if args.sequence.name != "sequence" else args.sequence.parent.name
    if not perturbation.is_identity:
        name += f" ({args.perturb})"
    for threshold in THRESHOLDS:
        print()
        print(format_table(f"{name}", tally, threshold, PAPER_KITTI00 if threshold == (5.0, 5.0) else None))
        if args.decoys:
            print()
            print(format_across_table(f"{name}", tally, threshold, args.decoys))
    print("\n" + ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items()) + f"; total {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()

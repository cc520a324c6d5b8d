"""Benchmark `match_submap`: one batched call over P aerial patches vs a per-patch loop, at the
shipped matching config (configs/default.yaml; flags override single values).

Synthetic scenes (all sizes are flags; the defaults are the issue-15 case, one submap against
25 patches of about 20 ground and 65 aerial primitives):
- one ground submap of 8 points + 12 lines, random positions in a disc of radius `--radius`
  metres around the odom origin, L2-normalised D = 32 descriptors drawn around 8 class centres
  (so top-k semantic neighbours are informative but not unique);
- P = 25 aerial patches (5 with `--quick`) of 25 points + 40 lines each in the world frame.
  One of them (the "true" patch) holds 70 % of the ground primitives moved by a known SE(2)
  T_world_odom, with 0.3 m position noise and perturbed descriptors, plus random outliers up to
  the same size; the other patches are random primitives around random world centres.
`--cases N` scenes (seeds seed .. seed + N - 1) are matched; the table shows medians over them.
`--submaps` takes recorded cases instead: rendered ground submaps (exp_registration.py --cache),
each against the 25 patches of its map nearest its true position.

Measured, each in a fresh subprocess (`--mode batched|loop|clipper`, spawned by the parent), so
that the process peak resident set size (ru_maxrss) belongs to that one stage:
  (a) batched: `match_submap(ground, stack_primitive_sets(all patches), ...)` in one call;
  (b) loop:    `match_submap(ground, stack_primitive_sets([patch]), ...)` for every patch;
  (c) clipper: `bench_clipper(sizes, seed)` from scripts/bench_clipper.py (CLIPPER solver alone
      on random planted-clique graphs, n = 500, 1000, 2000 by default; `--skip-clipper`).
With `--baseline-src DIR` (e.g. a checkout of an older commit) (a) and (b) also run on the
package under DIR, each tree at its own shipped config, alternating with this tree's children.
For (a) and (b) it reports wall and process CPU time per submap (after a tiny warm-up match that
loads lazy code paths), the peak RSS, and whether the top hypothesis of the true patch is within
5 m / 5 deg of the planted transform; then the seconds inside the Langevin loop (the same compiled
kernel in both modes) apart from the rest of the match, and how much faster that loop would have
to run for loop / batched to reach 5x (issue 15's target). Both modes draw the per-patch particle seeds from one
generator seeded with `--seed`, so if torch's generator yields the same sequence one draw at a
time the two modes solve identical problems (reported as "same per-patch seeds").

    python scripts/bench_matching.py --threads 1 --skip-clipper --baseline-src /path/to/old/tree
    python scripts/bench_matching.py --quick --cases 3
    python scripts/bench_matching.py --threads 1 --skip-clipper --submaps runs/exp00/submaps.pt \
        --map runs/exp00/aerial.mtm --sequence runs/exp00/sequence
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import statistics
import sys
import time

from _tree_child import run_in_tree  # scripts/ is on sys.path when a script runs

from meridian_torch.runtime import current_rss_mib, peak_rss_mib

HERE = os.path.dirname(os.path.abspath(__file__))
RESULT_TAG = "BENCH_MATCHING_RESULT "


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------


def build_scene(args: argparse.Namespace):
    """Returns ground PrimitiveSet, list of aerial PrimitiveSets, true index, (yaw, tx, ty)."""
    import torch
    import torch.nn.functional as F

    from meridian_torch.types import PrimitiveSet

    gen = torch.Generator().manual_seed(args.seed)
    D = args.descriptor_dim
    centres = F.normalize(torch.randn(args.classes, D, generator=gen), dim=1)

    def disc(n: int, radius: float) -> torch.Tensor:
        r = radius * torch.rand(n, generator=gen).sqrt()
        a = 2 * math.pi * torch.rand(n, generator=gen)
        return torch.stack([r * a.cos(), r * a.sin()], 1)

    def lines(n: int, radius: float) -> torch.Tensor:
        e0 = disc(n, radius)
        ang = torch.rand(n, generator=gen) * math.pi
        length = 4 + 10 * torch.rand(n, generator=gen)
        return torch.stack([e0, e0 + length[:, None] * torch.stack([ang.cos(), ang.sin()], 1)], 1)

    def desc(n: int) -> torch.Tensor:
        cls = torch.randint(0, args.classes, (n,), generator=gen)
        noise = F.normalize(torch.randn(n, D, generator=gen), dim=1)
        return F.normalize(centres[cls] + 0.8 * noise, dim=1)

    def perturb(d: torch.Tensor) -> torch.Tensor:
        return F.normalize(d + 0.5 * F.normalize(torch.randn(d.shape, generator=gen), dim=1), dim=1)

    def kinds(n: int) -> torch.Tensor:
        return torch.randint(0, 3, (n,), generator=gen)

    ngp, ngl = args.ground_points, args.ground_lines
    gp, gl = disc(ngp, args.radius), lines(ngl, args.radius)
    ground = PrimitiveSet(gp, desc(ngp), torch.arange(ngp), gl, kinds(ngl), desc(ngl), torch.arange(ngl))

    yaw = float(torch.empty(1).uniform_(-math.pi, math.pi, generator=gen))
    t = torch.tensor([400.0, -250.0]) + 200 * (torch.rand(2, generator=gen) - 0.5)
    R = torch.tensor([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    n_patches = 5 if args.quick else args.patches
    true_idx = int(torch.randint(0, n_patches, (1,), generator=gen))
    nap, nal = args.aerial_points, args.aerial_lines
    kp, kl = min(round(args.inlier_fraction * ngp), nap), min(round(args.inlier_fraction * ngl), nal)

    patches = []
    for p in range(n_patches):
        if p == true_idx:
            centre = t
            sel_p = torch.randperm(ngp, generator=gen)[:kp]
            sel_l = torch.randperm(ngl, generator=gen)[:kl]
            pts = gp[sel_p] @ R.T + t + args.noise * torch.randn(kp, 2, generator=gen)
            lns = gl[sel_l] @ R.T + t + args.noise * torch.randn(kl, 2, 2, generator=gen)
            pts = torch.cat([pts, centre + disc(nap - kp, 1.2 * args.radius)])
            lns = torch.cat([lns, centre + lines(nal - kl, 1.2 * args.radius)])
            pd = torch.cat([perturb(ground.point_descriptors[sel_p]), desc(nap - kp)])
            ld = torch.cat([perturb(ground.line_descriptors[sel_l]), desc(nal - kl)])
            lk = torch.cat([ground.line_kinds[sel_l], kinds(nal - kl)])
            # shuffle so the inliers are not the leading rows
            op, ol = torch.randperm(nap, generator=gen), torch.randperm(nal, generator=gen)
            pts, pd, lns, ld, lk = pts[op], pd[op], lns[ol], ld[ol], lk[ol]
        else:
            centre = torch.tensor([400.0, -250.0]) + 1000 * (torch.rand(2, generator=gen) - 0.5)
            pts, lns = centre + disc(nap, 1.2 * args.radius), centre + lines(nal, 1.2 * args.radius)
            pd, ld, lk = desc(nap), desc(nal), kinds(nal)
        patches.append(PrimitiveSet(pts, pd, torch.arange(nap), lns, lk, ld, torch.arange(nal)))
    return ground, patches, true_idx, (yaw, float(t[0]), float(t[1]))


def real_scenes(args: argparse.Namespace) -> list:
    """Recorded cases (`--submaps`): each ground submap against the `--patches` patches of `--map`
    nearest its true position (from the sequence's groundtruth.tum), as `build_scene` returns them."""
    import numpy as np
    import torch

    if HERE not in sys.path:
        sys.path.insert(0, HERE)
    from exp_registration import containing_patch, true_T_world_odom

    from meridian_torch.geometry.planar import scalar_yaw_of
    from meridian_torch.geometry.se3 import interpolate_poses
    from meridian_torch.io.map_file import load_aerial_map
    from meridian_torch.io.sequence import SequenceReader
    from meridian_torch.types import PrimitiveSet

    aerial_map = load_aerial_map(args.map)
    gt = SequenceReader(args.sequence).groundtruth
    b = aerial_map.primitives
    scenes = []
    for submap in torch.load(args.submaps, weights_only=False)[: args.cases]:
        T_map_base = interpolate_poses(gt.timestamps, gt.poses, np.array([submap.time]))[0]
        T_map_base[:2, 3] -= aerial_map.local_origin_xy
        T_true = true_T_world_odom(T_map_base, submap.T_odom_base)
        nearest = np.argsort(np.linalg.norm(aerial_map.patches.centres_xy - T_map_base[:2, 3], axis=1))[: args.patches]
        true_patch = containing_patch(aerial_map.patches.centres_xy, aerial_map.patches.bounds_xy, T_map_base[:2, 3])
        patches = []
        for index in nearest.tolist():
            pv, lv = b.point_valid[index], b.line_valid[index]
            patches.append(PrimitiveSet(
                b.points_xy[index][pv], b.point_descriptors[index][pv], torch.arange(int(pv.sum())),
                b.line_endpoints[index][lv], b.line_kinds[index][lv], b.line_descriptors[index][lv],
                torch.arange(int(lv.sum())),
            ))
        true_idx = nearest.tolist().index(true_patch) if true_patch in nearest.tolist() else 0
        truth = (scalar_yaw_of(T_true), float(T_true[0, 2]), float(T_true[1, 2]))
        scenes.append((submap.primitives, patches, true_idx, truth))
    return scenes


def make_config(args: argparse.Namespace):
    """The shipped matching config (configs/default.yaml), with the options given on the command line."""
    from meridian_torch.config import CONFIG_DIR, load_config

    shipped = load_config(CONFIG_DIR / "default.yaml").matching
    particles = {"seed": args.seed}
    if args.particles is not None:
        particles["n_particles"] = args.particles
    if args.iterations is not None:
        particles["n_iterations"] = args.iterations
    if args.max_associations is not None:
        particles["max_associations"] = args.max_associations or None
    update = {"particles": shipped.particles.model_copy(update=particles), "solver": args.solver}
    if args.k_prim is not None:
        update["associations"] = shipped.associations.model_copy(update={"k_prim": args.k_prim})
    return shipped.model_copy(update=update)


# --------------------------------------------------------------------------------------------
# Child modes
# --------------------------------------------------------------------------------------------


def _top(hyp, p: int, truth: tuple[float, float, float]) -> dict:
    yaw, tx, ty = truth
    ok_valid = bool(hyp.valid[p, 0])
    theta = float(hyp.theta[p, 0])
    t = hyp.t[p, 0].tolist()
    dt = math.hypot(t[0] - tx, t[1] - ty)
    dyaw = abs(math.degrees(math.remainder(theta - yaw, 2 * math.pi)))
    return {
        "valid": ok_valid,
        "theta_deg": math.degrees(theta),
        "t": t,
        "err_t_m": dt,
        "err_yaw_deg": dyaw,
        "probability": float(hyp.probability[p, 0]),
        "objective": float(hyp.objective[p, 0]),
        "n_assoc": int(hyp.association_mask[p, 0].sum()),
        "within_5m_5deg": ok_valid and dt <= 5.0 and dyaw <= 5.0,
    }


def run_match_mode(args: argparse.Namespace) -> dict:
    """`--cases` independent scenes (seeds seed, seed + 1, ...), each matched in this child's mode."""
    import torch

    torch.set_num_threads(args.threads)
    from meridian_torch.core.timing import record_stages
    from meridian_torch.matching.match import match_submap
    from meridian_torch.matching.particles import patch_seeds
    from meridian_torch.types import stack_primitive_sets

    rss_imports = peak_rss_mib()
    cfg = make_config(args)
    if args.submaps:
        scenes = real_scenes(args)
    else:
        scenes = [build_scene(argparse.Namespace(**{**vars(args), "seed": args.seed + c})) for c in range(args.cases)]

    warmup_s = 0.0
    if not args.no_warmup:  # tiny problem: loads lazy code paths without touching the peak much
        ground, patches = scenes[0][0], scenes[0][1]
        one = stack_primitive_sets([patches[0]])
        small = type(one)(*[getattr(one, f.name)[:, :8] for f in dataclasses.fields(one)])
        small_cfg = cfg.model_copy(
            update={"particles": cfg.particles.model_copy(update={"n_particles": 4, "n_iterations": 10})}
        )
        t0 = time.perf_counter()
        match_submap(ground, small, config=small_cfg, generator=torch.Generator().manual_seed(0))
        warmup_s = time.perf_counter() - t0

    # Do the two modes get the same per-patch seeds from one generator?
    n_patches = len(scenes[0][1])
    g1, g2 = torch.Generator().manual_seed(args.seed), torch.Generator().manual_seed(args.seed)
    same_seeds = torch.equal(patch_seeds(n_patches, g1), torch.cat([patch_seeds(1, g2) for _ in range(n_patches)]))

    rss_before = current_rss_mib()
    peak_before = peak_rss_mib()
    cases = []
    for ground, patches, true_idx, truth in scenes:
        gen = torch.Generator().manual_seed(args.seed)
        cpu0 = time.process_time()
        with record_stages() as stages:
            if args.mode == "batched":
                batch = stack_primitive_sets(patches)
                t0 = time.perf_counter()
                hyp = match_submap(ground, batch, config=cfg, generator=gen)
                elapsed = time.perf_counter() - t0
                tops = [_top(hyp, p, truth) for p in range(len(patches))]
            else:
                tops = []
                t0 = time.perf_counter()
                for patch in patches:
                    hyp = match_submap(ground, stack_primitive_sets([patch]), config=cfg, generator=gen)
                    tops.append(_top(hyp, 0, truth))
                elapsed = time.perf_counter() - t0
        best = max(range(len(patches)), key=lambda p: tops[p]["objective"] if tops[p]["valid"] else -1.0)
        cases.append({
            "time_s": elapsed,
            "cpu_s": time.process_time() - cpu0,
            # seconds inside the Langevin loop, summed over the threads that ran it side by side
            "langevin_s": stages.total("langevin"),
            "true_idx": true_idx,
            "truth": truth,
            "true_top": tops[true_idx],
            "best_is_true": best == true_idx,
            "other_patches_within": sum(t["within_5m_5deg"] for p, t in enumerate(tops) if p != true_idx),
        })
    return {
        "mode": args.mode,
        "threads": torch.get_num_threads(),
        # threads the batched match's Langevin loops run on side by side: one per patch group
        "langevin_threads": min(args.threads, -(-n_patches // cfg.patch_chunk)) if args.mode == "batched" else 1,
        "torch": torch.__version__,
        "n_patches": n_patches,
        "cases": cases,
        "warmup_s": warmup_s,
        "rss_imports_mib": rss_imports,
        "rss_before_mib": rss_before,
        "peak_before_mib": peak_before,
        "peak_after_mib": peak_rss_mib(),
        "same_seeds": same_seeds,
    }


def run_clipper_mode(args: argparse.Namespace) -> dict:
    import torch

    torch.set_num_threads(args.threads)
    if HERE not in sys.path:
        sys.path.insert(0, HERE)
    from bench_clipper import bench_clipper

    t0 = time.perf_counter()
    rows = bench_clipper(args.clipper_sizes, args.seed)
    return {"mode": "clipper", "threads": torch.get_num_threads(), "rows": rows, "total_s": time.perf_counter() - t0}


# --------------------------------------------------------------------------------------------
# Parent
# --------------------------------------------------------------------------------------------


def _child(args: argparse.Namespace, argv: list[str], mode: str, source: str | None = None) -> dict:
    """Runs `--mode mode` in a fresh interpreter; `source` = the package tree it imports (PYTHONPATH)."""
    # Passive OpenMP waiting: on a shared 2-core machine a second busy process otherwise makes every
    # 2-thread op wait out spinning/descheduled workers (measured: match_submap 1.4 s -> 34-42 s).
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads),
               OMP_WAIT_POLICY=os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    return run_in_tree(__file__, [*argv, "--mode", mode], source, RESULT_TAG, env)


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def _fmt_top(top: dict) -> str:
    return (
        f"valid={top['valid']} yaw={top['theta_deg']:.2f} deg t=({top['t'][0]:.2f}, {top['t'][1]:.2f}) "
        f"err {top['err_t_m']:.2f} m / {top['err_yaw_deg']:.2f} deg, p={top['probability']:.3f}, "
        f"J={top['objective']:.2f}, {top['n_assoc']} assoc -> within 5 m / 5 deg: "
        f"{'YES' if top['within_5m_5deg'] else 'NO'}"
    )


def _speedup_for_ratio(target: float, lb: float, restb: float, ll: float, restl: float) -> float | None:
    """How many times faster the Langevin loop must run in both modes for loop / batched to reach
    `target`: (restl + ll / f) / (restb + lb / f) >= target; None if no f does (the rest alone
    stays below it)."""
    if restl + ll >= target * (restb + lb):
        return 1.0
    if restl <= target * restb:
        return None
    return (target * lb - ll) / (restl - target * restb)


def orchestrate(args: argparse.Namespace, argv: list[str]) -> None:
    n_patches = 5 if args.quick else args.patches
    cfg = make_config(args)
    print(
        f"bench_matching: seed {args.seed}, {args.cases} cases, {args.threads} torch threads, solver {args.solver}, "
        f"particles {cfg.particles.n_particles}, iterations {cfg.particles.n_iterations}, pruned to "
        f"{cfg.particles.max_associations or 'all'} associations, k_prim {cfg.associations.k_prim} "
        "(each tree's shipped config unless given)"
    )
    if args.submaps:
        print(f"recorded cases: the first {args.cases} submaps of {args.submaps}, each against the {args.patches} "
              f"patches of {args.map} nearest its true position ({args.sequence}/groundtruth.tum)")
    else:
        print(
            f"scene: ground {args.ground_points} points + {args.ground_lines} lines (radius {args.radius} m, "
            f"D={args.descriptor_dim}, {args.classes} classes); {n_patches} aerial patches of "
            f"{args.aerial_points} points + {args.aerial_lines} lines; true patch holds "
            f"{args.inlier_fraction:.0%} of the ground with {args.noise} m noise"
        )
    print(f"load average before: {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    trees = [("this tree", None)] + ([("baseline", args.baseline_src)] if args.baseline_src else [])
    results = {}
    for mode in ("batched", "loop"):
        for tree, source in trees:  # the trees alternate, so load changes hit both alike
            t0 = time.perf_counter()
            results[tree, mode] = _child(args, argv, mode, source)
            print(f"  [{tree} {mode} subprocess finished in {time.perf_counter() - t0:.1f} s incl. imports]", flush=True)
    b = results["this tree", "batched"]
    print(f"torch {b['torch']}, {b['threads']} threads in children; same per-patch seeds in both modes: "
          f"{b['same_seeds']}")
    print()
    print("median seconds per submap against all patches (wall | process CPU), over the cases:")
    hdr = ("tree", "batched s", "loop s", "loop/batched", "batched CPU s", "loop CPU s", "CPU ratio", "true ok",
           "peak MiB")
    print("{:>10} {:>10} {:>10} {:>12} {:>13} {:>10} {:>9} {:>9} {:>9}".format(*hdr))
    for tree, _ in trees:
        rb, rl = results[tree, "batched"], results[tree, "loop"]
        tb, tl = _median([c["time_s"] for c in rb["cases"]]), _median([c["time_s"] for c in rl["cases"]])
        cb, cl = _median([c["cpu_s"] for c in rb["cases"]]), _median([c["cpu_s"] for c in rl["cases"]])
        ok = sum(c["true_top"]["within_5m_5deg"] for c in rb["cases"])
        print(f"{tree:>10} {tb:>10.3f} {tl:>10.3f} {tl / tb:>11.2f}x {cb:>13.3f} {cl:>10.3f} {cl / cb:>8.2f}x "
              f"{ok:>4}/{len(rb['cases']):<4} {rb['peak_after_mib']:>9.1f}")
    print("the Langevin loop (one kernel in both modes) against the rest, median seconds per submap:")
    needed = []
    print("{:>10} {:>16} {:>13} {:>16} {:>13} {:>22}".format(
        "tree", "batched Langevin", "batched rest", "loop Langevin", "loop rest", "loop/batched, rest"))
    for tree, _ in trees:
        rb, rl = results[tree, "batched"], results[tree, "loop"]
        if not any(c["langevin_s"] for c in rb["cases"] + rl["cases"]):
            print(f"{tree:>10}  (its package does not time the Langevin loop: no 'langevin' stage)")
            continue
        # The batched loops run side by side, so their wall share is their seconds / threads.
        lb = _median([c["langevin_s"] for c in rb["cases"]]) / rb.get("langevin_threads", 1)
        ll = _median([c["langevin_s"] for c in rl["cases"]])
        restb = _median([c["time_s"] - c["langevin_s"] / rb.get("langevin_threads", 1) for c in rb["cases"]])
        restl = _median([c["time_s"] - c["langevin_s"] for c in rl["cases"]])
        print(f"{tree:>10} {lb:>16.3f} {restb:>13.3f} {ll:>16.3f} {restl:>13.3f} {restl / restb:>21.2f}x")
        needed.append((tree, _speedup_for_ratio(5.0, lb, restb, ll, restl)))
    print("  (loop/batched, rest: the ratio if the Langevin loop cost nothing in either mode; the loop's own ratio "
          "is at most the threads that run it side by side)")
    for tree, f in needed:
        print(f"  {tree}: loop/batched reaches 5x " + ("already" if f is not None and f <= 1 else
              f"if the Langevin loop runs {f:.2f}x faster in both modes" if f is not None else
              "not even with a free Langevin loop"))
    if args.baseline_src:
        new, old = results["this tree", "batched"], results["baseline", "batched"]
        speedup = _median([c["time_s"] for c in old["cases"]]) / _median([c["time_s"] for c in new["cases"]])
        cpu_speedup = _median([c["cpu_s"] for c in old["cases"]]) / _median([c["cpu_s"] for c in new["cases"]])
        print(f"batched, baseline / this tree: {speedup:.2f}x wall, {cpu_speedup:.2f}x CPU")
    print(
        "  (true ok = cases whose true patch's top hypothesis is within 5 m / 5 deg, batched; peak = the "
        "batched child's ru_maxrss)"
    )
    for tree, _ in trees:
        for mode in ("batched", "loop"):
            r = results[tree, mode]
            other = sum(c["other_patches_within"] for c in r["cases"])
            print(f"{tree} {mode}: first case's true patch: {_fmt_top(r['cases'][0]['true_top'])}; "
                  f"other patches within 5 m / 5 deg over all cases: {other}; warm-up {r['warmup_s']:.2f} s")
    print(f"load average after: {', '.join(f'{x:.2f}' for x in os.getloadavg())}")

    if args.skip_clipper:
        return
    print()
    t0 = time.perf_counter()
    c = _child(args, argv, "clipper")
    rows = c["rows"]
    print(f"CLIPPER solver alone (scripts/bench_clipper.py bench_clipper(sizes={args.clipper_sizes}, "
          f"seed={args.seed}); {c['threads']} threads, subprocess {time.perf_counter() - t0:.1f} s)")
    print(f"peak RSS before the first problem {rows[0]['baseline_rss_mib']:.1f} MiB (process peak so far per row)")
    header = ("n", "rounding", "dtype", "time ms", "peak MiB", "iters", "sel", "prec", "recall")
    print("{:>6} {:>9} {:>8} {:>9} {:>9} {:>6} {:>5} {:>5} {:>6}".format(*header))
    for r in rows:
        print(
            f"{r['n']:>6} {r['rounding']:>9} {r['dtype']:>8} {r['time_ms']:>9.1f} {r['peak_rss_mib']:>9.1f} "
            f"{r['iterations']:>6} {r['selected']:>5} {r['precision']:>5.2f} {r['recall']:>6.2f}"
        )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=0, help="seed of the scene, the particle sampler and bench_clipper")
    p.add_argument("--threads", type=int, default=2, help="torch intra-op threads in every child (default 2)")
    p.add_argument("--quick", action="store_true", help="smoke run: 5 aerial patches instead of --patches")
    p.add_argument("--patches", type=int, default=25, help="number of aerial patches P (default 25)")
    p.add_argument("--cases", type=int, default=20, help="independent scenes (seeds seed, seed + 1, ...); medians over them")
    p.add_argument("--baseline-src", default=None,
                   help="another source tree (its package directory's parent) benchmarked in the same run, side by side")
    p.add_argument("--particles", type=int, default=None,
                   help="Langevin particles per patch (default: the shipped config's, configs/default.yaml)")
    p.add_argument("--iterations", type=int, default=None, help="max Langevin iterations (default: shipped)")
    p.add_argument("--max-associations", type=int, default=None,
                   help="support pruning before sampling, 0 = off (default: shipped)")
    p.add_argument("--k-prim", type=int, default=None, help="semantic neighbours per ground primitive (default: shipped)")
    p.add_argument("--solver", choices=["particles", "clipper"], default="particles", help="inlier-set solver")
    p.add_argument("--submaps", default=None,
                   help="recorded cases instead of synthetic scenes: ground submaps saved by exp_registration.py --cache "
                   "(needs --map and --sequence)")
    p.add_argument("--map", default=None, help="with --submaps: the aerial map (.mtm)")
    p.add_argument("--sequence", default=None, help="with --submaps: the sequence folder with groundtruth.tum")
    # Defaults: the issue-15 case, about 20 ground and 65 aerial primitives per patch.
    p.add_argument("--ground-points", type=int, default=8)
    p.add_argument("--ground-lines", type=int, default=12)
    p.add_argument("--aerial-points", type=int, default=25)
    p.add_argument("--aerial-lines", type=int, default=40)
    p.add_argument("--radius", type=float, default=40.0, help="radius (m) of the disc of ground primitives")
    p.add_argument("--descriptor-dim", type=int, default=32)
    p.add_argument("--classes", type=int, default=8, help="descriptor class centres")
    p.add_argument("--inlier-fraction", type=float, default=0.7, help="share of ground primitives in the true patch")
    p.add_argument("--noise", type=float, default=0.3, help="position noise (m) of the true patch's inliers")
    p.add_argument("--clipper-sizes", type=int, nargs="+", default=[500, 1000, 2000], help="n for bench_clipper")
    p.add_argument("--skip-clipper", action="store_true", help="do not run part (c)")
    p.add_argument("--no-warmup", action="store_true", help="skip the tiny warm-up match before timing")
    p.add_argument(
        "--mode",
        choices=["batched", "loop", "clipper"],
        default=None,
        help="internal: run one stage in this process and print its JSON result (the parent spawns these)",
    )
    return p


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.submaps and not (args.map and args.sequence):
        parser.error("--submaps needs --map and --sequence")
    if args.mode is None:
        orchestrate(args, argv)
        return
    result = run_clipper_mode(args) if args.mode == "clipper" else run_match_mode(args)
    print(RESULT_TAG + json.dumps(result), flush=True)


if __name__ == "__main__":
    main()

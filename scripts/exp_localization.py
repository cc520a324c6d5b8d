"""Full-pipeline experiments: the paper's Table I analogue on worlds built from the real KITTI maps,
the "without path-length scaling" ablation (paper Table V) and outdated aerial imagery.

Worlds come from configs/kitti00.yaml (real KITTI 00 map, aligned real ground truth, real ORB-SLAM2
odometry), kitti02.yaml and kitti09.yaml (real maps and ground truth, simulated drifting odometry);
`demo` is the built-in demo world (configs/demo.yaml), small enough to run every variant quickly.
Each sequence is rendered once into --work-dir and its aerial map built once; every variant then
runs the online pipeline (ground mapping, incremental localization, final optimization) and is
evaluated against the ground truth. The KITTI worlds need the team's shared data folder beside the
repository.

Variants:
  default      the configuration as shipped
  no-scaling   loop-closure consistency noise does not grow with path length (paper Table V)
  outdated     the aerial map is built from an outdated orthophoto of the same world (seasonal
               colours, some objects removed or added) while the robot sees today's world

The table gives per run the final and incremental ATE, the worst incremental error, the fraction
of frames localized online, the distance to the first fix, the consistency of the final and of the
online per-pose covariance (mean position NEES and the fraction of positions inside the 2-sigma
ellipse, final / online) and the real-time factor; the JSON keeps every metric. The covariance
columns need `backend.covariance`, which is on as shipped (`--set backend.covariance=false` leaves
them empty and saves the marginals' time).

Usage:
  python scripts/exp_localization.py --work-dir runs/exp [--sequences demo 00 09] \
      [--variants default no-scaling outdated] [--max-frames 600] [--set key=value ...]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from tqdm import tqdm

from meridian_torch.config import CONFIG_DIR, MeridianConfig, config_key, load_config
from meridian_torch.evaluation.trajectory_metrics import evaluate_run
from meridian_torch.io.atomic import write_text_atomic
from meridian_torch.io.map_file import load_aerial_map
from meridian_torch.io.ortho import write_orthophoto
from meridian_torch.io.sequence import SequenceReader
from meridian_torch.mapping.aerial_map import build_map_file, map_config_dict
from meridian_torch.pipeline import localize_sequence
from meridian_torch.pipeline.outputs import write_outputs
from meridian_torch.runtime import resolve_runtime
from meridian_torch.sim.simulate import render_world_orthophoto, simulate_sequence
from meridian_torch.types import AerialMap

# Paper Table I (KITTI ATE, m): Meridian incremental / final; Table V is on the Camp data only.
PAPER = {"kitti00": (2.0, 1.5), "kitti02": (3.3, 4.2), "kitti09": (2.4, 2.1)}  # by sim.name
CONFIGS = {"demo": "demo.yaml", "00": "kitti00.yaml", "02": "kitti02.yaml", "09": "kitti09.yaml"}
VARIANTS = ("default", "no-scaling", "outdated")


def _bar(desc: str):
    bar = tqdm(desc=desc, dynamic_ncols=True, leave=False)

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    return bar, update


def sequence_folder(cfg: MeridianConfig, work_dir: Path) -> Path:
    """Render the world once (cached by its sim config)."""
    folder = work_dir / f"{cfg.sim.name}-{config_key(cfg.sim.model_dump(mode='json'))}"
    if not folder.exists():
        bar, update = _bar(f"render {cfg.sim.name}")
        simulate_sequence(cfg.sim, folder, progress=update)
        bar.close()
    return folder


def outdated_orthophoto(cfg: MeridianConfig, folder: Path) -> Path:
    """The same world's orthophoto with the simulator's outdated-imagery changes, beside the sequence."""
    out = folder.with_name(folder.name + "-outdated-ortho")
    if not (out / "ortho.png").exists():
        sim = cfg.sim.model_copy(update={"ortho": cfg.sim.ortho.model_copy(update={"outdated": True})})
        ortho = render_world_orthophoto(sim)
        out.mkdir(parents=True, exist_ok=True)
        write_orthophoto(out, ortho)
    return out


def aerial_map(cfg: MeridianConfig, ortho_path: Path, out_dir: Path) -> AerialMap:
    map_config = map_config_dict(cfg.aerial_map, cfg.perception, cfg.primitives)
    path = out_dir / f"aerial-{config_key(map_config)}.mtm"
    if path.exists():
        return load_aerial_map(path, expected_config=map_config)
    bar, update = _bar(f"aerial map {ortho_path}")
    built = build_map_file(ortho_path, path, cfg.aerial_map, cfg.perception, cfg.primitives, progress=update)
    bar.close()
    return built


def variant_config(cfg: MeridianConfig, variant: str) -> MeridianConfig:
    if variant == "no-scaling":
        backend = cfg.backend.model_copy(update={"sigma_yaw_deg_per_m": 0.0, "sigma_t_m_per_m": 0.0})
        return cfg.model_copy(update={"backend": backend})
    return cfg


def run_variant(cfg: MeridianConfig, folder: Path, variant: str, work_dir: Path) -> dict:
    ortho_path = outdated_orthophoto(cfg, folder) if variant == "outdated" else folder
    amap = aerial_map(cfg, ortho_path, ortho_path)
    vcfg = variant_config(cfg, variant)
    reader = SequenceReader(folder)
    out = work_dir / "results" / f"{cfg.sim.name}-{variant}"
    bar, update = _bar(f"{cfg.sim.name} {variant}")
    run = localize_sequence(reader, amap, vcfg, resolve_runtime(vcfg.runtime), on_frames=update)
    bar.close()
    write_outputs(out, run.result, crs=reader.ortho().crs)
    metrics = evaluate_run(out, reader.groundtruth, vcfg.evaluation)
    return {
        "sequence": cfg.sim.name,
        "variant": variant,
        "frames": len(reader),
        "submaps": len(run.submaps),
        "metrics": metrics,
        "seconds": run.seconds,
        "real_time_factor": run.real_time_factor,
        "peak_memory_mib": run.peak_memory_mib,
        "out": str(out),
    }


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def _nees(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def table(rows: list[dict]) -> str:
    """One line per run: final and incremental ATE (RMSE), the worst incremental error, frames with
    an online estimate, ground-truth distance to the first fix, the final and online covariances'
    consistency as "final / online" (position NEES, consistent 2; positions inside the 2-sigma
    ellipse, consistent 86 %), RTF."""
    lines = [
        "| world | variant | frames | submaps | ATE final (m) | ATE incremental (m) | worst incremental (m) "
        "| localized online | first fix (m) | position NEES final / online (2) "
        "| inside 2 sigma final / online (86 %) | paper inc. / final (m) | RTF |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        m = r["metrics"]
        inc = m.get("incremental") or {}
        fin = m.get("final") or {}
        consistency = [m.get(f"{name}_covariance_consistency") or {} for name in ("final", "incremental")]
        nees = " / ".join(_nees(c.get("position_nees_mean")) for c in consistency)
        within = " / ".join(_percent(c.get("position_within_2sigma")) for c in consistency)
        paper = PAPER.get(r["sequence"])
        paper_s = f"{paper[0]} / {paper[1]}" if paper and r["variant"] == "default" else ""
        lines.append(
            f"| {r['sequence']} | {r['variant']} | {r['frames']} | {r['submaps']} | {_fmt(fin.get('ate_rmse_m'))} "
            f"| {_fmt(inc.get('ate_rmse_m'))} | {_fmt(inc.get('ate_max_m'))} "
            f"| {_percent(m.get('fraction_localized'))} | {_fmt(m.get('distance_to_first_fix_m'))} "
            f"| {nees} | {within} | {paper_s} | {r['real_time_factor']:.2f} |"
        )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--work-dir", type=Path, required=True, help="where worlds, maps and results are kept")
    parser.add_argument("--sequences", nargs="+", default=["00", "02", "09"], choices=list(CONFIGS))
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--max-frames", type=int, default=None, help="only the first N frames of each sequence")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    args = parser.parse_args()

    rows = []
    for seq in args.sequences:
        overrides = list(args.overrides)
        if args.max_frames:
            overrides.append(f"sim.trajectory.max_frames={args.max_frames}")
        cfg = load_config(CONFIG_DIR / CONFIGS[seq], overrides)
        started = time.perf_counter()
        folder = sequence_folder(cfg, args.work_dir)
        for variant in args.variants:
            row = run_variant(cfg, folder, variant, args.work_dir)
            rows.append(row)
            print(table([row]).splitlines()[-1], f"({time.perf_counter() - started:.0f} s so far)", flush=True)
    print()
    print(table(rows))
    out = args.work_dir / "results" / "exp_localization.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, json.dumps(rows, indent=2, default=float) + "\n")
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Commands that run the system: localize a sequence, evaluate a run, the demo on a simulated world."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from meridian_torch.cli.common import (
    ConfigOption,
    SetOption,
    config_from_options,
    error_boundary,
    interruptible,
)
from meridian_torch.cli.maps import build_map_with_progress
from meridian_torch.cli.sequences import simulate_with_progress
from meridian_torch.config import CONFIG_DIR, MeridianConfig, config_key
from meridian_torch.errors import CheckpointError

__all__ = ["demo", "evaluate", "localize"]


def _load_or_build_map(cfg: MeridianConfig, map_path: Path, ortho_path: Path, ortho: Any = None) -> Any:
    """The aerial map at `map_path`, checked against the config and `ortho` (the sequence's
    orthophoto) when given; built from `ortho_path` first when missing."""
    from meridian_torch.pipeline.prepare import open_aerial_map

    if map_path.exists():
        typer.echo(f"using the aerial map {map_path}")
        return open_aerial_map(cfg, map_path, ortho_path, ortho)
    typer.echo(f"building the aerial map {map_path} from {ortho_path}")
    return build_map_with_progress(cfg, ortho_path, map_path)


def _localize(cfg: MeridianConfig, reader: Any, ortho: Any, aerial_map: Any, out: Path,
              shown: Path | None = None, matcher: Any = None) -> dict[str, Any] | None:
    """Run the online pipeline with live progress, write the outputs into `out`, evaluate when ground
    truth exists; messages name `shown` (where the outputs will be) instead of `out`."""
    from tqdm import tqdm

    from meridian_torch.pipeline import localize_sequence
    from meridian_torch.pipeline.outputs import write_run_folder
    from meridian_torch.runtime import resolve_runtime

    runtime = resolve_runtime(cfg.runtime)
    bar = tqdm(desc="localizing", unit="frame", total=len(reader), dynamic_ncols=True)

    def on_frames(done: int, total: int) -> None:
        bar.update(done - bar.n)

    def on_submap(submap: Any, event: Any) -> None:
        bar.write(
            f"submap {submap.index:3d} t={submap.time:7.1f} s {submap.path_length_m:6.0f} m: "
            f"{event.n_patches} patches, {event.n_hypotheses} hypotheses | pool {event.n_candidates}, "
            f"{event.n_inliers} inliers [{event.state}]"
        )
        if event.fix_committed:
            bar.write(f"==> global fix committed at submap {submap.index} ({event.n_inliers} inliers)")
        if event.fix_doubted:
            bar.write(f"==> global fix in doubt at submap {submap.index}: too few of the submaps since it agree; "
                      "estimate withheld")
        if event.fix_revoked:
            bar.write(f"==> global fix revoked at submap {submap.index}: too few of the submaps since it agree; "
                      "searching the whole map again")

    try:
        run = localize_sequence(
            reader, aerial_map, cfg, runtime, on_frames=on_frames, on_submap=on_submap,
            on_stage=lambda name: bar.write(f"{name} ..."), matcher=matcher,
        )
    finally:
        bar.close()
    metrics, report = write_run_folder(out, run, crs=ortho.crs, ortho=ortho, groundtruth=reader.groundtruth,
                                       evaluation=cfg.evaluation)
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in run.seconds.items())
    typer.echo(f"{len(run.submaps)} submaps; {stages}; real-time factor {run.real_time_factor:.2f}; "
               f"peak memory {run.peak_memory_mib:.0f} MiB")
    why = f" ({run.result.rejected_because})" if run.result.rejected_because else ""
    typer.echo(f"localized: {'yes' if run.result.localized else 'no'}{why}; report: {(shown or out) / report.name}")
    return metrics


def _print_metrics(metrics: dict[str, Any]) -> None:
    final, inc = metrics.get("final") or {}, metrics.get("incremental") or {}
    def fmt(v: Any, unit: str) -> str:
        return "n/a" if v is None else f"{v:.2f} {unit}"
    typer.echo(
        f"ATE final {fmt(final.get('ate_rmse_m'), 'm')}, incremental {fmt(inc.get('ate_rmse_m'), 'm')}; "
        f"heading RMSE final {fmt(final.get('heading_rmse_deg'), 'deg')}"
    )


@error_boundary
def localize(
    sequence: Annotated[Path, typer.Argument(help="Sequence folder (format: README, Formats).")],
    map_file: Annotated[Path, typer.Option("--map", "-m", help="Aerial map (.mtm); built from the sequence's "
                                                                "orthophoto first if it does not exist.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder (trajectories, metrics, plots, report); "
                                                          "a folder that holds files needs --overwrite.")],
    config: ConfigOption = None,
    set_: SetOption = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an output folder that holds files (all of them, when "
                                                 "the run is complete).")] = False,
    resume: Annotated[bool, typer.Option(help="Continue an interrupted run of the same command from its checkpoint "
                                              "(.OUT.checkpoint beside OUT): same result as an uninterrupted run.")]
    = False,
) -> None:
    """Localize a sequence in an aerial map: online (incremental) and offline (final) trajectories.

    Writes trajectory.tum, trajectory_incremental.tum, covariances, loop-closure inliers, a report
    with plots, geo outputs when the orthophoto has a CRS, and metrics.json when groundtruth.tum
    exists. Progress shows every submap, its hypotheses, the inlier count and the global fix.
    The outputs are written into a temporary folder beside OUT that replaces it only when the run
    is complete: an interrupted or failed run leaves OUT as it was. Matching results are kept in a
    checkpoint folder beside OUT (.OUT.checkpoint) until the run completes; after an interruption
    (Ctrl-C, SIGTERM) the same command with --resume continues from it.
    """
    from meridian_torch.io.atomic import atomic_directory
    from meridian_torch.io.run_info import write_run_info
    from meridian_torch.pipeline.checkpoint import MatchingCheckpoint
    from meridian_torch.pipeline.prepare import checkpoint_key, open_sequence, refuse_foreign_folder

    refuse_foreign_folder(out, overwrite)
    cfg = config_from_options(config, set_)
    reader, ortho = open_sequence(cfg, sequence)
    checkpoint_dir = out.parent / f".{out.name}.checkpoint"
    if resume and not checkpoint_dir.exists():
        raise CheckpointError(f"{checkpoint_dir}: no checkpoint to resume (it is kept only when a run was interrupted)")
    if not resume and checkpoint_dir.exists():
        typer.echo(f"discarding the checkpoint of an interrupted earlier run ({checkpoint_dir}; --resume continues it)")
        shutil.rmtree(checkpoint_dir)
    checkpoint = None
    try:
        with interruptible(out), atomic_directory(out, overwrite=True) as tmp:
            write_run_info(tmp, cfg, "localize")
            aerial_map = _load_or_build_map(cfg, map_file, sequence, ortho)
            checkpoint = MatchingCheckpoint(checkpoint_dir, checkpoint_key(cfg, aerial_map, sequence))
            if resume:
                typer.echo(f"resuming: {checkpoint.recorded} matching results in {checkpoint_dir}")
            metrics = _localize(cfg, reader, ortho, aerial_map, tmp, shown=out, matcher=checkpoint)
    except typer.Exit as stop:
        if stop.exit_code == 130 and checkpoint is not None and checkpoint.recorded:
            typer.echo(f"{checkpoint.recorded} matching results are kept in {checkpoint_dir}: the same command with "
                       "--resume continues from there", err=True)
        raise
    if resume:
        typer.echo(f"resumed: {checkpoint.replayed} matching results taken from the checkpoint")
    checkpoint.discard()
    if metrics is not None:
        _print_metrics(metrics)
    typer.echo(f"outputs in {out}")


@error_boundary
def evaluate(
    run_dir: Annotated[Path, typer.Argument(help="Output folder of `meridian-torch localize`.")],
    groundtruth: Annotated[Path, typer.Option("--groundtruth", "-g", help="Ground truth T_world_base (TUM).")],
    config: ConfigOption = None,
    set_: SetOption = None,
) -> None:
    """(Re-)compute metrics.json of a localization run against a ground-truth TUM file."""
    from meridian_torch.evaluation.trajectory_metrics import evaluate_run
    from meridian_torch.io.poses import read_tum

    cfg = config_from_options(config, set_)
    metrics = evaluate_run(run_dir, read_tum(groundtruth), cfg.evaluation)
    _print_metrics(metrics)
    typer.echo(f"wrote {run_dir / 'metrics.json'}")


def _default_cache_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "meridian-torch"


@error_boundary
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the demo's outputs.")] = Path("meridian-demo"),
    cache_dir: Annotated[
        Path | None, typer.Option(help="Where rendered worlds and maps are cached (default: ~/.cache/meridian-torch).")
    ] = None,
    config: ConfigOption = None,
    set_: SetOption = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an output folder that holds files other than an "
                                                 "earlier demo's.")] = False,
) -> None:
    """Run the whole system on the built-in default world and print its ATE.

    Renders the world once into the cache, builds (or reuses) its aerial map, then maps the ground
    frames, localizes every submap online, optimizes the final trajectory and evaluates it against
    the simulator's ground truth. Outputs (trajectories, metrics, plots, report) go to OUT, through
    a temporary folder that replaces it when the demo is complete; an earlier demo's OUT is
    replaced, any other folder with files needs --overwrite.
    """
    from meridian_torch.evaluation.plots import plot_aerial_map
    from meridian_torch.io.atomic import atomic_directory
    from meridian_torch.io.run_info import write_run_info
    from meridian_torch.mapping.aerial_map import map_config_dict
    from meridian_torch.pipeline.prepare import open_sequence, refuse_foreign_folder
    from meridian_torch.sim.preview import write_preview

    refuse_foreign_folder(out, overwrite, command="demo")
    cfg = config_from_options(config if config is not None else CONFIG_DIR / "demo.yaml", set_)
    started = time.perf_counter()
    # Cache keys are the configs that shape each product: any change renders or builds anew.
    sequence = (cache_dir or _default_cache_dir()) / "worlds" / f"{cfg.sim.name}-{config_key(cfg.sim.model_dump(mode='json'))}"
    with interruptible(out), atomic_directory(out, overwrite=True) as tmp:
        write_run_info(tmp, cfg, "demo")
        if sequence.exists():
            typer.echo(f"[1/3] using the cached world {sequence}")
        else:
            typer.echo(f"[1/3] rendering the demo world into {sequence} (once)")
            summary = simulate_with_progress(cfg, sequence, overwrite=False)
            typer.echo(f"      {summary.frames} frames, {summary.path_length_m:.0f} m of driving")
        preview = write_preview(sequence, tmp / "preview.png")

        map_config = map_config_dict(cfg.aerial_map, cfg.perception, cfg.primitives)
        typer.echo("[2/3] aerial map")
        reader, ortho = open_sequence(cfg, sequence)
        aerial_map = _load_or_build_map(cfg, sequence / f"aerial-{config_key(map_config)}.mtm", sequence, ortho)
        prims = aerial_map.primitives
        typer.echo(f"      {len(aerial_map)} patches, {int(prims.point_valid.sum())} points, "
                   f"{int(prims.line_valid.sum())} lines")
        map_png = plot_aerial_map(aerial_map, ortho, tmp / "aerial_map.png")

        typer.echo("[3/3] ground mapping and localization")
        metrics = _localize(cfg, reader, ortho, aerial_map, tmp, shown=out)
    typer.echo(f"plots: {out / preview.name}, {out / map_png.name}")
    if metrics is not None:
        _print_metrics(metrics)
    typer.echo(f"demo finished in {time.perf_counter() - started:.1f} s; outputs in {out}")

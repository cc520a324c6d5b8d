"""The `meridian-torch` command: a thin layer over the package with one error boundary.

Heavy modules (simulator, renderer, matplotlib) are imported inside the commands that use them.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Annotated, Any, Callable

import typer

from meridian_torch import __version__
from meridian_torch.config import CONFIG_DIR, MeridianConfig, dump_config, load_config
from meridian_torch.errors import MeridianError

__all__ = ["app", "main"]

app = typer.Typer(
    name="meridian-torch",
    help="Cross-view geo-localization of a ground robot (RGB-D + odometry) in an aerial orthophoto.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
config_app = typer.Typer(help="Inspect configuration files.", no_args_is_help=True)
app.add_typer(config_app, name="config")

ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="YAML config file (default: configs/default.yaml).", dir_okay=False),
]
SetOption = Annotated[
    list[str] | None,
    typer.Option("--set", "-s", help="Override a config key, e.g. --set sim.seed=3 (repeatable)."),
]


def _error_boundary(command: Callable[..., Any]) -> Callable[..., Any]:
    """MeridianError -> one line on stderr and exit code 1; anything else keeps its traceback."""

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return command(*args, **kwargs)
        except MeridianError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1) from None

    return wrapper


def _load(config: Path | None, overrides: list[str] | None) -> MeridianConfig:
    return load_config(config, overrides or [])


def _progress_bar(desc: str, unit: str) -> tuple[Callable[[int, int], None], Callable[[], None]]:
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit=unit, dynamic_ncols=True)

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    return update, bar.close


@app.callback(invoke_without_command=True)
def _root(
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
) -> None:
    if version:
        typer.echo(f"meridian-torch {__version__}")
        raise typer.Exit()


@config_app.command("show")
@_error_boundary
def config_show(config: ConfigOption = None, set_: SetOption = None) -> None:
    """Print the fully resolved config (defaults, file and --set overrides) as YAML."""
    typer.echo(dump_config(_load(config, set_)), nl=False)


@app.command()
@_error_boundary
def check(
    sequence: Annotated[Path, typer.Argument(help="Sequence folder (see FORMAT.md in the README).")],
) -> None:
    """Validate a sequence folder against the format and report every problem found."""
    from meridian_torch.io.sequence import check_sequence

    problems = check_sequence(sequence)
    if problems:
        for problem in problems:
            typer.echo(f"- {problem}")
        typer.echo(f"{sequence}: {len(problems)} problem(s) found", err=True)
        raise typer.Exit(1)
    typer.echo(f"{sequence}: OK")


def _simulate(cfg: MeridianConfig, out: Path, overwrite: bool) -> Any:
    from meridian_torch.runtime import resolve_runtime
    from meridian_torch.sim.preview import write_preview
    from meridian_torch.sim.simulate import simulate_sequence

    runtime = resolve_runtime(cfg.runtime)
    update, close = _progress_bar("rendering frames", "frame")
    try:
        summary = simulate_sequence(cfg.sim, out, device=runtime.device, overwrite=overwrite, progress=update)
    finally:
        close()
    write_preview(out, out / "preview.png")
    return summary


@app.command()
@_error_boundary
def simulate(
    out: Annotated[Path, typer.Option("--out", "-o", help="Sequence folder to write (must not exist).")],
    config: ConfigOption = None,
    set_: SetOption = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing folder.")] = False,
) -> None:
    """Render a simulated world into a sequence folder, with ground truth and a preview PNG.

    The folder holds aerial/ (orthophoto), ground/ (RGB-D frames, odometry), groundtruth.tum,
    sim/ (the world's ground-truth objects and borders), preview.png, config.yaml and run.json.
    """
    from meridian_torch.io.run_info import write_run_info

    cfg = _load(config, set_)
    started = time.perf_counter()
    summary = _simulate(cfg, out, overwrite)
    write_run_info(out, cfg, "simulate")
    typer.echo(
        f"wrote {out}: {summary.frames} frames, {summary.path_length_m:.0f} m in {summary.duration_s:.0f} s "
        f"of driving ({time.perf_counter() - started:.1f} s); preview: {out / 'preview.png'}"
    )


def _build_map(cfg: MeridianConfig, ortho_path: Path, out: Path) -> Any:
    import shutil

    from meridian_torch.io.map_file import save_aerial_map
    from meridian_torch.io.ortho import find_orthophoto, read_orthophoto
    from meridian_torch.mapping.aerial_map import AerialMapper, build_aerial_map
    from meridian_torch.runtime import resolve_runtime

    runtime = resolve_runtime(cfg.runtime)
    ortho = read_orthophoto(ortho_path)
    mapper = AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives, device=runtime.device)
    work_dir = out.with_name(out.name + ".parts")
    update, close = _progress_bar("building aerial map", "patch")
    try:
        aerial_map = build_aerial_map(
            ortho, mapper, work_dir=work_dir, progress=update,
            source={"orthophoto": str(find_orthophoto(ortho_path).resolve())},
        )
    finally:
        close()
    save_aerial_map(aerial_map, out)
    shutil.rmtree(work_dir, ignore_errors=True)
    return aerial_map


@app.command("build-map")
@_error_boundary
def build_map(
    ortho: Annotated[Path, typer.Argument(help="Orthophoto: a sequence folder, its aerial/ folder, a PNG/JPEG "
                                               "with its .json georeference, or a GeoTIFF.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Map file to write (.mtm).")],
    config: ConfigOption = None,
    set_: SetOption = None,
) -> None:
    """Turn an orthophoto into an aerial map of point and line primitives (resumable).

    Finished patches are kept in OUT.parts/ while building: run the same command again after an
    interruption and it continues where it stopped.
    """
    cfg = _load(config, set_)
    started = time.perf_counter()
    aerial_map = _build_map(cfg, ortho, out)
    prims = aerial_map.primitives
    typer.echo(
        f"wrote {out}: {len(aerial_map)} patches, {int(prims.point_valid.sum())} points, "
        f"{int(prims.line_valid.sum())} lines ({time.perf_counter() - started:.1f} s)"
    )


@app.command("show-map")
@_error_boundary
def show_map(
    map_file: Annotated[Path, typer.Argument(help="Aerial map file (.mtm).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="PNG to write.")],
    ortho: Annotated[Path | None, typer.Option(help="Orthophoto to draw under the primitives "
                                                    "(default: the one the map was built from, if it exists).")] = None,
) -> None:
    """Draw a map's primitives over its orthophoto, coloured by descriptor cluster, with the patch grid."""
    from meridian_torch.evaluation.plots import plot_aerial_map
    from meridian_torch.io.map_file import load_aerial_map
    from meridian_torch.io.ortho import read_orthophoto

    aerial_map = load_aerial_map(map_file)
    source = ortho or (Path(aerial_map.source["orthophoto"]) if "orthophoto" in aerial_map.source else None)
    image = read_orthophoto(source) if source is not None and source.exists() else None
    typer.echo(f"wrote {plot_aerial_map(aerial_map, image, out)}")


def _default_cache_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "meridian-torch"


def _cache_key(*parts: Any) -> str:
    return hashlib.sha256(json.dumps([__version__, *parts], sort_keys=True).encode()).hexdigest()[:12]


@app.command()
@_error_boundary
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the demo's outputs.")] = Path("meridian-demo"),
    cache_dir: Annotated[
        Path | None, typer.Option(help="Where rendered worlds and maps are cached (default: ~/.cache/meridian-torch).")
    ] = None,
    config: ConfigOption = None,
    set_: SetOption = None,
) -> None:
    """Run every available stage on the built-in default world (rendered once, then cached).

    Stages today: simulate the world (cached), build its aerial map (cached), plot both.
    """
    from meridian_torch.evaluation.plots import plot_aerial_map
    from meridian_torch.io.map_file import load_aerial_map
    from meridian_torch.io.ortho import read_orthophoto
    from meridian_torch.io.run_info import write_run_info
    from meridian_torch.mapping.aerial_map import map_config_dict
    from meridian_torch.sim.preview import write_preview

    cfg = _load(config if config is not None else CONFIG_DIR / "demo.yaml", set_)
    started = time.perf_counter()
    write_run_info(out, cfg, "demo")
    # Cache keys are the configs that shape each product: any change renders or builds anew.
    sequence = (cache_dir or _default_cache_dir()) / "worlds" / f"{cfg.sim.name}-{_cache_key(cfg.sim.model_dump(mode='json'))}"
    if sequence.exists():
        typer.echo(f"[1/2] using the cached world {sequence}")
    else:
        typer.echo(f"[1/2] rendering the demo world into {sequence} (once)")
        summary = _simulate(cfg, sequence, overwrite=False)
        typer.echo(f"      {summary.frames} frames, {summary.path_length_m:.0f} m of driving")
    preview = write_preview(sequence, out / "preview.png")

    map_config = map_config_dict(cfg.aerial_map, cfg.perception, cfg.primitives)
    map_path = sequence / f"aerial-{_cache_key(map_config)}.mtm"
    if map_path.exists():
        typer.echo(f"[2/2] using the cached aerial map {map_path}")
        aerial_map = load_aerial_map(map_path, expected_config=map_config)
    else:
        typer.echo(f"[2/2] building the aerial map {map_path}")
        aerial_map = _build_map(cfg, sequence, map_path)
    prims = aerial_map.primitives
    typer.echo(f"      {len(aerial_map)} patches, {int(prims.point_valid.sum())} points, {int(prims.line_valid.sum())} lines")
    map_png = plot_aerial_map(aerial_map, read_orthophoto(sequence), out / "aerial_map.png")
    typer.echo(f"plots: {preview}, {map_png}")
    typer.echo(f"demo finished in {time.perf_counter() - started:.1f} s; outputs in {out}")


def main() -> None:
    """Console-script entry point."""
    app()

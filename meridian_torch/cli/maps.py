"""Commands on maps: build an aerial map, draw one, map the ground side of a sequence into submaps."""

from __future__ import annotations

import json
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
    progress_bar,
)
from meridian_torch.config import MeridianConfig

__all__ = ["build_map", "build_map_with_progress", "map_ground_command", "show_map"]


def build_map_with_progress(cfg: MeridianConfig, ortho_path: Path, out: Path) -> Any:
    """Build the aerial map of `ortho_path` into `out` under a progress bar, printing its messages."""
    from meridian_torch.mapping.aerial_map import build_map_file
    from meridian_torch.runtime import resolve_runtime

    runtime = resolve_runtime(cfg.runtime)
    with progress_bar("building aerial map", "patch") as update:
        return build_map_file(ortho_path, out, cfg.aerial_map, cfg.perception, cfg.primitives,
                              device=runtime.device, progress=update, on_message=typer.echo)


@error_boundary
def build_map(
    ortho: Annotated[Path, typer.Argument(help="Orthophoto: a sequence folder, its aerial/ folder, a PNG/JPEG "
                                               "with its .json georeference, or a GeoTIFF.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Map file to write (.mtm).")],
    config: ConfigOption = None,
    set_: SetOption = None,
    workers: Annotated[int | None, typer.Option(
        min=1, help="Worker processes (CPU; default aerial_map.workers). With the classical back ends use "
                    "one per core: on 2 cores 2 processes built a 600 m x 600 m map 1.55x faster, the same map.")] = None,
    backend: Annotated[str | None, typer.Option(
        help="Engine describing the patches: local (processes on this machine) or ray (Ray actors, "
             "extra 'distributed'; default aerial_map.engine). The same map either way.")] = None,
    address: Annotated[str | None, typer.Option(
        help="With --backend ray: the Ray cluster to join (HEAD:6379); without it a local cluster with "
             "--workers CPUs is started.")] = None,
) -> None:
    """Turn an orthophoto into an aerial map of point and line primitives (resumable).

    The orthophoto is read patch by patch (a tiled GeoTIFF is never held whole). Finished patches
    are kept in OUT.parts/ while building: run the same command again after an interruption, on
    any engine, and it continues where it stopped.
    """
    if backend not in (None, "local", "ray"):
        raise typer.BadParameter(f"{backend!r}: expected local or ray", param_hint="--backend")
    overrides = [
        *([f"aerial_map.workers={workers}"] if workers else []),
        *([f"aerial_map.engine={backend}"] if backend else []),
        *([f"aerial_map.ray_address={json.dumps(address)}"] if address else []),  # quoted: YAML reads 1:20 as a number
    ]
    cfg = config_from_options(config, [*(set_ or []), *overrides])
    if address and cfg.aerial_map.engine != "ray":
        raise typer.BadParameter("an address is for the Ray engine: add --backend ray", param_hint="--address")
    started = time.perf_counter()
    aerial_map = build_map_with_progress(cfg, ortho, out)
    prims = aerial_map.primitives
    typer.echo(
        f"wrote {out}: {len(aerial_map)} patches, {int(prims.point_valid.sum())} points, "
        f"{int(prims.line_valid.sum())} lines ({time.perf_counter() - started:.1f} s)"
    )


@error_boundary
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


@error_boundary
def map_ground_command(
    sequence: Annotated[Path, typer.Argument(help="Sequence folder (RGB-D frames + odometry).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder (submaps.mts, plots/, run info).")],
    config: ConfigOption = None,
    set_: SetOption = None,
    plots: Annotated[bool, typer.Option(help="Write a PNG per submap to OUT/plots/.")] = True,
    overwrite: Annotated[bool, typer.Option(help="Replace an output folder that holds files.")] = False,
) -> None:
    """Map the ground side: frames -> tracked 3D segments -> 2D point/line submaps (odom frame).

    Writes OUT/submaps.mts (format: meridian_torch/io/submap_file.py) and, with --plots, one PNG
    per submap; when the sequence has groundtruth.tum, the PNG also shows the primitives over the
    orthophoto through the ground-truth pose. The outputs go into a temporary folder that replaces
    OUT only when complete.
    """
    from meridian_torch.io.atomic import atomic_directory
    from meridian_torch.mapping.ground_map import GroundMapper
    from meridian_torch.pipeline.ground_outputs import write_ground_map_folder
    from meridian_torch.pipeline.prepare import open_sequence, refuse_foreign_folder
    from meridian_torch.runtime import resolve_runtime

    refuse_foreign_folder(out, overwrite)
    cfg = config_from_options(config, set_)
    reader, ortho = open_sequence(cfg, sequence)
    mapper = GroundMapper.from_config(cfg, reader.camera, resolve_runtime(cfg.runtime), keep_geometries=plots)
    started = time.perf_counter()
    with interruptible(out), atomic_directory(out, overwrite=True) as tmp:
        with progress_bar("mapping ground", "frame") as update:
            submaps = mapper.map_sequence(reader, update)
        seconds = time.perf_counter() - started
        write_ground_map_folder(tmp, cfg, sequence, reader, ortho, mapper, submaps, plots=plots)
    duration = float(reader.frame_times[-1] - reader.frame_times[0])
    typer.echo(
        f"wrote {out / 'submaps.mts'}: {len(submaps)} submaps, "
        f"{sum(s.primitives.points_xy.shape[0] for s in submaps)} points, "
        f"{sum(s.primitives.line_endpoints.shape[0] for s in submaps)} lines from {len(reader)} frames "
        f"({seconds:.1f} s, {len(reader) / max(seconds, 1e-9):.1f} frames/s, "
        f"{duration / max(seconds, 1e-9):.2f}x real time)"
    )

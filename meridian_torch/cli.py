"""The `meridian-torch` command: a thin layer over the package with one error boundary.

Heavy modules (simulator, renderer, matplotlib) are imported inside the commands that use them.
"""

from __future__ import annotations

import errno
import functools
import json
import os
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager

# Idle OpenMP threads sleep instead of spinning: on a shared 2-core machine spinning threads made
# small torch ops 25-50x slower (measured); set before torch is first imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from pathlib import Path
from typing import Annotated, Any, Callable

import typer

from meridian_torch import __version__
from meridian_torch.config import CONFIG_DIR, MeridianConfig, config_key, dump_config, load_config
from meridian_torch.errors import CheckpointError, MeridianError, OutputExistsError

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
models_app = typer.Typer(help="List and verify local model files (models/manifest.yaml).", no_args_is_help=True)
app.add_typer(models_app, name="models")
convert_app = typer.Typer(help="Convert other recordings to a sequence folder (README, Formats).", no_args_is_help=True)
app.add_typer(convert_app, name="convert")

ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="YAML config file (default: configs/default.yaml).", dir_okay=False),
]
SetOption = Annotated[
    list[str] | None,
    typer.Option("--set", "-s", help="Override a config key, e.g. --set sim.seed=3 (repeatable)."),
]


# Operating-system errors that are the user's situation, not a bug: permissions, a full or
# read-only disk, something in the way. They get one line like our own errors.
_USER_OS_ERRORS = {errno.EACCES, errno.EPERM, errno.EEXIST, errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EISDIR,
                   errno.ENOTDIR, errno.ENOENT, errno.ENOTEMPTY}


@contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM (a job scheduler, `kill`, a robot's shutdown) unwinds like Ctrl-C, so the same
    clean-up runs: temporary folders are removed and outputs left as they were."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _error_boundary(command: Callable[..., Any]) -> Callable[..., Any]:
    """MeridianError and the user's OS errors (permission, disk full, file in the way) -> one line on
    stderr and exit code 1; Ctrl-C -> a line and exit code 130; anything else keeps its traceback."""

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            with _terminate_as_interrupt():
                return command(*args, **kwargs)
        except MeridianError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1) from None
        except OSError as exc:
            if exc.errno not in _USER_OS_ERRORS:
                raise
            where = f"{exc.filename}: " if exc.filename else ""
            typer.echo(f"error: {where}{exc.strerror or exc}", err=True)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            typer.echo("interrupted", err=True)
            raise typer.Exit(130) from None

    return wrapper


def _load(config: Path | None, overrides: list[str] | None) -> MeridianConfig:
    return load_config(config, overrides or [])


@contextmanager
def _progress(desc: str, unit: str) -> Iterator[Callable[[int, int], None]]:
    """A tqdm bar for the block; yields its `update(done, total)` callback and closes it on exit."""
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit=unit, dynamic_ncols=True)

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        yield update
    finally:
        bar.close()


def _converted(out: Path, counts: dict[str, int], max_dt: float, pose_source: str) -> None:
    typer.echo(f"wrote {out}: {counts['frames']} frames; skipped {counts['unpaired']} colour images without depth "
               f"within {max_dt} s and {counts['without_pose']} outside the {pose_source}")


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
    sequence: Annotated[Path, typer.Argument(help="Sequence folder (format: README, Formats).")],
    quick: Annotated[bool, typer.Option("--quick", help="Read image headers only (default: decode every image).")]
    = False,
) -> None:
    """Validate a sequence folder against the format and report every problem found (images, odometry
    coverage and gaps, orthophoto and georeference)."""
    from meridian_torch.io.sequence import check_sequence

    problems = check_sequence(sequence, quick=quick)
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
    with _progress("rendering frames", "frame") as update:
        summary = simulate_sequence(cfg.sim, out, device=runtime.device, overwrite=overwrite, progress=update)
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
    from meridian_torch.mapping.aerial_map import build_map_file
    from meridian_torch.runtime import resolve_runtime

    runtime = resolve_runtime(cfg.runtime)
    with _progress("building aerial map", "patch") as update:
        return build_map_file(ortho_path, out, cfg.aerial_map, cfg.perception, cfg.primitives,
                              device=runtime.device, progress=update, on_message=typer.echo)


@convert_app.command("kitti")
@_error_boundary
def convert_kitti_command(
    source: Annotated[Path, typer.Argument(help="KITTI odometry sequence folder: image_2/, velodyne/, calib.txt, "
                                                "times.txt.")],
    odometry: Annotated[Path, typer.Option(help="Poses in KITTI format, one per frame: poses/XX.txt (camera 0) or "
                                                "an estimate such as KISS-ICP's (lidar; add --odometry-frame lidar).")],
    ortho: Annotated[Path, typer.Option("--ortho", help="Orthophoto of the area: GeoTIFF, or PNG/JPEG with its .json "
                                                        "georeference.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Sequence folder to write (must not exist).")],
    odometry_frame: Annotated[str, typer.Option(help="Frame of the odometry poses: camera or lidar.")] = "camera",
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output folder.")] = False,
) -> None:
    """A KITTI odometry sequence -> a sequence folder (depth images from the lidar projected into camera 2)."""
    from meridian_torch.io.converters.kitti import convert_kitti

    with _progress("converting", "frame") as update:
        counts = convert_kitti(source, odometry, ortho, out, odometry_frame=odometry_frame, overwrite=overwrite,
                               progress=update)
    typer.echo(f"wrote {out}: {counts['frames']} frames")


@convert_app.command("rosbag")
@_error_boundary
def convert_rosbag_command(
    bags: Annotated[list[Path], typer.Argument(help="One recording: a ROS 1 .bag, a ROS 2 bag folder (sqlite3 or "
                                                    "MCAP) or the parts of a split bag.")],
    ortho: Annotated[Path, typer.Option("--ortho", help="Orthophoto of the area: GeoTIFF, or PNG/JPEG with its .json "
                                                        "georeference.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Sequence folder to write (must not exist).")],
    rgb_topic: Annotated[str | None, typer.Option(help="Colour image topic (Image or CompressedImage; default: the "
                                                       "only one, or the one named *color*).")] = None,
    depth_topic: Annotated[str | None, typer.Option(help="Depth image topic registered to the colour camera (16UC1 mm "
                                                         "or 32FC1 m; default: the one named *depth*).")] = None,
    camera_info_topic: Annotated[str | None, typer.Option(help="CameraInfo of the colour camera.")] = None,
    odometry_topic: Annotated[str | None, typer.Option(help="nav_msgs/Odometry topic: T_odom_base.")] = None,
    camera_at_base: Annotated[bool, typer.Option(help="Without a /tf_static chain from the odometry frame to the "
                                                      "camera: put the base at the camera (right for a level camera "
                                                      "only).")] = False,
    max_dt: Annotated[float, typer.Option(help="Largest colour-depth time difference paired, seconds.")] = 0.02,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output folder.")] = False,
) -> None:
    """A ROS 1 / ROS 2 bag -> a sequence folder (no ROS needed; camera extrinsics from /tf_static)."""
    from meridian_torch.io.converters.rosbag import convert_rosbag

    with _progress("converting", "frame") as update:
        counts = convert_rosbag(bags, ortho, out, rgb_topic=rgb_topic, depth_topic=depth_topic,
                                camera_info_topic=camera_info_topic, odometry_topic=odometry_topic,
                                camera_at_base=camera_at_base, max_dt_s=max_dt,
                                overwrite=overwrite, progress=update)
    _converted(out, counts, max_dt, "odometry")


@convert_app.command("tum-rgbd")
@_error_boundary
def convert_tum_rgbd_command(
    source: Annotated[Path, typer.Argument(help="TUM RGB-D sequence folder: rgb.txt, depth.txt, rgb/, depth/ and "
                                                "groundtruth.txt (camera poses, used as odometry).")],
    ortho: Annotated[Path, typer.Option("--ortho", help="Orthophoto of the area: GeoTIFF, or PNG/JPEG with its .json "
                                                        "georeference.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Sequence folder to write (must not exist).")],
    camera: Annotated[str, typer.Option(help="The benchmark camera whose calibration undistorts the images: fr1, "
                                             "fr2 or fr3 (rectified already).")] = "fr1",
    trajectory: Annotated[Path | None, typer.Option(help="Camera poses in TUM format to use as odometry instead of "
                                                         "groundtruth.txt (e.g. a visual odometry estimate).")] = None,
    max_dt: Annotated[float, typer.Option(help="Largest colour-depth time difference paired, seconds.")] = 0.02,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output folder.")] = False,
) -> None:
    """A TUM RGB-D benchmark sequence -> a sequence folder (frames paired by time, images undistorted)."""
    from meridian_torch.io.converters.tum_rgbd import convert_tum_rgbd

    with _progress("converting", "frame") as update:
        counts = convert_tum_rgbd(source, ortho, out, camera=camera, trajectory=trajectory, max_dt_s=max_dt,
                                  overwrite=overwrite, progress=update)
    _converted(out, counts, max_dt, "trajectory")


@app.command("build-map")
@_error_boundary
def build_map(
    ortho: Annotated[Path, typer.Argument(help="Orthophoto: a sequence folder, its aerial/ folder, a PNG/JPEG "
                                               "with its .json georeference, or a GeoTIFF.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Map file to write (.mtm).")],
    config: ConfigOption = None,
    set_: SetOption = None,
    workers: Annotated[int | None, typer.Option(
        min=1, help="Worker processes (CPU; default aerial_map.workers). With the classical back ends use "
                    "one per core: on 2 cores 2 processes built a 600 m x 600 m map 1.55x faster, the same map.")] = None,
) -> None:
    """Turn an orthophoto into an aerial map of point and line primitives (resumable).

    Finished patches are kept in OUT.parts/ while building: run the same command again after an
    interruption and it continues where it stopped.
    """
    cfg = _load(config, [*(set_ or []), *([f"aerial_map.workers={workers}"] if workers else [])])
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


@app.command("map-ground")
@_error_boundary
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
    import numpy as np

    from meridian_torch.geometry.se3 import se3_inverse
    from meridian_torch.io.atomic import atomic_directory
    from meridian_torch.io.run_info import write_run_info
    from meridian_torch.io.submap_file import save_ground_submaps
    from meridian_torch.mapping.ground_map import GroundMapper, ground_map_config_dict
    from meridian_torch.runtime import resolve_runtime

    _refuse_foreign_folder(out, overwrite)
    cfg = _load(config, set_)
    reader, ortho = _open_sequence(cfg, sequence)
    mapper = GroundMapper.from_config(cfg, reader.camera, resolve_runtime(cfg.runtime))
    started = time.perf_counter()
    with _interruptible(out), atomic_directory(out, overwrite=True) as tmp:
        with _progress("mapping ground", "frame") as update:
            submaps = mapper.map_sequence(reader, update)
        seconds = time.perf_counter() - started
        save_ground_submaps(submaps, tmp / "submaps.mts", config=ground_map_config_dict(cfg),
                            source={"sequence": str(sequence.resolve())},
                            descriptor_dim=mapper.describer.dim, global_descriptor_dim=mapper.global_describer.dim)
        write_run_info(tmp, cfg, "map-ground")
        if plots:
            from meridian_torch.evaluation.plots import plot_ground_submap

            for submap, geometry in zip(submaps, mapper.geometries, strict=True):
                T_world_odom = None
                if reader.groundtruth is not None and reader.groundtruth.covers(np.array([submap.time])):
                    T_world_odom = reader.groundtruth.interpolate(np.array([submap.time]))[0] @ se3_inverse(
                        submap.T_odom_base)
                plot_ground_submap(submap, tmp / "plots" / f"submap_{submap.index:03d}.png", geometry=geometry,
                                   ortho=ortho if reader.groundtruth is not None else None, T_world_odom=T_world_odom)
    duration = float(reader.frame_times[-1] - reader.frame_times[0])
    typer.echo(
        f"wrote {out / 'submaps.mts'}: {len(submaps)} submaps, "
        f"{sum(s.primitives.points_xy.shape[0] for s in submaps)} points, "
        f"{sum(s.primitives.line_endpoints.shape[0] for s in submaps)} lines from {len(reader)} frames "
        f"({seconds:.1f} s, {len(reader) / max(seconds, 1e-9):.1f} frames/s, "
        f"{duration / max(seconds, 1e-9):.2f}x real time)"
    )


def _refuse_foreign_folder(out: Path, overwrite: bool, command: str | None = None) -> None:
    """An output folder that holds files is refused without --overwrite, unless `command` is given
    and the folder is that command's own earlier output (its run.json says so)."""
    if not out.exists():
        return
    if out.is_dir() and not any(out.iterdir()):
        return
    if overwrite:
        return
    if command is not None and out.is_dir():
        from meridian_torch.io.run_info import RUN_FILE

        try:
            ours = json.loads((out / RUN_FILE).read_text()).get("command") == command
        except (OSError, ValueError, AttributeError):
            ours = False
        if ours:
            return
    raise OutputExistsError(f"{out}: already exists and holds files; pass --overwrite to replace it, or choose "
                            "another output folder")


@contextmanager
def _interruptible(out: Path) -> Iterator[None]:
    """Ctrl-C inside the block: say that `out` was left as it was (the block writes into a temporary
    folder that only replaces `out` when complete) and exit 130."""
    try:
        yield
    except KeyboardInterrupt:
        typer.echo(f"interrupted: nothing was written, {out} is as it was", err=True)
        raise typer.Exit(130) from None


def _run_key(cfg: MeridianConfig, aerial_map: Any, sequence: Path) -> str:
    """What a checkpoint must belong to: the resolved config, the map and the sequence's files."""
    from meridian_torch.pipeline.checkpoint import run_key

    ground = sequence / "ground"
    return run_key(dump_config(cfg), aerial_map.content_hash,
                   [ground / "frames.csv", ground / "odometry.tum", ground / "camera.json"])


def _open_sequence(cfg: MeridianConfig, sequence: Path) -> tuple[Any, Any]:
    """The sequence reader and its orthophoto, checked before any work: the folder's files, odometry
    gaps, the orthophoto and its georeference (a problem found here costs seconds, not a run)."""
    from meridian_torch.io.sequence import SequenceReader

    reader = SequenceReader(sequence)
    reader.require_odometry_without_gaps(cfg.ground_map.max_odometry_gap_s)
    return reader, reader.ortho()


def _load_or_build_map(cfg: MeridianConfig, map_path: Path, ortho_path: Path, ortho: Any = None) -> Any:
    """The aerial map at `map_path` (built from `ortho_path` first when missing); its config must
    match, and its georeference that of `ortho` (the sequence's orthophoto) when given."""
    from meridian_torch.io.map_file import MapFileError, georeference_mismatches, load_aerial_map
    from meridian_torch.mapping.aerial_map import map_config_dict

    map_config = map_config_dict(cfg.aerial_map, cfg.perception, cfg.primitives)
    if map_path.exists():
        typer.echo(f"using the aerial map {map_path}")
        aerial_map = load_aerial_map(map_path, expected_config=map_config)
        mismatches = [] if ortho is None else georeference_mismatches(aerial_map, ortho)
        if mismatches:
            raise MapFileError(f"{map_path}: built from another orthophoto than {ortho_path}'s ("
                               + "; ".join(mismatches) + "); rebuild it (choose another --map or delete this one)")
        return aerial_map
    typer.echo(f"building the aerial map {map_path} from {ortho_path}")
    return _build_map(cfg, ortho_path, map_path)


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


@app.command()
@_error_boundary
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

    _refuse_foreign_folder(out, overwrite)
    cfg = _load(config, set_)
    reader, ortho = _open_sequence(cfg, sequence)
    checkpoint_dir = out.parent / f".{out.name}.checkpoint"
    if resume and not checkpoint_dir.exists():
        raise CheckpointError(f"{checkpoint_dir}: no checkpoint to resume (it is kept only when a run was interrupted)")
    if not resume and checkpoint_dir.exists():
        typer.echo(f"discarding the checkpoint of an interrupted earlier run ({checkpoint_dir}; --resume continues it)")
        shutil.rmtree(checkpoint_dir)
    checkpoint = None
    try:
        with _interruptible(out), atomic_directory(out, overwrite=True) as tmp:
            write_run_info(tmp, cfg, "localize")
            aerial_map = _load_or_build_map(cfg, map_file, sequence, ortho)
            checkpoint = MatchingCheckpoint(checkpoint_dir, _run_key(cfg, aerial_map, sequence))
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


@app.command()
@_error_boundary
def evaluate(
    run_dir: Annotated[Path, typer.Argument(help="Output folder of `meridian-torch localize`.")],
    groundtruth: Annotated[Path, typer.Option("--groundtruth", "-g", help="Ground truth T_world_base (TUM).")],
    config: ConfigOption = None,
    set_: SetOption = None,
) -> None:
    """(Re-)compute metrics.json of a localization run against a ground-truth TUM file."""
    from meridian_torch.evaluation.trajectory_metrics import evaluate_run
    from meridian_torch.io.poses import read_tum

    cfg = _load(config, set_)
    metrics = evaluate_run(run_dir, read_tum(groundtruth), cfg.evaluation)
    _print_metrics(metrics)
    typer.echo(f"wrote {run_dir / 'metrics.json'}")


def _default_cache_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "meridian-torch"


@app.command()
@_error_boundary
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
    from meridian_torch.sim.preview import write_preview

    _refuse_foreign_folder(out, overwrite, command="demo")
    cfg = _load(config if config is not None else CONFIG_DIR / "demo.yaml", set_)
    started = time.perf_counter()
    # Cache keys are the configs that shape each product: any change renders or builds anew.
    sequence = (cache_dir or _default_cache_dir()) / "worlds" / f"{cfg.sim.name}-{config_key(cfg.sim.model_dump(mode='json'))}"
    with _interruptible(out), atomic_directory(out, overwrite=True) as tmp:
        write_run_info(tmp, cfg, "demo")
        if sequence.exists():
            typer.echo(f"[1/3] using the cached world {sequence}")
        else:
            typer.echo(f"[1/3] rendering the demo world into {sequence} (once)")
            summary = _simulate(cfg, sequence, overwrite=False)
            typer.echo(f"      {summary.frames} frames, {summary.path_length_m:.0f} m of driving")
        preview = write_preview(sequence, tmp / "preview.png")

        map_config = map_config_dict(cfg.aerial_map, cfg.perception, cfg.primitives)
        typer.echo("[2/3] aerial map")
        reader, ortho = _open_sequence(cfg, sequence)
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


@app.command("fit-vocabulary")
@_error_boundary
def fit_vocabulary(
    images: Annotated[list[Path], typer.Argument(help="RGB images (PNG/JPEG) representative of the domain.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Vocabulary file to write (.pt).")],
    seed: Annotated[int, typer.Option(help="Seed of the token subsampling and k-means initialization.")] = 0,
    tokens_per_image: Annotated[
        int | None, typer.Option(help="Random tokens kept per image (default: all), bounds memory.", min=1)
    ] = None,
    config: ConfigOption = None,
    set_: SetOption = None,
) -> None:
    """Fit the AnyLoc VLAD vocabulary (cosine k-means) of perception.global_descriptor.anyloc.

    Tokens are the configured backbone/layer/facet of IMAGES; the number of clusters is
    perception.global_descriptor.anyloc.num_clusters. Point vocabulary_path at OUT to use it.
    """
    import numpy as np
    import torch
    from PIL import Image, UnidentifiedImageError

    from meridian_torch.errors import ConfigError
    from meridian_torch.perception.factory import build_anyloc_facet
    from meridian_torch.perception.neural import anyloc
    from meridian_torch.runtime import resolve_runtime

    cfg = _load(config, set_)
    c = cfg.perception.global_descriptor.anyloc
    runtime = resolve_runtime(cfg.runtime)
    facet = build_anyloc_facet(c).to(device=runtime.device, dtype=runtime.dtype)

    def read_rgb(path: Path) -> torch.Tensor:
        try:
            with Image.open(path) as img:
                rgb = np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0
        except (OSError, UnidentifiedImageError) as e:
            raise ConfigError(f"{path}: not a readable image ({e})") from None
        return torch.from_numpy(rgb).permute(2, 0, 1)[None]

    started = time.perf_counter()
    try:
        with _progress("extracting tokens", "image") as update:
            centers = anyloc.fit_vocabulary(
                facet, (read_rgb(p) for p in images), num_clusters=c.num_clusters,
                resize_short_side_px=c.resize_short_side_px, seed=seed, tokens_per_image=tokens_per_image,
                progress=update, total=len(images),
            )
    except ValueError as e:
        raise ConfigError(f"fit-vocabulary: {e}") from None
    vocabulary = anyloc.Vocabulary(centers, architecture=c.architecture, layer=c.layer, facet=c.facet)
    anyloc.save_vocabulary(out, vocabulary)
    typer.echo(
        f"wrote {out}: {centers.shape[0]} centres of dimension {centers.shape[1]} from {len(images)} images "
        f"({time.perf_counter() - started:.1f} s)"
    )


@app.command("export")
@_error_boundary
def export_onnx(
    model: Annotated[str, typer.Argument(help="dinov2-dense, anyloc-facet, vlad-head, sam-encoder or sam-decoder.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="ONNX file to write.", dir_okay=False)],
    config: ConfigOption = None,
    set_: SetOption = None,
    exporter: Annotated[str | None, typer.Option(help="legacy or dynamo (default: the model's, legacy).")] = None,
) -> None:
    """Export a model as configured (weights, architecture, layer, vocabulary) to ONNX.

    The graph is written only after onnxruntime reproduces eager torch on two input sizes; the
    max abs differences are printed. dinov2-dense comes from perception.descriptor.dinov2,
    anyloc-facet and vlad-head from perception.global_descriptor.anyloc, sam-* from
    perception.aerial_segmenter.sam. Point perception.onnx.* at the files to run them onboard.
    """
    from meridian_torch.export.models import EXPORTABLE_MODELS, export_model

    if model not in EXPORTABLE_MODELS:
        raise typer.BadParameter(f"{model!r}; exportable: {', '.join(EXPORTABLE_MODELS)}", param_hint="MODEL")
    if exporter not in (None, "legacy", "dynamo"):
        raise typer.BadParameter(f"{exporter!r}; use legacy or dynamo", param_hint="--exporter")
    cfg = _load(config, set_)
    started = time.perf_counter()
    report = export_model(model, cfg.perception, out, exporter=exporter)  # type: ignore[arg-type]
    shapes = ", ".join(f"{name}{list(shape)}" for name, shape in report.inputs.items())
    checked = "; ".join(f"{list(c.input_shapes)}: {max(c.max_abs_diff.values()):.2g}" for c in report.checks)
    typer.echo(f"wrote {out} ({report.size_bytes / 2**20:.1f} MiB, {report.exporter} exporter, "
               f"{time.perf_counter() - started:.1f} s); inputs {shapes}")
    typer.echo(f"max abs difference to torch (tolerance {report.atol:g} + {report.rtol:g}*|x|): {checked}")


ManifestOption = Annotated[
    Path | None,
    typer.Option("--manifest", dir_okay=False, help="Model manifest, files beside it (default: the models folder's "
                 "manifest.yaml, else the shipped one; the models folder is $MERIDIAN_TORCH_MODELS, the checkout's "
                 "models/ or ~/.local/share/meridian-torch/models)."),
]


@models_app.command("list")
@_error_boundary
def models_list(manifest: ManifestOption = None) -> None:
    """List the known model files, whether each is present, and where to get it."""
    from meridian_torch.export.manifest import load_manifest

    m = load_manifest(manifest)
    for e in m.entries:
        present = "present" if (m.folder / e.file).is_file() else "missing"
        recorded = "sha256 recorded" if e.sha256 else "no hash recorded"
        typer.echo(f"{e.name:24s} {present:8s} {recorded:17s} {e.file}\n{'':24s} {e.architecture}; {e.license}\n"
                   f"{'':24s} {e.source}")
    typer.echo(f"{len(m.entries)} models in {m.path}; files go in {m.folder}")


@models_app.command("verify")
@_error_boundary
def models_verify(
    names: Annotated[list[str] | None, typer.Argument(help="Models to check (default: every file present).")] = None,
    manifest: ManifestOption = None,
    record: Annotated[bool, typer.Option(help="Write the sha256 of present files that have none into the "
                                              "manifest (recorded hashes are never overwritten).")] = False,
) -> None:
    """Hash model files and compare with the manifest: ok, mismatch, missing or no hash recorded.

    Exits 1 on a mismatch, or when a model named on the command line is missing.
    """
    from meridian_torch.export.manifest import load_manifest, verify_models

    m = load_manifest(manifest)
    results = verify_models(m, names or (), record=record)
    for r in results:
        if r.status == "missing" and not names:
            continue  # without names, only the files the user has are checked
        detail = {"mismatch": f"file {r.sha256} != manifest {r.entry.sha256}", "missing": f"no file {r.path}",
                  "no hash recorded": "run `models verify --record` to record it"}.get(r.status, r.sha256 or "")
        typer.echo(f"{r.entry.name:24s} {r.status:17s} {detail}")
    checked = [r for r in results if names or r.status != "missing"]
    if not checked:
        from meridian_torch.core.paths import shipped_dir

        typer.echo(f"no model files in {m.folder} (see {shipped_dir('models') / 'README.md'})")
    failed = [r.entry.name for r in checked if r.failed]
    if failed:
        typer.echo(f"error: {', '.join(failed)} failed verification", err=True)
        raise typer.Exit(1)


def main() -> None:
    """Console-script entry point."""
    app()

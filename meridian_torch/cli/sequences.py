"""Commands on sequence folders: check one, simulate one, convert other recordings into one."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import typer

from meridian_torch.cli.common import (
    ConfigOption,
    SetOption,
    config_from_options,
    error_boundary,
    progress_bar,
)
from meridian_torch.config import MeridianConfig

__all__ = ["check", "convert_kitti_command", "convert_rosbag_command", "convert_tum_rgbd_command", "simulate",
           "simulate_with_progress"]


@error_boundary
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


def simulate_with_progress(cfg: MeridianConfig, out: Path, overwrite: bool) -> Any:
    """Render the configured world into `out` under a progress bar, then its preview.png."""
    from meridian_torch.runtime import resolve_runtime
    from meridian_torch.sim.preview import write_preview
    from meridian_torch.sim.simulate import simulate_sequence

    runtime = resolve_runtime(cfg.runtime)
    with progress_bar("rendering frames", "frame") as update:
        summary = simulate_sequence(cfg.sim, out, device=runtime.device, overwrite=overwrite, progress=update)
    write_preview(out, out / "preview.png")
    return summary


@error_boundary
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

    cfg = config_from_options(config, set_)
    started = time.perf_counter()
    summary = simulate_with_progress(cfg, out, overwrite)
    write_run_info(out, cfg, "simulate")
    typer.echo(
        f"wrote {out}: {summary.frames} frames, {summary.path_length_m:.0f} m in {summary.duration_s:.0f} s "
        f"of driving ({time.perf_counter() - started:.1f} s); preview: {out / 'preview.png'}"
    )


def _converted(out: Path, counts: dict[str, int], max_dt: float, pose_source: str) -> None:
    typer.echo(f"wrote {out}: {counts['frames']} frames; skipped {counts['unpaired']} colour images without depth "
               f"within {max_dt} s and {counts['without_pose']} outside the {pose_source}")


@error_boundary
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

    with progress_bar("converting", "frame") as update:
        counts = convert_kitti(source, odometry, ortho, out, odometry_frame=odometry_frame, overwrite=overwrite,
                               progress=update)
    typer.echo(f"wrote {out}: {counts['frames']} frames")


@error_boundary
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

    with progress_bar("converting", "frame") as update:
        counts = convert_rosbag(bags, ortho, out, rgb_topic=rgb_topic, depth_topic=depth_topic,
                                camera_info_topic=camera_info_topic, odometry_topic=odometry_topic,
                                camera_at_base=camera_at_base, max_dt_s=max_dt,
                                overwrite=overwrite, progress=update)
    _converted(out, counts, max_dt, "odometry")


@error_boundary
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

    with progress_bar("converting", "frame") as update:
        counts = convert_tum_rgbd(source, ortho, out, camera=camera, trajectory=trajectory, max_dt_s=max_dt,
                                  overwrite=overwrite, progress=update)
    _converted(out, counts, max_dt, "trajectory")

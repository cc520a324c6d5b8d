"""TUM RGB-D benchmark sequences -> the sequence folder format (README, Formats).

Input: a TUM RGB-D sequence folder (`rgb.txt`, `depth.txt`: `timestamp path` per line;
`groundtruth.txt` or another trajectory in TUM format for the camera poses) and an orthophoto of
the area. Each colour image is paired with the depth image nearest in time, within `max_dt_s`
(TUM's own associate.py uses 0.02 s); colour images without a partner are skipped and counted.

Frames: TUM poses are those of the camera's optical centre; the base frame is placed at the
camera with x forward (the optical axis), y left and z up, so `T_base_camera` is a fixed rotation
and T_odom_base = T_odom_camera * T_base_camera^-1. The trajectory given is the odometry only:
TUM's motion-capture frame is not the orthophoto's world frame, so no groundtruth.tum is written.

Images are undistorted with the published calibration of the TUM camera (`fr1`, `fr2`; `fr3` is
already rectified), colour bilinearly and depth with nearest neighbours (no depth is invented
between surfaces). Depth keeps TUM's units: depth_scale 5000 per metre.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from meridian_torch.errors import MeridianError
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.converters.sync import T_BASE_OPTICAL, associate, undistort_maps
from meridian_torch.io.ortho import read_orthophoto
from meridian_torch.io.poses import read_tum
from meridian_torch.io.sequence import SequenceWriter

__all__ = ["TUM_CAMERAS", "TumCamera", "TumRgbdError", "convert_tum_rgbd", "read_file_list"]

TUM_DEPTH_SCALE = 5000.0  # depth PNG units per metre in the TUM RGB-D benchmark


class TumRgbdError(MeridianError):
    """A TUM RGB-D input is missing, malformed or inconsistent (the message names the file)."""


@dataclass(frozen=True)
class TumCamera:
    """Pinhole intrinsics at 640x480 and OpenCV distortion (k1, k2, p1, p2, k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float]


# Published calibration of the benchmark's Kinects (vision.in.tum.de/data/datasets/rgbd-dataset/file_formats).
TUM_CAMERAS = {
    "fr1": TumCamera(517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": TumCamera(520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": TumCamera(535.4, 539.2, 320.1, 247.6, (0.0, 0.0, 0.0, 0.0, 0.0)),
}


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """TUM `timestamp path` list (comments start with #) -> (times (N,), paths), sorted by time."""
    if not path.is_file():
        raise TumRgbdError(f"{path}: not found (a TUM RGB-D sequence has rgb.txt and depth.txt)")
    times, names = [], []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        try:
            t = float(parts[0])
        except ValueError:
            raise TumRgbdError(f"{path}:{number}: expected 'timestamp path', got {line.strip()!r}") from None
        if len(parts) < 2 or not np.isfinite(t):
            raise TumRgbdError(f"{path}:{number}: expected 'timestamp path', got {line.strip()!r}")
        times.append(t)
        names.append(parts[1])
    if not times:
        raise TumRgbdError(f"{path}: no entries")
    order = np.argsort(times, kind="stable")
    return np.asarray(times)[order], [names[i] for i in order]


def _read_image(path: Path, flags: int) -> np.ndarray:
    image = cv2.imread(str(path), flags)
    if image is None:
        raise TumRgbdError(f"{path}: missing or not a readable image")
    return image


def convert_tum_rgbd(
    source: Path,
    ortho: Path,
    out: Path,
    *,
    camera: str = "fr1",
    trajectory: Path | None = None,
    max_dt_s: float = 0.02,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, int]:
    """Write the sequence folder `out`; returns counts (frames written, colour images skipped).

    Streams one frame at a time (bounded memory); `out` appears only when complete.
    """
    if camera not in TUM_CAMERAS:
        raise TumRgbdError(f"camera {camera!r}: expected one of {', '.join(TUM_CAMERAS)}")
    if not max_dt_s > 0:
        raise TumRgbdError(f"max_dt_s must be positive, got {max_dt_s}")
    rgb_times, rgb_names = read_file_list(source / "rgb.txt")
    depth_times, depth_names = read_file_list(source / "depth.txt")
    trajectory = trajectory or source / "groundtruth.txt"
    if not trajectory.is_file():
        raise TumRgbdError(f"{trajectory}: not found (give the camera poses with --trajectory)")
    T_odom_camera = read_tum(trajectory)
    SequenceWriter.check_target(out, overwrite)
    aerial = read_orthophoto(ortho)

    pair = associate(rgb_times, depth_times, max_dt_s)
    covered = (rgb_times >= T_odom_camera.timestamps[0]) & (rgb_times <= T_odom_camera.timestamps[-1])
    use = np.flatnonzero((pair >= 0) & covered)
    if len(use) == 0:
        raise TumRgbdError(
            f"{source}: no colour image has a depth image within {max_dt_s} s and a pose in {trajectory}"
        )
    first = _read_image(source / rgb_names[use[0]], cv2.IMREAD_COLOR)
    height, width = first.shape[:2]
    cam = TUM_CAMERAS[camera]
    scale = width / 640.0  # the calibration is for 640x480
    model = CameraModel(width, height, cam.fx * scale, cam.fy * scale, cam.cx * scale, cam.cy * scale,
                        TUM_DEPTH_SCALE, T_BASE_OPTICAL)
    maps = undistort_maps(model.K, cam.distortion, width, height)
    odometry = Trajectory(T_odom_camera.timestamps, T_odom_camera.poses @ np.linalg.inv(T_BASE_OPTICAL))

    with SequenceWriter(out, model, overwrite=overwrite) as writer:
        for done, i in enumerate(use):
            rgb_path, depth_path = source / rgb_names[i], source / depth_names[pair[i]]
            bgr = _read_image(rgb_path, cv2.IMREAD_COLOR)
            depth = _read_image(depth_path, cv2.IMREAD_UNCHANGED)
            if bgr.shape[:2] != (height, width) or depth.shape != (height, width) or depth.dtype != np.uint16:
                raise TumRgbdError(
                    f"{depth_path if bgr.shape[:2] == (height, width) else rgb_path}: expected {width}x{height} "
                    f"(colour 8-bit, depth 16-bit), got colour {bgr.shape} and depth {depth.shape} {depth.dtype}"
                )
            if maps is not None:
                bgr = cv2.remap(bgr, *maps, cv2.INTER_LINEAR)
                depth = cv2.remap(depth, *maps, cv2.INTER_NEAREST)
            writer.add_frame(rgb_times[i], cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth / TUM_DEPTH_SCALE)
            if progress is not None:
                progress(done + 1, len(use))
        writer.set_odometry(odometry)
        writer.set_orthophoto(aerial)
        writer.set_meta({"source": f"TUM RGB-D {source.name}", "camera": camera, "trajectory": str(trajectory)})
    return {"frames": len(use), "unpaired": int((pair < 0).sum()), "without_pose": int(((pair >= 0) & ~covered).sum())}

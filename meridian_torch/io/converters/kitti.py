"""KITTI odometry sequences -> the sequence folder format (README, Formats).

Input: a KITTI odometry sequence folder (`image_2/` left colour images, `velodyne/` scans as
float32 x y z reflectance, `calib.txt` with P2 and Tr, `times.txt`), an odometry in KITTI's pose
format (12 numbers per line: the ground-truth `poses/XX.txt`, which are poses of camera 0, or an
estimate such as KISS-ICP's, which are poses of the lidar: say which with `odometry_frame`), and
an orthophoto of the area.

Depth, as the paper does: every scan is moved into the colour camera (Tr, then the rectified
offset of camera 2 in P2) and projected; each pixel keeps its nearest point (a z-buffer), the
rest have no depth. Frames: the base is placed at camera 0 with x forward, y left, z up, so odom
is camera 0's first pose turned to z up. No groundtruth.tum is written: KITTI's poses are not in
the orthophoto's world frame.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from meridian_torch.errors import MeridianError
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.converters.sync import T_BASE_OPTICAL
from meridian_torch.io.ortho import read_orthophoto
from meridian_torch.io.sequence import SequenceWriter

__all__ = ["KittiError", "convert_kitti", "lidar_depth_image", "read_calib", "read_kitti_poses"]

DEPTH_SCALE = 256.0  # depth PNG units per metre: 1/256 m steps up to 256 m (KITTI depth benchmark's choice)


class KittiError(MeridianError):
    """A KITTI input is missing, malformed or inconsistent (the message names the file)."""


def read_calib(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """calib.txt -> (P2 (3, 4) projection of camera 2, Tr (4, 4) velodyne -> camera 0)."""
    if not path.is_file():
        raise KittiError(f"{path}: not found (a KITTI odometry sequence has calib.txt)")
    rows = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if ":" not in line:
            continue
        key, values = line.split(":", 1)
        try:
            rows[key.strip()] = np.array([float(v) for v in values.split()])
        except ValueError:
            raise KittiError(f"{path}:{number}: {key.strip()} must be numbers") from None
    for key in ("P2", "Tr"):
        if key not in rows:
            raise KittiError(f"{path}: key {key} missing")
        if rows[key].shape != (12,) or not np.isfinite(rows[key]).all():
            raise KittiError(f"{path}: {key} must be 12 finite numbers, got {len(rows[key])}")
    Tr = np.eye(4)
    Tr[:3] = rows["Tr"].reshape(3, 4)
    return rows["P2"].reshape(3, 4), Tr


def read_kitti_poses(path: Path, n: int) -> np.ndarray:
    """KITTI pose file -> (n, 4, 4); one pose per frame, in frame order."""
    if not path.is_file():
        raise KittiError(f"{path}: not found")
    try:
        values = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise KittiError(f"{path}: not a KITTI pose file ({exc})") from None
    if values.shape[1] != 12 or len(values) != n or not np.isfinite(values).all():
        raise KittiError(f"{path}: expected {n} lines of 12 finite numbers (one pose per frame), got {values.shape}")
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3] = values.reshape(n, 3, 4)
    return poses


def lidar_depth_image(points_camera: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 3) points in a camera's optical frame -> (H, W) float32 depth (z), nearest point per pixel, 0 = none."""
    z = points_camera[:, 2]
    front = z > 0.1
    p = points_camera[front]
    u = np.floor(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(np.int64)
    v = np.floor(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, z = u[inside], v[inside], p[inside, 2]
    depth = np.full(height * width, np.inf, dtype=np.float64)
    np.minimum.at(depth, v * width + u, z)
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(height, width).astype(np.float32)


def convert_kitti(
    source: Path,
    odometry: Path,
    ortho: Path,
    out: Path,
    *,
    odometry_frame: str = "camera",
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, int]:
    """Write the sequence folder `out` (one frame per scan/image pair); returns {"frames": n}."""
    if odometry_frame not in ("camera", "lidar"):
        raise KittiError(f"odometry_frame {odometry_frame!r}: expected 'camera' (poses/XX.txt) or 'lidar' (KISS-ICP)")
    P2, T_cam0_velo = read_calib(source / "calib.txt")
    times_path = source / "times.txt"
    if not times_path.is_file():
        raise KittiError(f"{times_path}: not found")
    times = np.loadtxt(times_path, ndmin=1)
    images = sorted((source / "image_2").glob("*.png"))
    if len(images) != len(times):
        raise KittiError(f"{source / 'image_2'}: {len(images)} images for {len(times)} lines of {times_path}")
    poses = read_kitti_poses(odometry, len(times))
    SequenceWriter.check_target(out, overwrite)
    aerial = read_orthophoto(ortho)

    K = P2[:, :3]
    t_cam2_cam0 = np.linalg.solve(K, P2[:, 3])  # rectified: camera 2 = camera 0 shifted by this
    T_cam2_cam0 = np.eye(4)
    T_cam2_cam0[:3, 3] = t_cam2_cam0
    T_base_cam0 = T_BASE_OPTICAL
    if odometry_frame == "camera":
        T_odom_base = T_base_cam0 @ poses @ np.linalg.inv(T_base_cam0)
    else:  # lidar poses in the first scan's frame
        T_base_velo = T_base_cam0 @ T_cam0_velo
        T_odom_base = T_base_velo @ poses @ np.linalg.inv(T_base_velo)
    first = cv2.imread(str(images[0]), cv2.IMREAD_COLOR)
    if first is None:
        raise KittiError(f"{images[0]}: not a readable image")
    height, width = first.shape[:2]
    camera = CameraModel(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], DEPTH_SCALE,
                         T_base_cam0 @ np.linalg.inv(T_cam2_cam0))
    T_cam2_velo = T_cam2_cam0 @ T_cam0_velo

    with SequenceWriter(out, camera, overwrite=overwrite) as writer:
        for i, image_path in enumerate(images):
            scan_path = source / "velodyne" / f"{image_path.stem}.bin"
            if not scan_path.is_file():
                raise KittiError(f"{scan_path}: missing (every image needs its scan)")
            raw = np.fromfile(scan_path, dtype=np.float32)
            if raw.size % 4:
                raise KittiError(f"{scan_path}: size {raw.size * 4} bytes is not a multiple of 16 (x y z r float32)")
            xyz = raw.reshape(-1, 4)[:, :3].astype(np.float64)
            bgr = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
            if bgr is None or bgr.shape[:2] != (height, width):
                raise KittiError(f"{image_path}: not a readable {width}x{height} image")
            depth = lidar_depth_image(xyz @ T_cam2_velo[:3, :3].T + T_cam2_velo[:3, 3], K, width, height)
            writer.add_frame(float(times[i]), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth)
            if progress is not None:
                progress(i + 1, len(images))
        writer.set_odometry(Trajectory(times.astype(np.float64), T_odom_base))
        writer.set_orthophoto(aerial)
        writer.set_meta({"source": f"KITTI odometry {source.name}", "odometry": str(odometry),
                         "odometry_frame": odometry_frame})
    return {"frames": len(images)}

"""`meridian-torch convert kitti`: lidar depth images, a small synthetic KITTI tree, bad inputs."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.io.converters.kitti import DEPTH_SCALE, KittiError, convert_kitti, lidar_depth_image
from meridian_torch.io.converters.sync import T_BASE_OPTICAL
from meridian_torch.io.ortho import Orthophoto, write_orthophoto
from meridian_torch.io.sequence import SequenceReader, check_sequence

W, H = 64, 40
K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 19.5], [0.0, 0.0, 1.0]])
P2 = np.c_[K, K @ np.array([0.06, 0.0, 0.0])]  # camera 2 beside camera 0, as in KITTI
# Velodyne x forward, y left, z up -> camera 0 optical frame; camera 0 sits 0.3 m ahead of the lidar.
TR = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.1], [1.0, 0.0, 0.0, -0.3]])


def _depth_loop(points: np.ndarray, width: int, height: int) -> np.ndarray:
    depth = np.zeros((height, width), np.float32)
    for x, y, z in points:
        if z <= 0.1:
            continue
        u, v = int(np.floor(K[0, 0] * x / z + K[0, 2])), int(np.floor(K[1, 1] * y / z + K[1, 2]))
        if 0 <= u < width and 0 <= v < height and (depth[v, u] == 0 or z < depth[v, u]):
            depth[v, u] = z
    return depth


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.floats(-20, 20), st.floats(-20, 20), st.floats(-5, 60)), max_size=200))
def test_lidar_depth_keeps_the_nearest_point_per_pixel(points: list) -> None:
    pts = np.array(points, dtype=np.float64).reshape(-1, 3)
    np.testing.assert_array_equal(lidar_depth_image(pts, K, W, H), _depth_loop(pts, W, H))


def _pose(x: float, yaw: float) -> np.ndarray:
    """Camera 0 pose in its first frame: driven x metres forward (optical z), turned by yaw."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]  # about camera y (down): a turn in the ground plane
    T[:3, 3] = [0.0, 0.0, x]
    return T


@pytest.fixture()
def kitti_tree(tmp_path: Path) -> tuple[Path, Path, np.ndarray]:
    seq = tmp_path / "sequences" / "07"
    (seq / "image_2").mkdir(parents=True)
    (seq / "velodyne").mkdir()
    rng = np.random.default_rng(0)
    n = 4
    for i in range(n):
        cv2.imwrite(str(seq / "image_2" / f"{i:06d}.png"), rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
        wall = np.c_[np.full(300, 12.0 + i), rng.uniform(-6, 6, 300), rng.uniform(-1.5, 2, 300), np.zeros(300)]
        wall.astype(np.float32).tofile(seq / "velodyne" / f"{i:06d}.bin")
    calib = [f"P{k}: " + " ".join(map(str, (P2 if k == 2 else np.c_[K, np.zeros(3)]).ravel())) for k in range(4)]
    (seq / "calib.txt").write_text("\n".join(calib + ["Tr: " + " ".join(map(str, TR.ravel()))]) + "\n")
    (seq / "times.txt").write_text("\n".join(f"{0.1 * i:.6e}" for i in range(n)) + "\n")
    poses = np.stack([_pose(1.0 * i, 0.05 * i) for i in range(n)])
    (tmp_path / "07.txt").write_text("\n".join(" ".join(map(str, p[:3].ravel())) for p in poses) + "\n")
    write_orthophoto(tmp_path / "aerial", Orthophoto(np.zeros((100, 100, 3), np.uint8), 0.5, (-25.0, 25.0)))
    return seq, tmp_path, poses


def test_a_kitti_tree_converts_to_a_valid_sequence(kitti_tree, tmp_path: Path) -> None:
    seq, root, poses = kitti_tree
    assert convert_kitti(seq, root / "07.txt", root / "aerial", tmp_path / "out") == {"frames": 4}
    assert check_sequence(tmp_path / "out") == []
    reader = SequenceReader(tmp_path / "out")
    frame = reader[1]
    # The wall 13 m ahead of the lidar is 12.7 m ahead of camera 0 and camera 2.
    valid = frame.depth[frame.depth > 0]
    assert len(valid) > 100 and np.allclose(valid, 12.7, atol=1.0 / DEPTH_SCALE)
    # Odometry: the base drives along its own x axis and turns left by the camera's yaw (about -y_cam = z_up).
    T = reader.odometry.interpolate(reader.frame_times)
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-9)
    np.testing.assert_allclose(T[2][:3, 3], [2.0, 0.0, 0.0], atol=1e-9)
    yaw = np.arctan2(T[3][1, 0], T[3][0, 0])
    np.testing.assert_allclose(yaw, -0.15, atol=1e-9)  # +yaw about camera y (down) is a right turn
    # P2 with +fx * 0.06 in its last column puts camera 2 6 cm left of camera 0 (base +y), as in KITTI.
    np.testing.assert_allclose(reader.camera.T_base_camera[:3, 3], [0.0, 0.06, 0.0], atol=1e-12)
    np.testing.assert_allclose(reader.camera.T_base_camera[:3, :3], T_BASE_OPTICAL[:3, :3], atol=1e-12)


@pytest.mark.parametrize("case", ["calib key", "scan missing", "pose count", "odometry frame"])
def test_bad_inputs_name_the_problem(kitti_tree, tmp_path: Path, case: str) -> None:
    seq, root, _ = kitti_tree
    kwargs: dict = {}
    if case == "calib key":
        (seq / "calib.txt").write_text("P2: " + " ".join(map(str, P2.ravel())) + "\n")
        match = "calib.txt: key Tr missing"
    elif case == "scan missing":
        (seq / "velodyne" / "000002.bin").unlink()
        match = r"velodyne/000002\.bin: missing"
    elif case == "pose count":
        shutil.copy(root / "07.txt", tmp_path / "short.txt")
        lines = (tmp_path / "short.txt").read_text().splitlines()[:3]
        (root / "07.txt").write_text("\n".join(lines) + "\n")
        match = r"07\.txt: expected 4 lines"
    else:
        kwargs["odometry_frame"] = "imu"
        match = "odometry_frame 'imu'"
    with pytest.raises(KittiError, match=match):
        convert_kitti(seq, root / "07.txt", root / "aerial", tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists()


def test_lidar_odometry_gives_the_same_trajectory_as_camera_poses(kitti_tree, tmp_path: Path) -> None:
    """KISS-ICP-style lidar poses of the same motion give the same base odometry."""
    seq, root, poses = kitti_tree
    Tr = np.vstack([TR, [0.0, 0.0, 0.0, 1.0]])
    lidar = np.linalg.inv(Tr) @ poses @ Tr
    (root / "lidar.txt").write_text("\n".join(" ".join(map(str, p[:3].ravel())) for p in lidar) + "\n")
    convert_kitti(seq, root / "07.txt", root / "aerial", tmp_path / "camera")
    convert_kitti(seq, root / "lidar.txt", root / "aerial", tmp_path / "lidar", odometry_frame="lidar")
    a, b = SequenceReader(tmp_path / "camera"), SequenceReader(tmp_path / "lidar")
    np.testing.assert_allclose(b.odometry.poses, a.odometry.poses, atol=1e-9)

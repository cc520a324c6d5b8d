"""Planned drives, trajectory files, frame times and simulated odometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from meridian_torch.config.sim import (
    ClassRasterConfig,
    OdometryConfig,
    OrthoRenderConfig,
    TrajectoryConfig,
    WorldConfig,
)
from meridian_torch.geometry.se3 import se3_inverse
from meridian_torch.sim.classes import SimClass
from meridian_torch.sim.odometry import simulate_odometry
from meridian_torch.sim.ortho_render import render_orthophoto
from meridian_torch.sim.procedural import generate_world
from meridian_torch.sim.trajectory import frame_times, load_trajectory, plan_drive
from meridian_torch.sim.world import World

SHARED = Path(__file__).resolve().parents[2] / "shared"
MAPS = SHARED / "data" / "cross_view_slam_maps"
EVO = SHARED / "data" / "evo"
DRIVABLE = (SimClass.ROAD, SimClass.PARKING)


@pytest.fixture(scope="module")
def world() -> World:
    return generate_world(WorldConfig(size_m=(120.0, 120.0), road_spacing_m=50.0), seed=5)


@pytest.fixture(scope="module")
def drive(world: World):
    return plan_drive(world, TrajectoryConfig(length_m=400.0, speed_mps=5.0, odometry_rate_hz=20.0), seed=2)


def _classes_at(world: World, xy: np.ndarray) -> np.ndarray:
    cr = np.round(world.world_to_cell(xy)).astype(int)
    return world.class_map[cr[:, 1], cr[:, 0]]


def test_drive_stays_on_road_in_the_ortho(world: World, drive) -> None:
    ortho = render_orthophoto(world, OrthoRenderConfig(meters_per_pixel=0.3), seed=0)
    px = np.round(ortho.world_to_pixel(drive.positions[:, :2]))
    assert np.all((px >= 0) & (px < np.array(ortho.size_px)))
    on = np.isin(_classes_at(world, ortho.pixel_to_world(px)), DRIVABLE)
    assert on.mean() > 0.95


def test_drive_length_rate_heading_and_determinism(world: World, drive) -> None:
    assert drive.path_lengths()[-1] == pytest.approx(400.0, abs=1.0)
    np.testing.assert_allclose(np.diff(drive.timestamps), 0.05, atol=1e-9)
    step = np.diff(drive.positions[:, :2], axis=0)
    np.testing.assert_allclose(np.linalg.norm(step, axis=1), 0.25, atol=0.02)
    motion = np.arctan2(step[:, 1], step[:, 0])
    err = np.angle(np.exp(1j * (motion - drive.yaws[:-1])))
    assert np.abs(err).max() < np.radians(10)
    again = plan_drive(world, TrajectoryConfig(length_m=400.0), seed=2)
    np.testing.assert_array_equal(again.poses, drive.poses)
    other = plan_drive(world, TrajectoryConfig(length_m=400.0), seed=3)
    assert not np.allclose(other.positions[:100], drive.positions[:100])


def test_frame_times_inside_span(drive) -> None:
    t = frame_times(drive, 3.0)
    assert t[0] > drive.timestamps[0] and t[-1] < drive.timestamps[-1]
    np.testing.assert_allclose(np.diff(t), 1 / 3.0)
    assert len(frame_times(drive, 3.0, max_frames=7)) == 7


def test_perfect_odometry_is_relative_ground_truth(drive) -> None:
    odo = simulate_odometry(drive, OdometryConfig(kind="perfect"), seed=0)
    np.testing.assert_allclose(odo.poses[0], np.eye(4), atol=1e-12)
    gt_rel = se3_inverse(drive.poses[:-1]) @ drive.poses[1:]
    odo_rel = se3_inverse(odo.poses[:-1]) @ odo.poses[1:]
    np.testing.assert_allclose(odo_rel, gt_rel, atol=1e-9)


def test_drift_grows_with_distance(drive) -> None:
    gt = se3_inverse(drive.poses[:1]) @ drive.poses
    near, far = len(drive) // 10, len(drive) - 1
    errs = []
    for seed in range(8):
        odo = simulate_odometry(drive, OdometryConfig(kind="drift"), seed=seed)
        np.testing.assert_allclose(odo.poses[0], np.eye(4), atol=1e-12)
        e = np.linalg.norm(odo.positions - gt[:, :3, 3], axis=1)
        errs.append((e[near], e[far]))
    errs = np.array(errs)
    assert errs[:, 1].mean() > 3 * errs[:, 0].mean() > 0
    again = simulate_odometry(drive, OdometryConfig(kind="drift"), seed=0)
    np.testing.assert_array_equal(again.poses, simulate_odometry(drive, OdometryConfig(kind="drift"), seed=0).poses)


@pytest.mark.skipif(not (MAPS / "kitti0" / "class1.png").exists() or not (EVO / "KITTI_00_gt.txt").exists(),
                    reason="shared KITTI map data not available")
def test_kitti0_world_puts_aligned_ground_truth_on_road() -> None:
    from meridian_torch.sim.from_raster import world_from_class_raster

    raster = ClassRasterConfig(path=str(MAPS / "kitti0"), meters_per_pixel=1 / 3.0671, flip_vertical=True,
                               object_spacing_m=10.0,
                               classes={0: "grass", 1: "road", 3: "building", 4: "tree"})
    world = world_from_class_raster(WorldConfig(kind="class_raster", class_raster=raster, resolution_m=0.5), seed=0)
    assert any(o.class_id == SimClass.BUILDING for o in world.objects)
    assert any(o.class_id == SimClass.TREE for o in world.objects)
    assert world.road_centrelines and world.borders
    cfg = TrajectoryConfig(kind="file", path=str(EVO / "KITTI_00_gt.txt"), format="kitti",
                           kitti_times_path=str(EVO / "KITTI_00_gt_times.txt"),
                           alignment_path=str(MAPS / "kitti_gt_alignment.json"), alignment_map="kitti0")
    gt = load_trajectory(cfg, world)
    assert len(gt) == 4541
    assert np.isin(_classes_at(world, gt.positions[:, :2]), DRIVABLE).mean() > 0.9
    step = np.diff(gt.positions[:, :2], axis=0)
    moving = np.linalg.norm(step, axis=1) > 0.3
    err = np.angle(np.exp(1j * (np.arctan2(step[moving, 1], step[moving, 0]) - gt.yaws[:-1][moving])))
    assert np.median(np.abs(err)) < np.radians(5)  # base x axis points along the motion

    odo = simulate_odometry(gt, OdometryConfig(kind="file", path=str(EVO / "KITTI_00_ORB.txt"), format="kitti"), 0)
    assert len(odo) == len(gt)
    np.testing.assert_allclose(odo.poses[0], np.eye(4), atol=1e-9)
    perfect = simulate_odometry(gt, OdometryConfig(kind="perfect"), 0)
    err = np.linalg.norm(odo.positions[:, :2] - perfect.positions[:, :2], axis=1)
    assert np.median(err) < 30.0  # ORB-SLAM2 drifts by metres, not by hundreds of metres
    drive = plan_drive(world, TrajectoryConfig(length_m=500.0), seed=1)
    assert np.isin(_classes_at(world, drive.positions[:, :2]), DRIVABLE).mean() > 0.95

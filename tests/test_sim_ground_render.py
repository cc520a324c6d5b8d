"""Ground renderer against analytic pinhole geometry on hand-built worlds (flat ground + one box)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from meridian_torch.config.sim import CameraConfig, GroundRenderConfig
from meridian_torch.sim.camera import camera_model_from_config
from meridian_torch.sim.ground_render import NO_CLASS, GroundRenderer
from meridian_torch.sim.world import World

RES = 0.2
ORIGIN = (-50.0, 50.0)
N = 500  # 100 m x 100 m
CAM_Z = 1.2
# Box: x in [10, 12], y in [-1, 1], 2 m tall; all on cell boundaries of the raster.
BOX = (10.0, 12.0, -1.0, 1.0, 2.0)

NOISE_FREE = GroundRenderConfig(depth_noise_a=0.0, depth_noise_b=0.0, rgb_noise_std=0.0, haze_strength=0.0)


def _world(with_box: bool = True) -> World:
    height = np.zeros((N, N), np.float32)
    cls = np.zeros((N, N), np.uint8)
    inst = np.full((N, N), -1, np.int32)
    albedo = np.full((N, N, 3), 0.4, np.float32)
    wall = np.full((N, N, 3), 0.7, np.float32)
    if with_box:
        x0, x1, y0, y1, h = BOX
        c0, c1 = round((x0 - ORIGIN[0]) / RES), round((x1 - ORIGIN[0]) / RES)
        r0, r1 = round((ORIGIN[1] - y1) / RES), round((ORIGIN[1] - y0) / RES)
        height[r0:r1, c0:c1] = h
        cls[r0:r1, c0:c1] = 6
        inst[r0:r1, c0:c1] = 1
    return World(RES, ORIGIN, cls, height, albedo, wall, inst)


def _T_world_camera(camera, xyz=(0.0, 0.0, 0.0), yaw=0.0) -> np.ndarray:
    """Camera pose of a base at `xyz` with heading `yaw`, through the camera's mount."""
    T_world_base = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    T_world_base[:2, :2] = [[c, -s], [s, c]]
    T_world_base[:3, 3] = xyz
    return T_world_base @ camera.T_base_camera


def _camera(pitch_deg: float = 0.0, width: int = 320, height: int = 180):
    return camera_model_from_config(
        CameraConfig(width=width, height=height, hfov_deg=90.0, mount_xyz=(0.0, 0.0, CAM_Z),
                     mount_rpy_deg=(0.0, pitch_deg, 0.0))
    )


def test_camera_model_axes() -> None:
    cam = _camera(pitch_deg=10.0)
    R = cam.T_base_camera[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    z_opt = R[:, 2]  # optical axis in base: forward and 10 deg down
    assert np.allclose(z_opt, [math.cos(math.radians(10)), 0.0, -math.sin(math.radians(10))])
    assert np.allclose(R[:, 0], [0.0, -1.0, 0.0])  # image right = base right
    assert cam.fx == pytest.approx(160.0) and cam.cx == pytest.approx(159.5)


@pytest.mark.parametrize("pitch_deg", [0.0, 12.0])
def test_box_lands_on_projected_pixels_at_right_depth(pitch_deg: float) -> None:
    cam = _camera(pitch_deg)
    renderer = GroundRenderer(_world(), cam, NOISE_FREE)
    T = _T_world_camera(cam)
    classes, inst, depth = renderer.render_labels(T[None])
    box = inst[0] == 1

    # Front face x = 10 of the box, projected with the pinhole model.
    x0, _, y0, y1, h = BOX
    corners_w = np.array([[x0, y0, 0.0], [x0, y1, 0.0], [x0, y1, h], [x0, y0, h]])
    T_cw = np.linalg.inv(T)
    pc = corners_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv = np.stack([cam.fx * pc[:, 0] / pc[:, 2] + cam.cx, cam.fy * pc[:, 1] / pc[:, 2] + cam.cy], -1)

    # Signed distance (pixels) of every pixel centre to the convex projected quad, > 0 inside.
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    dist = np.full(u.shape, np.inf)
    e0, e1 = uv[1] - uv[0], uv[2] - uv[1]
    orient = np.sign(e0[0] * e1[1] - e0[1] * e1[0])
    for k in range(4):
        p, q = uv[k], uv[(k + 1) % 4]
        e = (q - p) / np.linalg.norm(q - p)
        d = orient * (e[0] * (v - p[1]) - e[1] * (u - p[0]))
        dist = np.minimum(dist, d)
    # The face's lower edge meets the ground (also rendered), so only its silhouette edges matter;
    # more than 1 px inside must be box, more than 1 px outside must not.
    assert box[dist > 1.0].all()
    assert not box[dist < -1.0].any()
    assert box.sum() > 100

    # Depth of interior pixels: intersection of the pixel ray with the plane x = 10.
    inner = dist > 1.0
    rays_c = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    rays_w = rays_c @ T[:3, :3].T
    z_true = (x0 - T[0, 3]) / rays_w[..., 0]
    err = np.abs(depth[0][inner] - z_true[inner])
    assert err.max() < 1e-3 * 10.0
    assert (classes[0][inner] == 6).all()


def test_pitched_camera_sees_flat_ground_at_analytic_depth() -> None:
    pitch = 15.0
    cam = _camera(pitch)
    cfg = NOISE_FREE.model_copy(update={"max_depth_m": 20.0, "render_distance_m": 40.0})
    renderer = GroundRenderer(_world(with_box=False), cam, cfg)
    T = _T_world_camera(cam, yaw=0.3)
    _, depth = renderer.render(T[None], seed=0)
    depth = depth[0]

    # Ray (x, y, 1) * z in the camera; pitched down by theta, its drop below the camera is
    # z * (sin(theta) + y cos(theta)), and it meets the ground when that equals CAM_Z.
    th = math.radians(pitch)
    y = (np.arange(cam.height) - cam.cy) / cam.fy
    drop = math.sin(th) + y * math.cos(th)
    z_true = np.where(drop > 0, CAM_Z / np.where(drop > 0, drop, 1.0), np.inf)
    # Horizontal range of a pixel's ground point: z * sqrt(1 + x^2 + y^2 - drop^2).
    x = (np.arange(cam.width) - cam.cx) / cam.fx
    ground_range = z_true[:, None] * np.sqrt(1.0 + x[None] ** 2 + y[:, None] ** 2 - drop[:, None] ** 2)

    seen = (z_true[:, None] <= cfg.max_depth_m) & (ground_range < cfg.render_distance_m * 0.999)
    seen = np.broadcast_to(seen, depth.shape)
    z_full = np.broadcast_to(z_true[:, None], depth.shape)
    rel = np.abs(depth[seen] - z_full[seen]) / z_full[seen]
    assert seen.sum() > 0.3 * depth.size
    assert rel.max() < 1e-4
    # Beyond the sensor range (still rendered in RGB) and sky: no depth.
    beyond = np.broadcast_to(z_true[:, None] > cfg.max_depth_m * 1.001, depth.shape)
    assert beyond.any() and (depth[beyond] == 0).all()
    sky = np.broadcast_to((drop <= 0)[:, None], depth.shape)
    assert sky.any() and (depth[sky] == 0).all()


def test_sky_has_no_depth_and_sky_colour() -> None:
    cam = _camera(-20.0)  # looking up: the top rows see only sky
    renderer = GroundRenderer(_world(), cam, NOISE_FREE)
    rgb, depth = renderer.render(_T_world_camera(cam)[None], seed=0)
    classes, _, _ = renderer.render_labels(_T_world_camera(cam)[None])
    assert (depth[0, :10] == 0).all()
    assert (classes[0, :10] == NO_CLASS).all()
    top = rgb[0, 0].astype(int)
    assert (top[:, 2] > top[:, 0]).all()  # blue sky


def test_same_seed_same_output_and_noise_present() -> None:
    cam = _camera(5.0)
    renderer = GroundRenderer(_world(), cam, GroundRenderConfig())
    T = np.stack([_T_world_camera(cam, yaw=y) for y in (0.0, 0.4)])
    rgb1, d1 = renderer.render(T, seed=7)
    rgb2, d2 = renderer.render(T, seed=7)
    rgb3, d3 = renderer.render(T, seed=8)
    assert np.array_equal(rgb1, rgb2) and np.array_equal(d1, d2)
    assert not np.array_equal(rgb1, rgb3) and not np.array_equal(d1, d3)
    _, _, clean = GroundRenderer(_world(), cam, NOISE_FREE).render_labels(T)
    valid = d1 > 0
    # Noise std a z^2 + b: at most a few sigma away from the clean depth.
    sigma = 0.002 * clean[valid] ** 2 + 0.005
    assert np.all(np.abs(d1[valid] - clean[valid]) < 6 * sigma)


def test_batch_equals_single_frames() -> None:
    cam = _camera(8.0)
    renderer = GroundRenderer(_world(), cam, NOISE_FREE.model_copy(update={"batch_size": 4}))
    T = np.stack([
        _T_world_camera(cam, xyz=(0.0, 0.0, 0.0), yaw=0.0),
        _T_world_camera(cam, xyz=(3.0, -4.0, 0.0), yaw=1.0),
        _T_world_camera(cam, xyz=(20.0, 5.0, 0.5), yaw=-2.5),
    ])
    rgb_b, d_b = renderer.render(T, seed=0)
    for k in range(len(T)):
        rgb_k, d_k = renderer.render(T[k : k + 1], seed=0)
        assert np.abs(rgb_b[k].astype(int) - rgb_k[0].astype(int)).max() <= 1
        assert np.allclose(d_b[k], d_k[0], rtol=1e-5, atol=1e-6)

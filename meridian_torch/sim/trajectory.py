"""Ground-truth drives T_world_base: planned on a world's road network or loaded from a file."""

from __future__ import annotations

import json
import math

import cv2
import networkx as nx
import numpy as np
from scipy.ndimage import gaussian_filter1d, map_coordinates

from meridian_torch.config.sim import TrajectoryConfig
from meridian_torch.errors import SimulationError
from meridian_torch.geometry.se3 import pose_from_xyz_yaw
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.poses import read_kitti, read_tum
from meridian_torch.sim.canvas import CAR_SIZE_M
from meridian_torch.sim.classes import SimClass
from meridian_torch.sim.ground_truth import ground_layer
from meridian_torch.sim.roads import road_graph
from meridian_torch.sim.world import World

__all__ = ["plan_drive", "load_trajectory", "frame_times", "kitti_to_base"]

TURN_SMOOTH_M = 1.0  # final Gaussian smoothing of the joined path (removes curvature jumps)
ROBOT_HALF_WIDTH_M = 0.6


def plan_drive(world: World, cfg: TrajectoryConfig, seed: int) -> Trajectory:
    """Drive about `cfg.length_m` in the right-hand lane along the road network at `cfg.speed_mps`,
    sampled at `cfg.odometry_rate_hz`: a random walk over junctions that never turns back
    unless at a dead end, with smoothed corners."""
    rng = np.random.default_rng(seed)
    g = road_graph(world.road_centrelines)
    comp = max(nx.connected_components(g), key=lambda c: g.subgraph(c).size(weight="length"))
    g = g.subgraph(comp)
    widths = _road_half_widths(world, g)
    edges = list(g.edges(keys=True))
    lengths = np.array([g.edges[e]["length"] for e in edges])
    edge = edges[rng.choice(len(edges), p=lengths / lengths.sum())]
    node = edge[int(rng.integers(2))] if min(g.degree(edge[0]), g.degree(edge[1])) > 1 else \
        min(edge[:2], key=g.degree)  # start driving away from a dead end
    lanes: list[tuple[np.ndarray, float]] = []  # right-hand lane polylines and their road half-widths
    total = 0.0
    while total < cfg.length_m + 2 * TURN_SMOOTH_M:
        data = g.edges[edge]
        xy = data["xy"] if data["start"] == node else data["xy"][::-1]
        lanes.append((_offset_right(_resample(xy, 0.25), _lane_offset(widths[edge])), widths[edge]))
        total += max(data["length"] - 2 * widths[edge], 0.0)
        node = edge[1] if node == edge[0] else edge[0]
        came_by = (frozenset(edge[:2]), edge[2])
        options = [(node, nbr, key) for nbr, keyed in g[node].items() for key in keyed
                   if (frozenset((node, nbr)), key) != came_by]
        # At a junction take any road but the one we came by, avoiding dead ends if possible;
        # at a dead end turn back.
        through = [e for e in options if g.degree(e[1]) > 1]
        if options:
            pool = through or options
            edge = pool[int(rng.integers(len(pool)))]
    path = _resample(_join_lanes(lanes), 0.25)
    path = _resample(gaussian_filter1d(path, TURN_SMOOTH_M / 0.25, axis=0, mode="nearest"), 0.25)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    s_end = min(cfg.length_m, s[-1] - 2 * TURN_SMOOTH_M)
    times = np.arange(0.0, s_end / cfg.speed_mps, 1.0 / cfg.odometry_rate_hz)
    q = times * cfg.speed_mps
    heading = np.unwrap(np.arctan2(*np.gradient(path, axis=0).T[::-1]))
    xy = np.stack([np.interp(q, s, path[:, 0]), np.interp(q, s, path[:, 1])], axis=1)
    yaw = np.interp(q, s, heading)
    return _on_ground(world, times, xy, yaw)


def _join_lanes(lanes: list[tuple[np.ndarray, float]]) -> np.ndarray:
    """Concatenate lane polylines; each junction is crossed by a cubic Hermite curve from the
    lane end to the next lane start, both cut back by the wider road's half-width, so that
    turns are arcs around the kerb corner rather than cuts across it."""
    cut = [max(a[1], b[1]) + 0.5 for a, b in zip(lanes[:-1], lanes[1:])]
    parts: list[np.ndarray] = []
    for i, (lane, _) in enumerate(lanes):
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(lane, axis=0), axis=1))])
        lo = min(cut[i - 1], along[-1] / 2.5) if i > 0 else 0.0
        hi = along[-1] - (min(cut[i], along[-1] / 2.5) if i < len(cut) else 0.0)
        piece = lane[(along >= lo) & (along <= hi)]
        if len(piece) < 2:
            continue
        if parts:
            parts.append(_hermite(parts[-1], piece))
        parts.append(piece)
    return np.concatenate(parts)


def _hermite(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Cubic Hermite points strictly between the end of `before` and the start of `after`."""
    p0, p1 = before[-1], after[0]
    t0 = before[-1] - before[max(len(before) - 8, 0)]
    t1 = after[min(7, len(after) - 1)] - after[0]
    t0 /= max(np.linalg.norm(t0), 1e-9)
    t1 /= max(np.linalg.norm(t1), 1e-9)
    d = max(float(np.linalg.norm(p1 - p0)), 0.5)
    u = np.linspace(0, 1, max(int(d / 0.1), 4))[1:-1, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    return h00 * p0 + h10 * d * t0 + h01 * p1 + h11 * d * t1


def _road_half_widths(world: World, g: nx.MultiGraph) -> dict[tuple, float]:
    """Half the road width per edge, from the road/parking cells around its centreline."""
    drivable = np.isin(world.class_map, [SimClass.ROAD, SimClass.PARKING, SimClass.CAR]).astype(np.uint8)
    dist = cv2.distanceTransform(drivable, cv2.DIST_L2, 5) * world.resolution_m
    out = {}
    for u, v, k, d in g.edges(keys=True, data=True):
        cr = world.world_to_cell(d["xy"])
        vals = map_coordinates(dist, [cr[:, 1], cr[:, 0]], order=1, mode="nearest")
        out[(u, v, k)] = out[(v, u, k)] = float(np.median(vals)) if len(vals) else 0.0
    return out


def _lane_offset(half_width: float) -> float:
    """Right-hand lane centre, keeping clear of cars parked along the kerb."""
    return float(np.clip(min(half_width / 2, half_width - CAR_SIZE_M[1] - 0.4 - ROBOT_HALF_WIDTH_M), 0.0, None))


def _offset_right(xy: np.ndarray, offset: float) -> np.ndarray:
    t = np.gradient(xy, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
    return xy + offset * np.stack([t[:, 1], -t[:, 0]], axis=1)


def _resample(path: np.ndarray, step: float) -> np.ndarray:
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    keep = np.concatenate([[True], np.diff(s) > 1e-9])
    s, path = s[keep], path[keep]
    q = np.arange(0.0, s[-1], step)
    return np.stack([np.interp(q, s, path[:, 0]), np.interp(q, s, path[:, 1])], axis=1)


def _on_ground(world: World, times: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> Trajectory:
    """Planar poses at the terrain height under each position (objects ignored)."""
    _, ground_h = ground_layer(world)
    cr = world.world_to_cell(xy)
    z = map_coordinates(ground_h, [cr[:, 1], cr[:, 0]], order=1, mode="nearest")
    return Trajectory(times, pose_from_xyz_yaw(np.column_stack([xy, z]), yaw))


def kitti_to_base(traj: Trajectory) -> Trajectory:
    """KITTI camera poses (x right, y down, z forward, in the first camera frame) -> gravity-
    aligned base poses: x = camera z, y = -camera x, z = -camera y, yaw from the camera heading."""
    T = traj.poses
    xyz = np.stack([T[:, 2, 3], -T[:, 0, 3], -T[:, 1, 3]], axis=1)
    yaw = np.arctan2(-T[:, 0, 2], T[:, 2, 2])
    return Trajectory(traj.timestamps, pose_from_xyz_yaw(xyz, yaw))


def load_trajectory(cfg: TrajectoryConfig, world: World) -> Trajectory:
    """T_world_base from a TUM file (already in the world frame) or a KITTI file.

    KITTI poses land in the world through `cfg.alignment_path`/`cfg.alignment_map` when given
    (a kitti_gt_alignment.json similarity into the class raster's stored pixels, with rows
    counted from the south edge if `cfg.alignment_y_up`), else the world is the first base frame.
    """
    if cfg.path is None:
        raise SimulationError("trajectory kind 'file' needs a path")
    if cfg.format == "tum":
        return read_tum(cfg.path)
    raw = read_kitti(cfg.path, cfg.kitti_times_path)
    if cfg.alignment_path is None:
        base = kitti_to_base(raw)
        return _on_ground(world, base.timestamps, base.positions[:, :2], base.yaws)
    try:
        maps = json.loads(open(cfg.alignment_path, encoding="utf-8").read())["maps"]
        a = maps[cfg.alignment_map]
        s, th, tx, ty = float(a["s_px_per_m"]), math.radians(float(a["theta_deg"])), float(a["tx_px"]), float(a["ty_px"])
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise SimulationError(f"{cfg.alignment_path}: no usable alignment {cfg.alignment_map!r}: {exc}") from exc
    T = raw.poses
    c, sn = math.cos(th), math.sin(th)

    def to_px(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return s * (c * x + sn * z), s * (-sn * x + c * z)

    col, row = to_px(T[:, 0, 3], T[:, 2, 3])
    col, row = col + tx, row + ty
    dcol, drow = to_px(T[:, 0, 2], T[:, 2, 2])
    x = world.origin_xy[0] + (col + 0.5) / s
    if cfg.alignment_y_up:  # stored row 0 is the south edge of the world
        y = world.extent_m[2] + (row + 0.5) / s
        yaw = np.arctan2(drow, dcol)
    else:
        y = world.origin_xy[1] - (row + 0.5) / s
        yaw = np.arctan2(-drow, dcol)
    return _on_ground(world, raw.timestamps, np.stack([x, y], axis=1), yaw)


def frame_times(traj: Trajectory, frame_rate_hz: float, max_frames: int | None = None) -> np.ndarray:
    """Camera frame timestamps at `frame_rate_hz`, strictly inside the trajectory's time span."""
    t0, t1 = float(traj.timestamps[0]), float(traj.timestamps[-1])
    n = int(math.floor((t1 - t0) * frame_rate_hz + 0.5 - 1e-9))
    times = t0 + (np.arange(max(n, 0)) + 0.5) / frame_rate_hz
    times = times[times < t1]
    if max_frames is not None:
        times = times[:max_frames]
    if len(times) == 0:
        raise SimulationError(f"the trajectory ({t1 - t0:.2f} s) is too short for one frame at {frame_rate_hz} Hz")
    return times

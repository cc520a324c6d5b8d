"""Simulate a whole sequence folder: world, orthophoto, drive, odometry, RGB-D frames, ground truth."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from meridian_torch import __version__
from meridian_torch.config.sim import SimConfig
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.io.sequence import SequenceWriter
from meridian_torch.sim.camera import camera_model_from_config
from meridian_torch.sim.from_raster import world_from_class_raster
from meridian_torch.sim.ground_render import GroundRenderer
from meridian_torch.sim.ground_truth import save_ground_truth
from meridian_torch.sim.odometry import simulate_odometry
from meridian_torch.sim.ortho_render import render_orthophoto
from meridian_torch.sim.procedural import generate_world
from meridian_torch.sim.trajectory import frame_times, load_trajectory, plan_drive
from meridian_torch.sim.world import World

__all__ = ["SimulationSummary", "build_world", "render_world_orthophoto", "simulate_sequence", "GROUND_TRUTH_DIR"]

GROUND_TRUTH_DIR = "sim"  # inside the sequence folder: the world's objects, borders and rasters


@dataclass(frozen=True)
class SimulationSummary:
    path: Path
    frames: int
    duration_s: float
    path_length_m: float
    world_extent_m: tuple[float, float, float, float]


def _stage_seeds(seed: int) -> dict[str, int]:
    # Independent streams per stage, so changing e.g. the camera never changes the world.
    names = ("world", "ortho", "trajectory", "odometry", "render")
    states = np.random.SeedSequence(seed).generate_state(len(names))
    return {name: int(s) for name, s in zip(names, states)}


def build_world(cfg: SimConfig) -> World:
    seed = _stage_seeds(cfg.seed)["world"]
    if cfg.world.kind == "class_raster":
        return world_from_class_raster(cfg.world, seed)
    return generate_world(cfg.world, seed)


def render_world_orthophoto(cfg: SimConfig) -> Orthophoto:
    """Only the orthophoto of `cfg`'s world (as `simulate_sequence` renders it), e.g. an outdated variant."""
    return render_orthophoto(build_world(cfg), cfg.ortho, _stage_seeds(cfg.seed)["ortho"])


def simulate_sequence(
    cfg: SimConfig,
    out: Path,
    *,
    device: torch.device | str = "cpu",
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> SimulationSummary:
    """Render `cfg` into the sequence folder `out` (written atomically).

    `progress(done, total)` is called after every rendered batch of frames.
    """
    SequenceWriter.check_target(out, overwrite)
    seeds = _stage_seeds(cfg.seed)
    world = build_world(cfg)
    ortho = render_orthophoto(world, cfg.ortho, seeds["ortho"])
    if cfg.trajectory.kind == "file":
        T_world_base = load_trajectory(cfg.trajectory, world)
    else:
        T_world_base = plan_drive(world, cfg.trajectory, seeds["trajectory"])
    times = frame_times(T_world_base, cfg.trajectory.frame_rate_hz, cfg.trajectory.max_frames)
    T_odom_base = simulate_odometry(T_world_base, cfg.odometry, seeds["odometry"])
    camera = camera_model_from_config(cfg.camera)
    renderer = GroundRenderer(world, camera, cfg.render, device=device)

    batch = cfg.render.batch_size
    with SequenceWriter(out, camera, overwrite=overwrite) as writer:
        writer.set_orthophoto(ortho)
        writer.set_odometry(T_odom_base)
        writer.set_groundtruth(Trajectory(times, T_world_base.interpolate(times)))
        for start in range(0, len(times), batch):
            stamps = times[start : start + batch]
            T_world_camera = T_world_base.interpolate(stamps) @ camera.T_base_camera
            rgb, depth = renderer.render(T_world_camera, seed=seeds["render"] + start)
            for stamp, rgb_i, depth_i in zip(stamps, rgb, depth):
                writer.add_frame(float(stamp), rgb_i, depth_i)
            if progress is not None:
                progress(min(start + batch, len(times)), len(times))
        save_ground_truth(world, writer.extra_dir / GROUND_TRUTH_DIR)
        writer.set_meta(
            {
                "name": cfg.name,
                "source": f"meridian-torch {__version__} simulator",
                "notes": f"seed {cfg.seed}; world {cfg.world.kind}; odometry {cfg.odometry.kind}",
            }
        )
    lengths = T_world_base.path_lengths()
    return SimulationSummary(
        path=Path(out),
        frames=len(times),
        duration_s=float(times[-1] - times[0]),
        path_length_m=float(np.interp(times[-1], T_world_base.timestamps, lengths)
                            - np.interp(times[0], T_world_base.timestamps, lengths)),
        world_extent_m=world.extent_m,
    )

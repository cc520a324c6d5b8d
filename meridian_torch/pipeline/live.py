"""Live localization on a robot: frames in one at a time (RGB, depth, odometry pose, timestamp, as
from a ROS callback), the current `T_world_base` with its covariance out.

    live = LiveLocalizer(aerial_map, cfg, camera, runtime)
    for rgb, depth, T_odom_base, t in frames:            # e.g. in a ROS subscriber
        estimate = live.add_frame(rgb, depth, T_odom_base, t)
        if estimate.localized:
            publish(estimate.T_world_base, estimate.covariance)
    result = live.finish()                               # the final offline pass (optional)

Frames go through the ground mapper (those due at `ground_map.mapping_rate_hz`; the others only
carry odometry); each submap it completes is localized at once (stamped with the time of the
frame that completed it). The perception models are those of the config
(`perception.ground_engine: onnx` runs them in onnxruntime). A sequence folder fed through this
class frame by frame gives the same submaps, online estimates and final trajectory as
`localize_sequence` with `ground_map.batch_size: 1` (a test checks it); larger batches segment
frames together and only delay when a submap's result becomes available.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from meridian_torch.backend.localizer import Localizer
from meridian_torch.backend.results import LocalizationResult, LocalizerEvent, Matcher
from meridian_torch.config import MeridianConfig
from meridian_torch.core.timing import stage
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.sequence import Frame
from meridian_torch.mapping.ground_map import GroundMapper, PerceivedFrames
from meridian_torch.matching.place_recognition import reads_global_descriptors
from meridian_torch.runtime import Runtime
from meridian_torch.types import AerialMap, GroundSubmap

__all__ = ["LiveEstimate", "LiveLocalizer"]


@dataclass(frozen=True)
class LiveEstimate:
    """The localizer's answer after a frame."""

    time: float  # the frame's timestamp
    T_world_base: np.ndarray | None  # (4, 4) world (the orthophoto's CRS, metres), None before the fix
    covariance: np.ndarray | None  # (3, 3) of (x, y, yaw) in world axes (m^2, rad^2), None before the fix
    state: Literal["pre", "post"]  # "post": a global fix was committed
    events: tuple[LocalizerEvent, ...]  # the submaps localized on this call

    @property
    def localized(self) -> bool:
        return self.T_world_base is not None


class LiveLocalizer:
    """Online localization of one drive, frame by frame (frames must come in time order).

    Args:
        aerial_map: the aerial map of the area (`meridian-torch build-map`).
        cfg: the full config (perception, ground mapping, matching, back end).
        camera: the RGB-D camera (intrinsics, image size, T_base_camera).
        runtime: device and dtype (`meridian_torch.runtime.resolve_runtime(cfg.runtime)`).
        seed: seeds matching and CLIPPER (default `cfg.matching.particles.seed`).
        matcher: the matching function (default `match_submap`; e.g. a `MatchingCheckpoint`).
    """

    def __init__(
        self,
        aerial_map: AerialMap,
        cfg: MeridianConfig,
        camera: CameraModel,
        runtime: Runtime,
        *,
        seed: int | None = None,
        matcher: Matcher | None = None,
    ) -> None:
        self.camera = camera
        # frame descriptors only when place recognition on this map reads them
        reads = reads_global_descriptors(cfg.matching.place_recognition, len(aerial_map), aerial_map.global_descriptor_backend)
        self.mapper = GroundMapper.from_config(cfg, camera, runtime, frame_descriptors=reads)
        # matching runs where the map's primitives are: on the runtime's device
        self.localizer = Localizer(aerial_map.to(runtime.device), cfg, seed=seed, matcher=matcher, online_covariance=cfg.backend.covariance)
        self.submaps: list[GroundSubmap] = []
        self.mapping_seconds = 0.0  # wall time in the ground mapper so far
        self._n_frames = 0

    def add_frame(self, rgb: np.ndarray, depth: np.ndarray, T_odom_base: np.ndarray, timestamp: float) -> LiveEstimate:
        """One frame: rgb (H, W, 3) uint8, depth (H, W) metres along the optical axis (0 or NaN =
        none), T_odom_base (4, 4) the odometry pose at `timestamp` (seconds, after the last frame's)."""
        frame = Frame(self._n_frames, float(timestamp), np.asarray(rgb), np.asarray(depth, dtype=np.float32),
                      np.asarray(T_odom_base, dtype=np.float64))
        return self.add_frames([frame])

    def add_frames(self, frames: Sequence[Frame]) -> LiveEstimate:
        """Several frames at once (those due segmented as one batch); the estimate is that after
        the last."""
        if not frames:
            raise ValueError("add_frames needs at least one frame")
        for frame in frames:
            self._check(frame)
        mapped, skipped = self.mapper.split_due(frames)
        skipped_times = np.array([f.timestamp for f in skipped], dtype=np.float64)
        skipped_poses = np.array([f.T_odom_base for f in skipped], dtype=np.float64).reshape(-1, 4, 4)
        if not mapped:
            return self.add_odometry(skipped_times, skipped_poses)
        started = time.perf_counter()
        with stage("ground mapping"):
            batch = self.mapper.perceive(mapped)
        self.mapping_seconds += time.perf_counter() - started
        return self.add_perceived(batch, skipped=(skipped_times, skipped_poses))

    def add_perceived(
        self, batch: PerceivedFrames, *, skipped: tuple[np.ndarray, np.ndarray] | None = None
    ) -> LiveEstimate:
        """Frames the mapper already perceived (`GroundMapper.perceive`, e.g. one batch ahead in
        another thread, `perceived_batches`); the estimate is that after the last. `skipped`:
        (times (K,), T_odom_base (K, 4, 4)) of frames since the previous call that were not due
        (`GroundMapper.due`); they reach the localizer in time order with the batch's."""
        times, T_odom_base = batch.times, batch.T_odom_base
        if skipped is not None and len(skipped[0]):
            times = np.concatenate([skipped[0], times])
            T_odom_base = np.concatenate([skipped[1], T_odom_base])
            order = np.argsort(times, kind="stable")
            times, T_odom_base = times[order], T_odom_base[order]
        self.localizer.add_frames(times, T_odom_base)
        started = time.perf_counter()
        with stage("ground mapping"):
            new = self.mapper.integrate(batch)
        self.mapping_seconds += time.perf_counter() - started
        self._n_frames += len(times)
        return self._localize(new, float(times[-1]))

    def add_odometry(self, frame_times: np.ndarray, T_odom_base: np.ndarray) -> LiveEstimate:
        """Frames that are not mapped (not due, `GroundMapper.due`): their (K,) times and (K, 4, 4)
        odometry poses only, in time order; the estimate is that after the last."""
        self.localizer.add_frames(frame_times, T_odom_base)
        self._n_frames += len(frame_times)
        return self._localize([], float(self.localizer.frame_times[-1]))

    def finish(self) -> LocalizationResult:
        """End of the drive: the last submap, then the final offline pass over every frame (the
        final trajectory, its covariances and the sanity gate; see `Localizer.finalize`)."""
        started = time.perf_counter()
        with stage("ground mapping"):
            last = self.mapper.finish()
        self.mapping_seconds += time.perf_counter() - started
        if last:
            self._localize(last, float(self.localizer.frame_times[-1]))
        with stage("final pass"):
            return self.localizer.finalize()

    def _localize(self, new: list[GroundSubmap], available_time: float) -> LiveEstimate:
        events = []
        for submap in new:
            self.submaps.append(submap)
            with stage("localization"):
                events.append(self.localizer.add_submap(submap, available_time=available_time))
        spacing = self.mapper.cfg.submap_spacing_after_fix
        if spacing is not None and events:
            if events[-1].state == "post" and any(e.fix_committed for e in events):
                self.mapper.trigger.use_spacing(spacing)
            elif events[-1].state == "pre" and any(e.fix_revoked for e in events):
                self.mapper.trigger.use_spacing(None)
        T_world_base, covariance = self.localizer.latest_estimate()
        return LiveEstimate(float(self.localizer.frame_times[-1]), T_world_base, covariance, self.localizer.state,
                            tuple(events))

    def _check(self, frame: Frame) -> None:
        """Refuse a frame the pipeline would misread, naming the field."""
        h, w = self.camera.height, self.camera.width
        rgb, depth, T = frame.rgb, frame.depth, frame.T_odom_base
        if rgb.shape != (h, w, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"rgb: expected a ({h}, {w}, 3) uint8 image for this camera, got {rgb.shape} {rgb.dtype}")
        if depth.shape != (h, w):
            raise ValueError(f"depth: expected a ({h}, {w}) image in metres for this camera, got {depth.shape}")
        if T.shape != (4, 4) or not np.isfinite(T).all() or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError(f"T_odom_base: expected a finite (4, 4) homogeneous pose, got shape {T.shape}")
        if not np.isfinite(frame.timestamp):
            raise ValueError(f"timestamp: expected a finite time in seconds, got {frame.timestamp}")

"""Ground mapping pipeline: RGB-D frames with odometry -> tracked 3D segments -> 2D submaps.

`GroundMapper` is online: `add_frame` (or `add_frames` for a batch, which segments the frames
together) returns the submaps completed by those frames; `finish` flushes the last one.
`map_ground` runs it over a whole sequence. See ground_observations / ground_tracking /
ground_submaps for the stages and the reference rules they follow.

Frames come faster than the mapper needs them on many robots (cameras at 10-30 Hz); like the
paper, which maps at a fixed 6 Hz, only the first frame of each 1 / `mapping_rate_hz` interval
of a clock started at the first frame is mapped (`frames_to_map`); the others still carry
odometry to the localizer.

Per frame mapped: segment, describe the masks, build the observations; a global
(place-recognition) descriptor is computed only when the camera moved `frame_descriptor_dist_m`
since the last one;
update the tracker; check the submap trigger. A submap's centre is the frame nearest in time to
the median of its NEW segments' (first_seen + last_seen) / 2 (non-decreasing; the reference
takes the mean over all selected segments, which with few segments per frame reaches back to the
start of the run; with `submap_spacing_after_fix.max_centre_lag_m`, at most that much travel behind
the newest frame); `GroundSubmap.time`,
`T_odom_base` and `path_length_m` are that frame's. Its `frame_descriptors` are the global
descriptors of the frames in the window where all its segments were in view (the reference's
[min last_seen, max first_seen], else [min first_seen, max last_seen]) whose camera is within the
submap radius, thinned to one per `frame_descriptor_dist_m`; if none, the descriptor of the frame
with one nearest in time to the centre.
"""

from __future__ import annotations

import contextvars
from bisect import bisect_left
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from meridian_torch.config import GroundMapConfig, MeridianConfig
from meridian_torch.config.mapping import PrimitiveConfig
from meridian_torch.config.perception import active_backend_dict
from meridian_torch.core.parallel import pipelined_threads, share_cpu_threads
from meridian_torch.core.timing import stage
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.sequence import Frame, SequenceReader
from meridian_torch.mapping.ground_observations import FrameObservations, observe_frames
from meridian_torch.mapping.ground_submaps import (
    SubmapGeometry,
    SubmapTrigger,
    submap_primitives,
    thin_by_distance,
)
from meridian_torch.mapping.ground_tracking import SegmentTracker, TrackedSegment
from meridian_torch.perception.factory import build_ground_perception
from meridian_torch.perception.protocols import GlobalDescriber, SegmentDescriber, Segmenter
from meridian_torch.runtime import Runtime
from meridian_torch.types import GroundSubmap

__all__ = [
    "GroundMapper", "PerceivedFrames", "frames_to_map", "ground_map_config_dict", "map_ground", "perceived_batches"
]


def frames_to_map(times: np.ndarray, origin: float, previous: float | None, rate_hz: float | None) -> np.ndarray:
    """(N,) bool: which frames at `times` (increasing seconds) to map at `rate_hz` at most - the first
    of each interval [origin + k / rate_hz, origin + (k + 1) / rate_hz). `previous` is the time of
    the frame offered before `times[0]` (None: it is the first). Every frame when `rate_hz` is None.
    """
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    if rate_hz is None:
        return np.ones(len(times), dtype=bool)
    # a frame exactly on a tick (e.g. 12 Hz frames, a 6 Hz clock) opens it despite rounding
    tick = np.floor((np.concatenate([[origin if previous is None else previous], times]) - origin) * rate_hz + 1e-6)
    if previous is None:
        tick[0] = -1
    return tick[1:] > tick[:-1]


@dataclass(frozen=True)
class PerceivedFrames:
    """A batch of frames after the stateless work (segmentation, descriptors, 3D observations),
    ready for `GroundMapper.integrate`."""

    images: torch.Tensor  # (B, 3, H, W) in [0, 1], for the global descriptors
    T_odom_base: np.ndarray  # (B, 4, 4)
    T_odom_camera: np.ndarray  # (B, 4, 4)
    times: np.ndarray  # (B,)
    observations: list[FrameObservations]

    def __len__(self) -> int:
        return len(self.times)


@dataclass
class _FrameRecord:
    time: float
    T_odom_base: np.ndarray
    camera_xyz: np.ndarray
    path_length_m: float
    descriptor: torch.Tensor | None


class GroundMapper:
    """Online ground mapping of one RGB-D sequence (frames must come in time order).

    `frame_descriptors=False` leaves the frames' global descriptors out: submaps then carry none
    (0 rows), which only place recognition by global descriptors would miss, and no global
    describer is needed (`global_describer` may be None).
    """

    def __init__(
        self,
        cfg: GroundMapConfig,
        primitives: PrimitiveConfig,
        camera: CameraModel,
        segmenter: Segmenter,
        describer: SegmentDescriber,
        global_describer: GlobalDescriber | None,
        runtime: Runtime,
        *,
        keep_geometries: bool = False,
        frame_descriptors: bool = True,
    ) -> None:
        if frame_descriptors and global_describer is None:
            raise ValueError("frame descriptors need a global describer")
        self.cfg = cfg
        self.primitives = primitives
        self.camera = camera
        self.segmenter = segmenter
        self.describer = describer
        self.global_describer = global_describer
        self.runtime = runtime
        self.tracker = SegmentTracker(cfg.tracking)
        self.trigger = SubmapTrigger(cfg)
        self.frames: list[_FrameRecord] = []
        # Every submap's flattened points, for writing and evaluating submaps; a localizer does
        # not need them and on a long drive they would be most of its memory.
        self.geometries: list[SubmapGeometry] | None = [] if keep_geometries else None
        # Only global place recognition reads frame descriptors; a localizer that matches by
        # another mode leaves them out (about a tenth of ground mapping's time).
        self.frame_descriptors = frame_descriptors
        self._n_submaps = 0
        self._last_descriptor_xyz: np.ndarray | None = None
        self._clock_origin: float | None = None  # mapping_rate_hz's clock: the first frame's time
        self._last_offered_time: float | None = None
        self._last_submap_time = -np.inf
        self._T_base_camera = np.asarray(camera.T_base_camera, dtype=np.float64)
        self._finished = False

    @classmethod
    def from_config(
        cls, cfg: MeridianConfig, camera: CameraModel, runtime: Runtime, *, keep_geometries: bool = False,
        frame_descriptors: bool = True,
    ) -> "GroundMapper":
        # perception.ground_engine decides whether models run in torch or onnxruntime
        segmenter, describer, global_describer = build_ground_perception(cfg.perception,
                                                                         global_descriptor=frame_descriptors)
        return cls(cfg.ground_map, cfg.primitives, camera, segmenter, describer, global_describer, runtime,
                   keep_geometries=keep_geometries, frame_descriptors=frame_descriptors)

    @property
    def num_submaps(self) -> int:
        return self._n_submaps

    def add_frame(self, frame: Frame) -> list[GroundSubmap]:
        """Process one frame; returns the submaps it completed (usually none or one)."""
        return self.add_frames([frame])

    def add_frames(self, frames: Sequence[Frame]) -> list[GroundSubmap]:
        """Process frames in time order, segmenting those due (`due`) as one batch; returns
        completed submaps."""
        mapped, _ = self.split_due(frames)
        if not mapped:
            return []
        return self.integrate(self.perceive(mapped))

    def split_due(self, frames: Sequence[Frame]) -> tuple[list[Frame], list[Frame]]:
        """The next frames offered (`due`), split into those to map and those that only carry odometry."""
        mapped: list[Frame] = []
        skipped: list[Frame] = []
        for frame, due in zip(frames, self.due([f.timestamp for f in frames])):
            (mapped if due else skipped).append(frame)
        return mapped, skipped

    def due(self, times: Sequence[float] | np.ndarray) -> np.ndarray:
        """(N,) bool: which of the next frames offered (their times, after every earlier call's) to
        map at `mapping_rate_hz` (`frames_to_map`). Each frame is offered once, in time order."""
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        if not len(times):
            return np.zeros(0, dtype=bool)
        if self._last_offered_time is not None and times[0] <= self._last_offered_time:
            raise ValueError(f"frame times must be strictly increasing: {times[0]} is not after the previous "
                             f"frame's {self._last_offered_time}")
        if np.any(np.diff(times) <= 0):
            raise ValueError(f"frame times must be strictly increasing, got {times.tolist()}")
        if self._clock_origin is None:
            self._clock_origin = float(times[0])
        due = frames_to_map(times, self._clock_origin, self._last_offered_time, self.cfg.mapping_rate_hz)
        self._last_offered_time = float(times[-1])
        return due

    def perceive(self, frames: Sequence[Frame]) -> PerceivedFrames:
        """The stateless part of `add_frames`: segmentation, segment descriptors and 3D observations
        of a batch. It reads no mapper state, so the next batch can be perceived (in another thread)
        while this one is integrated."""
        device, dtype = self.runtime.device, self.runtime.dtype
        with torch.inference_mode():
            images = torch.from_numpy(np.stack([f.rgb for f in frames])).to(device)
            images = images.permute(0, 3, 1, 2).to(dtype).div_(255.0)
            depths = np.stack([f.depth for f in frames])
            T_odom_base = np.stack([np.asarray(f.T_odom_base, dtype=np.float64) for f in frames])
            T_odom_camera = T_odom_base @ self._T_base_camera
            times = np.array([f.timestamp for f in frames])
            observations = observe_frames(images, depths, T_odom_camera, times, self.segmenter, self.describer,
                                          self.camera, self.cfg.observation)
        return PerceivedFrames(images, T_odom_base, T_odom_camera, times, observations)

    def integrate(self, batch: PerceivedFrames) -> list[GroundSubmap]:
        """The stateful part of `add_frames`: global descriptors, tracking and submaps of a
        perceived batch (batches in time order); returns the completed submaps."""
        if self._finished:
            raise RuntimeError("GroundMapper.finish() was called; create a new mapper for a new sequence")
        images, T_odom_base, T_odom_camera, times = batch.images, batch.T_odom_base, batch.T_odom_camera, batch.times
        if self.frames and times[0] <= self.frames[-1].time:
            raise ValueError(f"frame time {times[0]} is not after the previous frame's {self.frames[-1].time}")
        with torch.inference_mode():
            # global descriptors (when kept) only every frame_descriptor_dist_m of camera travel
            wanted, last = [], self._last_descriptor_xyz
            for b in range(len(batch) if self.frame_descriptors else 0):
                xyz = T_odom_camera[b, :3, 3]
                if last is None or np.linalg.norm(xyz - last) >= self.cfg.frame_descriptor_dist_m:
                    wanted.append(b)
                    last = xyz
            self._last_descriptor_xyz = last
            global_desc = None
            if wanted:
                with stage("global descriptors"):
                    global_desc = self.global_describer.describe(images[wanted]).to("cpu", torch.float32)

            submaps = []
            for b, obs in enumerate(batch.observations):
                path = 0.0
                if self.frames:
                    step = np.linalg.norm(T_odom_base[b, :3, 3] - self.frames[-1].T_odom_base[:3, 3])
                    path = self.frames[-1].path_length_m + float(step)
                desc = global_desc[wanted.index(b)] if b in wanted else None
                self.frames.append(_FrameRecord(float(times[b]), T_odom_base[b], T_odom_camera[b, :3, 3].copy(),
                                                path, desc))
                with stage("tracking"):
                    self.tracker.update(obs)
                with stage("submaps"):
                    self.trigger.observe(self.tracker)
                    submap = self._maybe_submap(force=False)
                    if submap is not None:
                        submaps.append(submap)
                    self.trigger.prune(self.tracker)
        return submaps

    def finish(self) -> list[GroundSubmap]:
        """End of the sequence: clean up the live segments and make a last submap from any new ones."""
        if self._finished or not self.frames:
            self._finished = True
            return []
        self._finished = True
        with torch.inference_mode():
            self.tracker.finish()
            self.trigger.observe(self.tracker)
            submap = self._maybe_submap(force=True)
        return [] if submap is None else [submap]

    def map_sequence(
        self, reader: SequenceReader, progress: Callable[[int, int], None] | None = None, n_frames: int | None = None
    ) -> list[GroundSubmap]:
        """The first `n_frames` frames of `reader` (default all) in batches of `batch_size`, then
        `finish`: all submaps. Frames inside an odometry gap are refused before any work."""
        reader.require_odometry_without_gaps(self.cfg.max_odometry_gap_s, n_frames)
        n = len(reader) if n_frames is None else min(n_frames, len(reader))
        submaps: list[GroundSubmap] = []
        if progress is not None:
            progress(0, n)
        times = reader.frame_times[:n]
        for batch in perceived_batches(self, reader, n):
            submaps += self.integrate(batch)
            if progress is not None:  # frames offered so far, mapped or not
                progress(int(np.searchsorted(times, batch.times[-1])) + 1, n)
        if progress is not None:
            progress(n, n)
        return submaps + self.finish()

    # ---------------------------------------------------------------------------- submaps

    def _maybe_submap(self, force: bool) -> GroundSubmap | None:
        segments = self.trigger.select(self.tracker, self.frames[-1].path_length_m, force=force)
        if segments is None:
            return None
        # centred on the NEW segments (median of their mid times), not on all selected ones as the
        # reference: when segments are few, the fill-up reaches back to the start of the run and
        # long-tracked segments (a road) drag the time back by minutes; the gates then skip every
        # later submap
        new = segments[: len(self.trigger.pending)]
        mid = float(np.median([0.5 * (s.first_seen + s.last_seen) for s in new]))
        mid = max(mid, self._last_submap_time)
        times = np.array([f.time for f in self.frames])
        lag_m = None if self.trigger.spacing is None else self.trigger.spacing.max_centre_lag_m
        if lag_m is not None:
            # A postponed submap keeps its new segments; where few come, their median stays behind
            # and the submap waited for it (KITTI 02: 110 m without a submap).
            behind = bisect_left(self.frames, self.frames[-1].path_length_m - lag_m, key=lambda f: f.path_length_m)
            mid = max(mid, self.frames[behind].time)
        centre = int(np.argmin(np.abs(times - mid)))
        record = self.frames[centre]
        if not self.trigger.gate(record.time, record.path_length_m):
            return None
        prims, geometry = submap_primitives(segments, record.camera_xyz, self.cfg, self.primitives,
                                            self.tracker.cfg.segment_voxel_m)
        self.trigger.commit(segments, record.time, record.path_length_m)
        self._last_submap_time = mid
        if self.geometries is not None:
            self.geometries.append(geometry)
        self._n_submaps += 1
        device, dtype = self.runtime.device, self.runtime.dtype
        return GroundSubmap(
            index=self._n_submaps - 1,
            time=record.time,
            T_odom_base=record.T_odom_base.copy(),
            path_length_m=record.path_length_m,
            primitives=prims.to(device=device, dtype=dtype),
            frame_descriptors=self._frame_descriptors(segments, record, times).to(device=device, dtype=dtype),
            segment_ids=torch.from_numpy(geometry.segment_ids.copy()).to(device),
        )

    def _frame_descriptors(self, segments: list[TrackedSegment], centre: _FrameRecord, times: np.ndarray) -> torch.Tensor:
        if not self.frame_descriptors:
            return torch.zeros(0, 0 if self.global_describer is None else self.global_describer.dim)
        first = np.array([s.first_seen for s in segments])
        last = np.array([s.last_seen for s in segments])
        t0, t1 = last.min(), first.max()
        if t0 > t1:
            t0, t1 = first.min(), last.max()
        with_desc = np.array([f.descriptor is not None for f in self.frames])
        xyz = np.stack([f.camera_xyz for f in self.frames])
        inside = with_desc & (times >= t0) & (times <= t1)
        inside &= np.linalg.norm(xyz - centre.camera_xyz, axis=1) <= self.cfg.submap_radius_m
        idx = np.flatnonzero(inside)
        if len(idx):
            idx = idx[thin_by_distance(xyz[idx], self.cfg.frame_descriptor_dist_m)]
        else:  # fall back to the frame with a descriptor nearest in time to the centre
            cand = np.flatnonzero(with_desc)
            idx = cand[[int(np.argmin(np.abs(times[cand] - centre.time)))]]
        return torch.stack([self.frames[i].descriptor for i in idx])


def perceived_batches(mapper: GroundMapper, reader: Any, n_frames: int) -> Iterator[PerceivedFrames]:
    """The frames due (`GroundMapper.due`) among the first `n_frames` of `reader`, in batches of
    `ground_map.batch_size`, in a pipeline: a reader thread decodes batch k + P + 1 while P =
    `ground_map.perception_threads` threads perceive batches k + 1 .. k + P and the caller
    integrates batch k (the tracker and submaps are serial). Perception is stateless; a second
    batch in flight fills the cores at the seams between one batch's stages and while the caller
    waits. The batches and their contents are those of a plain loop over the frames due; every
    thread records its stages into the caller's stage table.

    From the first batch asked for until the generator ends or is closed, torch runs
    single-threaded in every thread, the caller's included (`core.parallel.pipelined_threads`):
    the pipeline's own threads fill the cores."""
    mapped = np.flatnonzero(mapper.due(reader.frame_times[:n_frames]))  # the others are never decoded
    starts = list(range(0, len(mapped), mapper.cfg.batch_size))
    perceivers = mapper.cfg.perception_threads

    def read(start: int) -> list[Frame]:
        with stage("read frames"):
            return [reader[int(i)] for i in mapped[start : start + mapper.cfg.batch_size]]

    def perceive(frames: Future[list[Frame]]) -> PerceivedFrames:
        share_cpu_threads(perceivers)  # the perceivers' per-frame threads share the cores
        return mapper.perceive(frames.result())

    with pipelined_threads(), ThreadPoolExecutor(1, thread_name_prefix="meridian-read") as read_pool, \
            ThreadPoolExecutor(perceivers, thread_name_prefix="meridian-perceive") as perceive_pool:
        reads: dict[int, Future[list[Frame]]] = {}  # batch -> its frames being decoded
        perceiving: dict[int, Future[PerceivedFrames]] = {}
        n_read = n_perceiving = 0  # batches handed to each pool so far

        def top_up(k: int) -> None:
            """Batches k .. k + perceivers - 1 being perceived, the next one being decoded."""
            nonlocal n_read, n_perceiving
            while n_read < min(k + perceivers + 1, len(starts)):
                reads[n_read] = read_pool.submit(contextvars.copy_context().run, read, starts[n_read])
                n_read += 1
            while n_perceiving < min(k + perceivers, len(starts)):
                perceiving[n_perceiving] = perceive_pool.submit(
                    contextvars.copy_context().run, perceive, reads.pop(n_perceiving))
                n_perceiving += 1

        for k in range(len(starts)):
            top_up(k)
            batch = perceiving.pop(k).result()
            top_up(k + 1)  # the next batches go on while the caller integrates this one
            yield batch


def ground_map_config_dict(cfg: MeridianConfig) -> dict[str, Any]:
    """The config blocks that shape ground submaps (stored in submap files)."""
    p = cfg.perception
    return {
        "ground_map": cfg.ground_map.model_dump(mode="json", exclude={"batch_size", "perception_threads"}),
        "perception": {
            "ground_segmenter": active_backend_dict(p.ground_segmenter),
            "descriptor": active_backend_dict(p.descriptor),
            "global_descriptor": active_backend_dict(p.global_descriptor),
        },
        "primitives": cfg.primitives.model_dump(mode="json"),
    }


def map_ground(
    reader: SequenceReader,
    cfg: MeridianConfig,
    runtime: Runtime,
    progress: Callable[[int, int], None] | None = None,
    n_frames: int | None = None,
) -> list[GroundSubmap]:
    """All submaps of the first `n_frames` frames of a sequence (default all; frames segmented in
    batches of `cfg.ground_map.batch_size`)."""
    reader.require_odometry_without_gaps(cfg.ground_map.max_odometry_gap_s, n_frames)  # before the models load
    return GroundMapper.from_config(cfg, reader.camera, runtime).map_sequence(reader, progress, n_frames)

"""The online run over one sequence folder: its frames fed through `LiveLocalizer` as a robot would.

Frames go to the ground mapper in the order they were recorded (those due at
`ground_map.mapping_rate_hz`; the others only carry odometry to the localizer); every submap it
completes goes to the localizer at once, stamped with the time of the frame that completed it, so
the incremental trajectory only uses what was known online. `finalize` then runs the offline pass
for the final trajectory. Stage timings and the real-time factor make the run's cost visible.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from meridian_torch.backend.results import LocalizationResult, LocalizerEvent, Matcher
from meridian_torch.config import MeridianConfig
from meridian_torch.core.timing import stage
from meridian_torch.io.sequence import SequenceReader
from meridian_torch.mapping.ground_map import perceived_batches
from meridian_torch.pipeline.live import LiveLocalizer
from meridian_torch.runtime import Runtime, peak_rss_mib
from meridian_torch.types import AerialMap, GroundSubmap

__all__ = ["SequenceRun", "localize_sequence"]


@dataclass
class SequenceRun:
    """Everything one run produced, plus what it cost."""

    result: LocalizationResult
    submaps: list[GroundSubmap]
    seconds: dict[str, float] = field(default_factory=dict)  # per stage and "total"
    sequence_duration_s: float = 0.0
    peak_memory_mib: float = 0.0
    frames_mapped: int = 0  # frames due at ground_map.mapping_rate_hz (the others carried odometry only)

    @property
    def real_time_factor(self) -> float:
        """Sequence duration / processing time (> 1 is faster than real time)."""
        return self.sequence_duration_s / max(self.seconds.get("total", 0.0), 1e-9)


def localize_sequence(
    reader: SequenceReader,
    aerial_map: AerialMap,
    cfg: MeridianConfig,
    runtime: Runtime,
    *,
    on_frames: Callable[[int, int], None] | None = None,
    on_submap: Callable[[GroundSubmap, LocalizerEvent], None] | None = None,
    on_stage: Callable[[str], None] | None = None,
    matcher: Matcher | None = None,
) -> SequenceRun:
    """Feed the sequence through `LiveLocalizer` in batches of `ground_map.batch_size` frames
    (every submap localized as it appears), then finalize. The next batch is read and perceived in
    a second thread meanwhile (`perceived_batches`), which changes no result.

    Callbacks (all optional): `on_frames(done, total)` after each batch of frames,
    `on_submap(submap, event)` after each submap was localized, `on_stage(name)` when the final
    offline pass starts. `matcher` replaces `match_submap` (e.g. a `MatchingCheckpoint`).
    """
    reader.require_odometry_without_gaps(cfg.ground_map.max_odometry_gap_s)
    started = time.perf_counter()
    live = LiveLocalizer(aerial_map, cfg, reader.camera, runtime, matcher=matcher)
    n = len(reader)
    frame_times, T_odom_base = reader.frame_times[:n], reader.T_odom_base[:n]
    done, waiting_s = 0, 0.0  # frames given to the localizer, mapped or not
    batches = perceived_batches(live.mapper, reader, n)  # the next batch is read and perceived meanwhile
    while True:
        t0 = time.perf_counter()
        with stage("ground mapping"):
            perceived = next(batches, None)
        waiting_s += time.perf_counter() - t0
        if perceived is None:
            break
        # frames not due (ground_map.mapping_rate_hz) up to this batch's last carry odometry only
        end = int(np.searchsorted(frame_times, perceived.times[-1])) + 1
        skipped = done + np.flatnonzero(~np.isin(frame_times[done:end], perceived.times))
        estimate = live.add_perceived(perceived, skipped=(frame_times[skipped], T_odom_base[skipped]))
        if on_submap is not None:
            for event in estimate.events:
                on_submap(live.submaps[event.submap_index], event)
        done = end
        if on_frames is not None:
            on_frames(done, n)
    if done < n:
        live.add_odometry(frame_times[done:], T_odom_base[done:])
        if on_frames is not None:
            on_frames(n, n)
    if on_stage is not None:
        on_stage("final optimization")
    result = live.finish()
    # ground mapping as the main thread saw it: waiting for perceived frames, then integrating them
    seconds = {"ground_mapping": waiting_s + live.mapping_seconds, **result.timings}
    seconds["total"] = time.perf_counter() - started
    times = reader.frame_times
    return SequenceRun(
        result=result,
        submaps=live.submaps,
        seconds=seconds,
        sequence_duration_s=float(times[-1] - times[0]),
        peak_memory_mib=peak_rss_mib(),
        frames_mapped=len(live.mapper.frames),
    )

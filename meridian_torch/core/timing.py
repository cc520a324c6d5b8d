"""Wall time per pipeline stage, recorded only when someone asks for it.

Stages mark themselves with `with stage("affinity"):`. Outside `record_stages()` this costs two
attribute lookups; inside, each stage adds its wall time and call count under its full name,
the names of the stages around it joined by '/' ("localize/matching/affinity"), so a report
shows where the time of a parent went. Recording follows the context (context variables): a
thread's work lands in a table only when the thread runs in a copy of the recording context
(`contextvars.copy_context().run`, as the ground mapper's prefetch thread does); each context
keeps its own stack of open stages, so threads recording into one table never mix their paths.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field

__all__ = ["StageTimes", "record_stages", "stage"]


@dataclass
class StageTimes:
    """Seconds and calls per stage path ("parent/child"), in first-seen order."""

    seconds: dict[str, float] = field(default_factory=dict)
    calls: dict[str, int] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def add(self, path: str, seconds: float) -> None:
        with self._lock:  # stages of several threads may record into one table
            self.seconds[path] = self.seconds.get(path, 0.0) + seconds
            self.calls[path] = self.calls.get(path, 0) + 1

    def total(self, name: str) -> float:
        """Seconds of every stage called `name`, wherever it ran (summed over parents)."""
        return sum(s for path, s in self.seconds.items() if path.rsplit("/", 1)[-1] == name)


_recorder: ContextVar[StageTimes | None] = ContextVar("meridian_stage_times", default=None)
_open_path: ContextVar[str] = ContextVar("meridian_stage_path", default="")  # the open stages, "a/b"


@contextmanager
def record_stages(times: StageTimes | None = None) -> Iterator[StageTimes]:
    """Record every `stage` entered in this thread until the block ends."""
    times = StageTimes() if times is None else times
    token, path_token = _recorder.set(times), _open_path.set("")  # paths start afresh in a new table
    try:
        yield times
    finally:
        _open_path.reset(path_token)
        _recorder.reset(token)


@contextmanager
def stage(name: str) -> Iterator[None]:
    """Mark a block as the stage `name` (nested inside whatever stage is running)."""
    times = _recorder.get()
    if times is None:
        yield
        return
    parent = _open_path.get()
    path = f"{parent}/{name}" if parent else name
    token = _open_path.set(path)
    start = time.perf_counter()
    try:
        yield
    finally:
        times.add(path, time.perf_counter() - start)
        _open_path.reset(token)

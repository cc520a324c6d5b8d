"""Wall time per pipeline stage, recorded only when someone asks for it.

Stages mark themselves with `with stage("affinity"):`. Outside `record_stages()` this costs two
attribute lookups; inside, each stage adds its wall time and call count under its full name,
the names of the stages around it joined by '/' ("localize/matching/affinity"), so a report
shows where the time of a parent went. Recording is per thread (a context variable): a reader
thread's work never lands in the main thread's table.
"""

from __future__ import annotations

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
    _stack: list[str] = field(default_factory=list)

    def add(self, path: str, seconds: float) -> None:
        self.seconds[path] = self.seconds.get(path, 0.0) + seconds
        self.calls[path] = self.calls.get(path, 0) + 1

    def total(self, name: str) -> float:
        """Seconds of every stage called `name`, wherever it ran (summed over parents)."""
        return sum(s for path, s in self.seconds.items() if path.rsplit("/", 1)[-1] == name)


_recorder: ContextVar[StageTimes | None] = ContextVar("meridian_stage_times", default=None)


@contextmanager
def record_stages(times: StageTimes | None = None) -> Iterator[StageTimes]:
    """Record every `stage` entered in this thread until the block ends."""
    times = StageTimes() if times is None else times
    token = _recorder.set(times)
    try:
        yield times
    finally:
        _recorder.reset(token)


@contextmanager
def stage(name: str) -> Iterator[None]:
    """Mark a block as the stage `name` (nested inside whatever stage is running)."""
    times = _recorder.get()
    if times is None:
        yield
        return
    times._stack.append(name)
    path = "/".join(times._stack)
    start = time.perf_counter()
    try:
        yield
    finally:
        times.add(path, time.perf_counter() - start)
        times._stack.pop()

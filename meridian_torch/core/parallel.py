"""Per-item CPU work spread over threads: NumPy, SciPy, scikit-image, numba's `nogil` kernels
and torch's ops release the GIL in their heavy loops (measured: Felzenszwalb and KD-tree queries
run 1.8-2x faster on 2 threads), so one item per thread uses every core without the cost of
processes. Results are those of the plain loop, in order: each item is computed alone, exactly
as it would be sequentially.

`cpu_threads()` is how many threads such pools use: torch's CPU thread count
(`runtime.num_threads`), except inside `pipelined_threads()`, where the pools keep that count
while torch's own ops run single-threaded."""

from __future__ import annotations

import contextvars
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

import torch

__all__ = ["cpu_threads", "pipelined_threads", "share_cpu_threads", "thread_map"]

T = TypeVar("T")
R = TypeVar("R")

# Set inside pipelined_threads(); a context variable, so that a pipeline's threads can each
# take a share (they run in copies of the caller's context).
_pool_threads: contextvars.ContextVar[int | None] = contextvars.ContextVar("meridian_pool_threads", default=None)


def cpu_threads() -> int:
    """Threads a pool of per-item CPU work may use (see the module docstring)."""
    return _pool_threads.get() or torch.get_num_threads()


def share_cpu_threads(ways: int) -> None:
    """In this context, pools use a `ways`-th of `cpu_threads()` (at least 1): for work that runs
    `ways` side by side, e.g. in each thread of a pool, inside its own context copy."""
    _pool_threads.set(max(1, cpu_threads() // ways))


@contextmanager
def pipelined_threads() -> Iterator[None]:
    """For a stretch where several of our own threads run side by side (the ground mapper's
    pipeline: reader, perceivers, the caller tracking and matching): torch's intra-op threads
    are set to 1 in every thread, while the pools (`thread_map`, the matcher's patch groups) keep
    `cpu_threads()`. With torch's threads on top of them (2 perceivers and the caller, each with
    a 2-thread OpenMP team, on 2 cores), KITTI 09's ground mapping took 9-16 % longer and the
    run peaked 140-210 MiB higher (README, stop 43). Results do not depend on thread counts. Not
    reentrant across threads: one pipelined stretch at a time (torch's thread count is
    process-wide)."""
    previous_pool, previous_torch = _pool_threads.get(), torch.get_num_threads()
    _pool_threads.set(cpu_threads())
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous_torch)
        _pool_threads.set(previous_pool)


def thread_map(
    fn: Callable[[T], R], items: Iterable[T], threads: int | None = None, *, torch_threads_each: int | None = None
) -> list[R]:
    """[fn(x) for x in items], computed in up to `threads` threads (default `cpu_threads()`, i.e.
    `runtime.num_threads`, so one setting sizes every kind of parallelism).

    Each item runs in a copy of the caller's context, so the stages it marks land in the
    caller's `record_stages` table (summed over the threads). `torch_threads_each` caps torch's
    intra-op threads inside each worker, so that items that each call torch do not oversubscribe
    the cores (the caller keeps its own count; threads started later begin with the cap)."""
    items = list(items)
    workers = min(threads or cpu_threads(), len(items))
    if workers <= 1:
        return [fn(x) for x in items]
    context = contextvars.copy_context()

    def run(x: T) -> R:
        if torch_threads_each is not None:
            torch.set_num_threads(torch_threads_each)  # this pool's own thread; it ends with the call
        return context.copy().run(fn, x)

    with ThreadPoolExecutor(workers, thread_name_prefix="meridian-item") as pool:
        return list(pool.map(run, items))

"""Where the aerial map's blocks of patches are described: this process, local worker processes, or Ray.

Every engine runs `describe_block` (the mapper's `describe_patches` under inference mode) on the
same blocks and yields their results in block order, so the map does not depend on the engine
(`aerial_map.engine`, `aerial_map.workers`). Workers receive the orthophoto as it was given: an
`OrthophotoSource` travels as its path and each worker opens the file itself; an in-memory
`Orthophoto` travels with its pixels.

- local, workers = 1: this process.
- local, workers > 1: a spawn process pool, one mapper per process (CPU only), at most two blocks
  per worker submitted at a time (finished blocks wait for the one before them: what is held is
  bounded by the workers, not by the map).
- ray: one actor per worker holding the orthophoto, the grid and the mapper (neural back ends
  load their weights once per actor; an actor takes a GPU when the mapper's device is CUDA),
  each actor holding up to two blocks (queued in its mailbox) so that it does not wait for the
  driver; finished blocks wait for the one before them, two blocks per actor in flight or waiting
  in all (as in the local pool), so results held are bounded by the actors; at most as many
  actors as the cluster has CPUs (GPUs). Without `aerial_map.ray_address` a local cluster with
  `workers` CPUs is started (and stopped afterwards); with it, the running cluster is joined. A
  Ray session already initialised by the caller is used as it is. Ray is imported only here.
"""

from __future__ import annotations

import itertools
import multiprocessing
from collections import deque
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import TYPE_CHECKING

import numpy as np
import torch

from meridian_torch.errors import ConfigError
from meridian_torch.runtime import set_blas_threads
from meridian_torch.types import PatchGrid, PrimitiveSet

if TYPE_CHECKING:
    from meridian_torch.io.ortho import Orthophoto
    from meridian_torch.io.ortho_source import OrthophotoSource
    from meridian_torch.mapping.aerial_map import AerialMapper

__all__ = ["BlockResult", "describe_block", "described_blocks", "start_local_ray_cluster"]

BlockResult = list[tuple[PrimitiveSet, torch.Tensor]]  # per patch: primitives, global descriptor


def describe_block(
    ortho: Orthophoto | OrthophotoSource, grid: PatchGrid, mapper: AerialMapper, indices: np.ndarray
) -> BlockResult:
    """The per-block function every engine runs."""
    with torch.inference_mode():
        return mapper.describe_patches(ortho, grid, indices)


def described_blocks(
    ortho: Orthophoto | OrthophotoSource, grid: PatchGrid, mapper: AerialMapper, blocks: list[np.ndarray]
) -> Iterator[BlockResult]:
    """`describe_block` of each block, in order, on the engine of `mapper.aerial`."""
    if mapper.aerial.engine == "ray":
        yield from _ray_blocks(ortho, grid, mapper, blocks)
    else:
        yield from _local_blocks(ortho, grid, mapper, blocks)


# A BlockResult as NumPy arrays, as workers send it back. Tensors sent through a local pool travel
# as shared-memory file descriptors, one per tensor, held open as long as the receiver keeps the
# tensor, so a caller holding a whole map (`build_aerial_map`, 4 km^2: about 35 000 tensors) ran
# out of descriptors; through Ray each tensor's storage is pickled by `torch.save`, 8x the time of
# its array (a 4-patch block: 8.1 against 1.0 ms to put and get). Arrays travel by value.
_ArrayResult = list[tuple[dict[str, np.ndarray], np.ndarray]]


class _BlockDescriber:
    """A worker's state: the orthophoto (opened on first read), the grid and the mapper."""

    def __init__(self, ortho: Orthophoto | OrthophotoSource, grid: PatchGrid, mapper: AerialMapper) -> None:
        torch.set_num_threads(1)  # the workers are the parallelism
        set_blas_threads(1)
        self.state = (ortho, grid, mapper)

    def describe(self, indices: np.ndarray) -> _ArrayResult:
        """A block as arrays, to travel back to the driver (`_ArrayResult`)."""
        return [(prims.arrays(), global_desc.numpy()) for prims, global_desc in describe_block(*self.state, indices)]


_worker: _BlockDescriber | None = None  # a local pool worker's state


def _init_worker(ortho: Orthophoto | OrthophotoSource, grid: PatchGrid, mapper: AerialMapper) -> None:
    global _worker
    _worker = _BlockDescriber(ortho, grid, mapper)


def _describe_in_worker(indices: np.ndarray) -> _ArrayResult:
    """A block described in a pool worker."""
    assert _worker is not None, "worker not initialized"
    return _worker.describe(indices)


def _from_arrays(block: _ArrayResult) -> BlockResult:
    """A worker's arrays as the block's primitives and global descriptors again. Arrays from Ray are
    read-only views of its object store: those are copied, so that the tensors can be written and
    the store does not keep every block the caller holds."""

    def owned(a: np.ndarray) -> np.ndarray:
        return a if a.flags.writeable else a.copy()

    return [(PrimitiveSet.from_arrays({name: owned(a) for name, a in arrays.items()}), torch.from_numpy(owned(desc)))
            for arrays, desc in block]


def _local_blocks(
    ortho: Orthophoto | OrthophotoSource, grid: PatchGrid, mapper: AerialMapper, blocks: list[np.ndarray]
) -> Iterator[BlockResult]:
    workers = min(mapper.aerial.workers, len(blocks))
    if workers > 1 and mapper.device.type != "cpu":
        raise ConfigError(f"aerial_map.workers = {mapper.aerial.workers} needs the CPU device, got {mapper.device}")
    if workers <= 1:
        for indices in blocks:
            yield describe_block(ortho, grid, mapper, indices)
        return
    # spawn, not fork: a forked child of a process whose OpenMP pool is running can deadlock.
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker, initargs=(ortho, grid, mapper))
    remaining = iter(blocks)
    try:
        ahead = deque(pool.submit(_describe_in_worker, b) for b in itertools.islice(remaining, 2 * workers))
        while ahead:
            awaited = ahead.popleft()
            ahead.extend(pool.submit(_describe_in_worker, b) for b in itertools.islice(remaining, 1))
            yield _from_arrays(awaited.result())
    finally:  # interrupted (Ctrl-C, an error while saving): drop the blocks not started
        pool.shutdown(wait=True, cancel_futures=True)


def _in_order(ray, actors: list, blocks: list[np.ndarray], depth: int = 2) -> Iterator:
    """The actors' results of `blocks`, in block order: depth x actors blocks are in flight or
    waiting for the one before them, and each block taken frees a slot for the actor with the
    fewest blocks queued. (Ray's ActorPool frees an actor only once its result is taken in order,
    so an actor that finished early idled behind a slower one: 14.5 % longer than the local
    workers for 4 km^2.)"""
    pending: dict = {}  # result ref -> (block number, actor)
    finished: dict[int, object] = {}  # block number -> its result ref, done but not yet yielded
    submitted = 0

    def submit(actor) -> None:
        nonlocal submitted
        ref = actor.describe.remote(blocks[submitted])
        pending[ref] = (submitted, actor)
        submitted += 1

    for _ in range(depth):  # round robin: the first blocks run side by side
        for actor in actors:
            if submitted < len(blocks):
                submit(actor)
    for number in range(len(blocks)):
        while number not in finished:
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            finished[pending.pop(ref)[0]] = ref
        result = ray.get(finished.pop(number))
        if submitted < len(blocks):  # the slot just freed goes to the actor with the fewest blocks queued
            queued = [actor for _, actor in pending.values()]
            submit(min(actors, key=queued.count))
        yield result


def start_local_ray_cluster(cpus: int) -> None:
    """Start the local Ray cluster of `cpus` CPUs that the ray engine uses without an address
    (`bench_aerial.py` times it); stopped by `ray.shutdown()`."""
    import logging

    import ray

    # address "local": a new cluster, even where `ray start` left one (or its address file) behind
    ray.init(address="local", num_cpus=cpus, include_dashboard=False, logging_level=logging.WARNING)


def _ray_blocks(
    ortho: Orthophoto | OrthophotoSource, grid: PatchGrid, mapper: AerialMapper, blocks: list[np.ndarray]
) -> Iterator[BlockResult]:
    try:
        import ray
    except ImportError as e:
        raise ConfigError(
            "aerial_map.engine = 'ray' needs Ray, which is not installed: pip install -e '.[distributed]'"
        ) from e
    import logging

    if not blocks:
        return
    aerial = mapper.aerial
    started = not ray.is_initialized()
    if started and aerial.ray_address is None:
        start_local_ray_cluster(aerial.workers)
    elif started:
        try:
            ray.init(address=aerial.ray_address, logging_level=logging.WARNING)
        except ConnectionError as e:
            raise ConfigError(
                f"aerial_map.ray_address = {aerial.ray_address!r}: cannot connect ({e}); a cluster with token "
                "authentication (Ray's default) needs RAY_AUTH_MODE=token and its token (ray get-auth-token on "
                "the head) in RAY_AUTH_TOKEN or ~/.ray/auth_token"
            ) from e
    actors = []
    try:
        gpus = 1 if mapper.device.type == "cuda" else 0
        # No more actors than the cluster can place: a block sent to an actor still waiting for
        # resources would wait with it.
        resources = ray.cluster_resources()
        capacity = int(resources.get("GPU", 0)) if gpus else int(resources.get("CPU", 1))
        if capacity < 1:
            raise ConfigError(f"aerial_map.engine = 'ray' on device {mapper.device}: the Ray cluster has no GPU")
        actor_class = ray.remote(num_cpus=1, num_gpus=gpus)(_BlockDescriber)
        state = [ray.put(v) for v in (ortho, grid, mapper)]  # stored once, shared by the actors
        actors = [actor_class.remote(*state) for _ in range(min(aerial.workers, len(blocks), capacity))]
        for block in _in_order(ray, actors, blocks):
            yield _from_arrays(block)
    finally:  # finished or interrupted: the actors (and a cluster started here) go
        for actor in actors:
            ray.kill(actor)
        if started:
            ray.shutdown()

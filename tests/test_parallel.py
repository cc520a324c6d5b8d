"""Thread budgets: `thread_map`'s pools, and `pipelined_threads`, where our own threads fill the
cores and torch runs single-threaded."""

from __future__ import annotations

import contextvars
import threading

import pytest
import torch

from meridian_torch.core.parallel import cpu_threads, pipelined_threads, share_cpu_threads, thread_map


@pytest.fixture
def three_torch_threads():
    """torch at 3 threads (a count no machine default gives here), restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _workers_reached(n: int) -> None:
    """thread_map over n items whose calls all wait for each other: passes only if n threads ran them."""
    barrier = threading.Barrier(n, timeout=20)
    thread_map(lambda _: barrier.wait(), range(n))


def test_pools_follow_torch_threads_outside_a_pipeline(three_torch_threads) -> None:
    assert cpu_threads() == 3
    _workers_reached(3)


def test_a_pipeline_runs_torch_single_threaded_and_keeps_its_pools(three_torch_threads) -> None:
    with pipelined_threads():
        assert torch.get_num_threads() == 1
        assert cpu_threads() == 3
        _workers_reached(3)
        seen = []
        worker = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
        worker.start()
        worker.join()
        assert seen == [1]  # threads started inside inherit torch's setting
    assert torch.get_num_threads() == 3 and cpu_threads() == 3


def test_a_failing_pipeline_restores_the_thread_counts(three_torch_threads) -> None:
    with pytest.raises(RuntimeError, match="stage failed"), pipelined_threads():
        raise RuntimeError("stage failed")
    assert torch.get_num_threads() == 3 and cpu_threads() == 3


def test_a_share_applies_to_its_own_context_only(three_torch_threads) -> None:
    with pipelined_threads():
        def shared(ways: int) -> int:
            share_cpu_threads(ways)
            return cpu_threads()

        assert contextvars.copy_context().run(shared, 2) == 1
        assert contextvars.copy_context().run(shared, 4) == 1  # never below one thread
        assert contextvars.copy_context().run(shared, 1) == 3
        assert cpu_threads() == 3

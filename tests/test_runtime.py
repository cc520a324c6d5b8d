"""The runtime's thread settings: `runtime.blas_threads` reaches the BLAS libraries NumPy, SciPy
and OpenCV loaded (0 leaves them alone), and torch's own thread count is not touched by it; and
the C heap's free pages go back to the OS when asked."""

from __future__ import annotations

import subprocess
import sys

import cv2  # noqa: F401  (loads OpenCV's OpenBLAS copy, one of the libraries set)
import pytest
import scipy.linalg  # noqa: F401
import torch
from threadpoolctl import threadpool_info, threadpool_limits

from meridian_torch import runtime
from meridian_torch.config import RuntimeConfig
from meridian_torch.runtime import resolve_runtime


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_blas_threads_reach_every_loaded_blas_and_zero_leaves_them():
    original = threadpool_limits(limits=None)  # remembers every library's current setting
    torch_threads = torch.get_num_threads()
    try:
        assert _blas_threads(), "no BLAS library found"
        resolve_runtime(RuntimeConfig(blas_threads=3))
        assert _blas_threads() == [3] * len(_blas_threads())
        resolve_runtime(RuntimeConfig(blas_threads=1))
        assert _blas_threads() == [1] * len(_blas_threads())
        resolve_runtime(RuntimeConfig(blas_threads=0))
        assert _blas_threads() == [1] * len(_blas_threads())
        assert torch.get_num_threads() == torch_threads
    finally:
        original.restore_original_limits()


_FRAGMENTED_HEAP = """
from meridian_torch.runtime import current_rss_mib, release_free_memory
# 100 kB blocks (below glibc's mmap threshold) each followed by a small block that stays: freeing
# the large ones leaves holes the heap's top cannot give back, only a trim can
large, small = [], []
for k in range(2000):
    large.append(bytes([k % 251 + 1]) * 100_000)  # written, so resident
    small.append(bytes([k % 7 + 1]) * 1_000)
del large
held = current_rss_mib()
trimmed = release_free_memory()
assert len(small) == 2000 and all(s[0] == k % 7 + 1 for k, s in enumerate(small))  # live blocks intact
print(held - current_rss_mib(), trimmed)
"""


@pytest.mark.skipif(runtime._malloc_trim() is None, reason="no glibc malloc_trim here")
def test_release_free_memory_returns_pages_freed_between_live_blocks():
    # in a fresh process: the suite's own heap (what earlier tests freed) would blur the numbers
    out = subprocess.run([sys.executable, "-c", _FRAGMENTED_HEAP], capture_output=True, text=True, check=True)
    released, trimmed = out.stdout.split()
    assert trimmed == "True"
    assert float(released) > 150, f"only {float(released):.0f} MiB of the 190 freed came back"

"""The runtime's thread settings: `runtime.blas_threads` reaches the BLAS libraries NumPy, SciPy
and OpenCV loaded (0 leaves them alone), and torch's own thread count is not touched by it."""

from __future__ import annotations

import cv2  # noqa: F401  (loads OpenCV's OpenBLAS copy, one of the libraries set)
import scipy.linalg  # noqa: F401
import torch
from threadpoolctl import threadpool_info, threadpool_limits

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

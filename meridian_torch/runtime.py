"""The torch runtime: device, dtype and thread counts, resolved once at the entry point."""

from __future__ import annotations

import ctypes
import functools
import os
import resource
import sys
from dataclasses import dataclass

import torch

from meridian_torch.config import RuntimeConfig
from meridian_torch.errors import ConfigError

__all__ = ["Runtime", "resolve_runtime", "set_blas_threads", "peak_rss_mib", "current_rss_mib", "release_free_memory"]


@dataclass(frozen=True)
class Runtime:
    device: torch.device
    dtype: torch.dtype


def resolve_runtime(cfg: RuntimeConfig) -> Runtime:
    """Pick the device and dtype; 'auto' means CUDA when present, else CPU. Sets the thread counts."""
    if cfg.num_threads:
        torch.set_num_threads(cfg.num_threads)
    if cfg.blas_threads:
        set_blas_threads(cfg.blas_threads)
    name = cfg.device
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"runtime.device: {cfg.device!r} requested but no CUDA device is available")
    return Runtime(device=torch.device(name), dtype=getattr(torch, cfg.dtype))


def set_blas_threads(n: int) -> None:
    """Threads of the BLAS libraries loaded so far (the OpenBLAS copies of NumPy, SciPy and
    OpenCV; torch's are `torch.set_num_threads`'). Idle OpenBLAS threads spin on the cores they
    would share with the pipeline's own threads (`runtime.blas_threads`)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=n, user_api="blas")


def peak_rss_mib() -> float:
    """Peak resident set size of this process, MiB. Linux: VmHWM, which (unlike ru_maxrss, kept
    across exec) starts afresh in a new program, so a child does not inherit its parent's peak."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 1024.0
    except (OSError, StopIteration):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def current_rss_mib() -> float:
    """Current resident set size of this process, MiB (the peak where /proc is missing)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return peak_rss_mib()


@functools.cache
def _malloc_trim():
    """glibc's `int malloc_trim(size_t pad)`, or None (other C libraries, other systems)."""
    try:
        return getattr(ctypes.CDLL(None), "malloc_trim", None)
    except (OSError, TypeError):  # TypeError: Windows has no process-wide handle for None
        return None


def release_free_memory() -> bool:
    """Hand the free pages of the C heap back to the OS (glibc's `malloc_trim`); False where there
    is no such call or nothing was released.

    glibc serves arrays up to 32 MiB from its heaps once a block that large was freed (its mmap
    threshold rises), and pages freed between blocks still in use stay resident. Over a long
    drive that grew resident memory by about 95 MiB per 1.7 km while what the localizer holds
    stayed flat, so the localizer calls this after every submap it adds or re-matches (about
    25 ms a call). A fixed mmap threshold (mallopt) would keep large arrays off the heap but
    page-fault every fresh one; not measured."""
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False

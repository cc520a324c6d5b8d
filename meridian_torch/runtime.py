"""The torch runtime: device, dtype and thread count, resolved once at the entry point."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from meridian_torch.config import RuntimeConfig
from meridian_torch.errors import ConfigError

__all__ = ["Runtime", "resolve_runtime"]


@dataclass(frozen=True)
class Runtime:
    device: torch.device
    dtype: torch.dtype


def resolve_runtime(cfg: RuntimeConfig) -> Runtime:
    """Pick the device and dtype; 'auto' means CUDA when present, else CPU."""
    if cfg.num_threads:
        torch.set_num_threads(cfg.num_threads)
    name = cfg.device
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"runtime.device: {cfg.device!r} requested but no CUDA device is available")
    return Runtime(device=torch.device(name), dtype=getattr(torch, cfg.dtype))

"""One instance per model in a process: aerial and ground mapping (and the segment and global
describers) that name the same DINOv2 weights share a single loaded module."""

from __future__ import annotations

import os
from pathlib import Path

from meridian_torch.perception.neural.dinov2 import DinoVisionTransformer, load_dinov2

__all__ = ["shared_dinov2"]

_DINOV2: dict[tuple[str, str | None, int | None], DinoVisionTransformer] = {}


def shared_dinov2(
    architecture: str, weights_path: str | os.PathLike[str] | None, random_weights_seed: int | None, what: str
) -> DinoVisionTransformer:
    """`load_dinov2(...)`, loaded once per (architecture, weights file or seed)."""
    if weights_path is not None:
        key = (architecture, str(Path(weights_path).resolve()), None)
    else:
        key = (architecture, None, random_weights_seed)
    if key not in _DINOV2:
        _DINOV2[key] = load_dinov2(architecture, weights_path, random_weights_seed, what)
    return _DINOV2[key]

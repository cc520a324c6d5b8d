"""Reading local checkpoint files and loading them strictly; nothing is ever downloaded.

Every neural back end config names either `weights_path` (a local file: `.pth`/`.pt` read with
`torch.load(weights_only=True)`, or `.safetensors`) or `random_weights_seed` (seeded random
initialization, for tests and CI only). Any problem is a `ModelWeightsError` naming the path.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from meridian_torch.errors import ConfigError, ModelWeightsError

__all__ = ["read_checkpoint", "load_strict", "initialize_weights"]


def read_checkpoint(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """The flat state dict stored in `path` (tensors on the CPU)."""
    path = Path(path)
    if not path.is_file():
        raise ModelWeightsError(
            f"weights file not found: {path} (models are never downloaded; see models/README.md for where to get it)"
        )
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path), device="cpu")
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # any reader failure means the file is not a usable checkpoint
        raise ModelWeightsError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {exc})") from None
    # some checkpoints wrap the weights, e.g. {"model": state_dict} or {"state_dict": ...}
    for key in ("model", "state_dict"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ModelWeightsError(f"{path}: expected a dict of tensors (a state dict)")
    return state


def load_strict(module: nn.Module, state: dict[str, torch.Tensor], path: str | os.PathLike[str]) -> None:
    """Load `state` into `module`; every key and shape must match, else a ModelWeightsError naming `path`."""
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    wrong = sorted(k for k in set(own) & set(state) if tuple(own[k].shape) != tuple(state[k].shape))
    if missing or unexpected or wrong:
        parts = []
        for label, keys in (("missing keys", missing), ("unexpected keys", unexpected), ("wrong shapes", wrong)):
            if keys:
                shown = ", ".join(keys[:5]) + (f" and {len(keys) - 5} more" if len(keys) > 5 else "")
                parts.append(f"{label}: {shown}")
        raise ModelWeightsError(f"{path}: does not fit the {type(module).__name__} architecture ({'; '.join(parts)})")
    module.load_state_dict(state, strict=True)


def initialize_weights(
    module: nn.Module, weights_path: str | os.PathLike[str] | None, random_weights_seed: int | None, what: str
) -> nn.Module:
    """Load `weights_path` strictly, or (tests and CI only) re-initialize `module` from a seed.

    `what` names the config block for the error when neither is given, e.g.
    "perception.descriptor.dinov2".
    """
    if weights_path is not None:
        load_strict(module, read_checkpoint(weights_path), weights_path)
    elif random_weights_seed is not None:
        generator = torch.Generator().manual_seed(random_weights_seed)
        with torch.no_grad():
            for name, tensor in module.state_dict().items():
                if tensor.is_floating_point():
                    # small values keep deep random networks numerically tame
                    scale = 1.0 if name.endswith(("norm.weight", "norm1.weight", "norm2.weight")) else 0.02
                    tensor.copy_(torch.randn(tensor.shape, generator=generator) * scale)
    else:
        raise ConfigError(f"{what}: set weights_path to a local checkpoint file (see models/README.md)")
    return module.eval()

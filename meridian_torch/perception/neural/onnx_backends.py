"""Describer back ends that run exported DINOv2 / AnyLoc graphs with onnxruntime (`perception.ground_engine: onnx`).

Only the graphs written by `meridian-torch export` run: no torch model executes. Pre- and
post-processing are the same tensor functions the torch back ends use (resizing, mask pooling,
GeM), so both engines give the same descriptors up to float32 rounding. Graph metadata written by
the exporter (model kind, architecture, layer, facet, descriptor size) is checked against the
config, so a graph exported from another model is an error instead of silently wrong descriptors.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meridian_torch.errors import ConfigError, ModelWeightsError
from meridian_torch.perception.neural.anyloc import anyloc_input, gem
from meridian_torch.perception.neural.describers import masked_feature_pool
from meridian_torch.perception.neural.dinov2 import resize_to_patch_multiple

__all__ = [
    "OnnxGraph",
    "load_graph",
    "OnnxDinoSegmentDescriber",
    "OnnxAnyLocGlobalDescriber",
    "OnnxGemGlobalDescriber",
    "clear_session_cache",
]

_SESSIONS: dict[str, Any] = {}


class OnnxGraph:
    """One onnxruntime session with a single input, run on torch tensors (float32 on the CPU).

    `expect` maps metadata keys (e.g. "meridian.architecture") to the values the config asks for;
    a graph recording another value is a ConfigError naming `what` and the file.
    """

    def __init__(self, path: str | os.PathLike[str], what: str, expect: dict[str, str]) -> None:
        from meridian_torch.core.onnx_runtime import graph_metadata, graph_signature, open_session

        self.path = Path(path)
        key = str(self.path.resolve())
        if key not in _SESSIONS:  # aerial and ground (or two describers) naming one file share it
            _SESSIONS[key] = open_session(self.path, f"{what} ONNX graph")
        self.session = _SESSIONS[key]
        self.signature = graph_signature(self.session)
        self.metadata = graph_metadata(self.session)
        if len(self.signature.inputs) != 1:
            raise ModelWeightsError(f"{self.path}: expected one input, the graph has {list(self.signature.inputs)}")
        self.input_name = next(iter(self.signature.inputs))
        for meta_key, wanted in expect.items():
            found = self.metadata.get(meta_key)
            if found is not None and found != wanted:
                raise ConfigError(f"{what}: {self.path} was exported with {meta_key.removeprefix('meridian.')} "
                                  f"{found!r} but the config asks for {wanted!r}; re-export it "
                                  "with `meridian-torch export`")

    def output_dim(self, axis: int) -> int:
        """Size of the first output's `axis`, from the metadata or the graph (e.g. the feature dimension)."""
        if "meridian.dim" in self.metadata:
            return int(self.metadata["meridian.dim"])
        size = next(iter(self.signature.outputs.values()))[axis]
        if not isinstance(size, int):
            raise ModelWeightsError(f"{self.path}: output axis {axis} is symbolic and the graph has no "
                                    "meridian.dim metadata; export it with `meridian-torch export`")
        return size

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Run on (B, ...) and return the first output on `x`'s device and dtype."""
        from meridian_torch.core.onnx_runtime import run_session

        feed = x.detach().to("cpu", torch.float32).contiguous().numpy()
        out = run_session(self.session, {self.input_name: feed})[0]
        return torch.from_numpy(np.ascontiguousarray(out)).to(x.device, x.dtype)


def load_graph(path: str | None, what: str, expect: dict[str, str]) -> OnnxGraph:
    """The graph at `path`; `what` names the config key, which must be set."""
    if path is None:
        raise ConfigError(f"{what}: set it to a graph written by `meridian-torch export` "
                          "(perception.ground_engine is onnx)")
    return OnnxGraph(path, what, expect)


def clear_session_cache() -> None:
    """Forget every cached onnxruntime session."""
    _SESSIONS.clear()


class OnnxDinoSegmentDescriber:
    """`DinoSegmentDescriber` with the dense features from an exported `dinov2-dense` graph."""

    def __init__(self, dense: OnnxGraph, *, short_side_px: int) -> None:
        self.dense = dense
        self.short_side_px = short_side_px
        self.dim = dense.output_dim(1)

    def describe(self, images: torch.Tensor, masks: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        features = self.dense(resize_to_patch_multiple(images, self.short_side_px))
        return masked_feature_pool(features, masks, valid)


class OnnxAnyLocGlobalDescriber:
    """`AnyLocGlobalDescriber` from exported `anyloc-facet` and `vlad-head` graphs."""

    def __init__(self, facet: OnnxGraph, head: OnnxGraph, *, resize_short_side_px: int | None) -> None:
        token_dim, head_dim = facet.output_dim(2), next(iter(head.signature.inputs.values()))[2]
        if isinstance(head_dim, int) and head_dim != token_dim:
            raise ModelWeightsError(f"{head.path} takes {head_dim}-d tokens but {facet.path} "
                                    f"makes {token_dim}-d ones")
        self.facet, self.head = facet, head
        self.resize_short_side_px = resize_short_side_px
        self.dim = head.output_dim(1)

    def describe(self, images: torch.Tensor) -> torch.Tensor:
        return self.head(self.facet(anyloc_input(images, self.resize_short_side_px)))


class OnnxGemGlobalDescriber:
    """`GemGlobalDescriber` with the dense features from an exported `dinov2-dense` graph."""

    def __init__(self, dense: OnnxGraph, *, short_side_px: int, p: float) -> None:
        self.dense = dense
        self.short_side_px = short_side_px
        self.p = p
        self.dim = dense.output_dim(1)

    def describe(self, images: torch.Tensor) -> torch.Tensor:
        features = self.dense(resize_to_patch_multiple(images, self.short_side_px))
        return gem(features.flatten(2).transpose(1, 2), self.p)

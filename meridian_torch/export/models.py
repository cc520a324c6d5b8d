"""The models `meridian-torch export` writes, built from a perception config and checked by `export_checked`.

* dinov2-dense (perception.descriptor.dinov2): images (B, 3, H, W) in [0, 1] -> features (B, D, H/14, W/14);
* anyloc-facet (perception.global_descriptor.anyloc): images (B, 3, H, W) in [0, 1] -> tokens (B, N, D);
* vlad-head (perception.global_descriptor.anyloc): tokens (B, N, D) -> descriptors (B, K * D);
* sam-encoder (perception.aerial_segmenter.sam): preprocessed images (B, 3, S, S) -> embeddings
  (B, C, S/16, S/16);
* sam-decoder (perception.aerial_segmenter.sam): embeddings (1, C, h, w), points (N, T, 2) and
  labels (N, T) -> mask logits (N, 3, 4h, 4w) and IoU predictions (N, 3).

Batch and image size are dynamic for the DINOv2 graphs (H and W multiples of 14), batch and
token count for the VLAD head, batch for the SAM encoder (its input size is fixed by the
architecture), prompt and point count for the SAM decoder. Each graph stores metadata
(`meridian.model`, the architecture, layer, ...) that the onnxruntime back ends check.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import nn

from meridian_torch.config import PerceptionConfig
from meridian_torch.export.onnx import Exporter, ExportReport, export_checked

__all__ = ["EXPORTABLE_MODELS", "ExportSpec", "export_spec", "export_model", "weights_label"]

# float32 graphs of deep ViTs reorder sums differently in onnxruntime; features are O(1)
_ATOL, _RTOL = 1e-3, 1e-3


@dataclass
class ExportSpec:
    """A module ready for `export_checked`, with its inputs, names, dynamic axes and metadata."""

    module: nn.Module
    example_inputs: tuple[torch.Tensor, ...]
    check_inputs: list[tuple[torch.Tensor, ...]]
    input_names: list[str]
    output_names: list[str]
    dynamic_axes: dict[str, list[int]]
    metadata: dict[str, str] = field(default_factory=dict)
    exporter: Exporter = "legacy"  # exports every model here; see meridian_torch.export.onnx


def weights_label(weights_path: str | None, random_weights_seed: int | None) -> str:
    """How graph metadata names the weights a model was exported with."""
    return os.path.basename(weights_path) if weights_path is not None else f"random seed {random_weights_seed}"


def _images(generator: torch.Generator, batch: int, h: int, w: int) -> torch.Tensor:
    return torch.rand(batch, 3, h, w, generator=generator)


def _dinov2_dense(p: PerceptionConfig, g: torch.Generator) -> ExportSpec:
    from meridian_torch.perception.neural.dinov2 import DinoDenseFeatures
    from meridian_torch.perception.neural.runtime_cache import shared_dinov2

    c = p.descriptor.dinov2
    backbone = shared_dinov2(c.architecture, c.weights_path, c.random_weights_seed, "perception.descriptor.dinov2")
    module = DinoDenseFeatures(backbone)
    return ExportSpec(
        module, (_images(g, 2, 112, 140),), [(_images(g, 1, 84, 168),)],
        ["images"], ["features"], {"images": [0, 2, 3]},
        {"meridian.model": "dinov2-dense", "meridian.architecture": c.architecture, "meridian.dim": str(module.dim),
         "meridian.weights": weights_label(c.weights_path, c.random_weights_seed)},
    )


def _anyloc_describer(p: PerceptionConfig) -> object:
    # the factory's AnyLoc builder resolves the backbone, the layer check and the vocabulary
    from meridian_torch.perception.factory import GLOBAL_DESCRIBER_BUILDERS

    return GLOBAL_DESCRIBER_BUILDERS["anyloc"](p.global_descriptor)


def _anyloc_metadata(p: PerceptionConfig, model: str) -> dict[str, str]:
    c = p.global_descriptor.anyloc
    return {"meridian.model": model, "meridian.architecture": c.architecture, "meridian.layer": str(c.layer),
            "meridian.facet": c.facet, "meridian.weights": weights_label(c.weights_path, c.random_weights_seed)}


def _anyloc_facet(p: PerceptionConfig, g: torch.Generator) -> ExportSpec:
    describer = _anyloc_describer(p)
    metadata = _anyloc_metadata(p, "anyloc-facet") | {"meridian.dim": str(describer.facet.dim)}
    return ExportSpec(
        describer.facet, (_images(g, 2, 112, 140),), [(_images(g, 1, 84, 168),)],
        ["images"], ["tokens"], {"images": [0, 2, 3]}, metadata,
    )


def _vlad_head(p: PerceptionConfig, g: torch.Generator) -> ExportSpec:
    describer = _anyloc_describer(p)
    dim = describer.facet.dim

    def tokens(batch: int, n: int) -> torch.Tensor:
        return torch.nn.functional.normalize(torch.randn(batch, n, dim, generator=g), dim=-1)

    metadata = _anyloc_metadata(p, "vlad-head")
    metadata["meridian.vocabulary"] = os.path.basename(p.global_descriptor.anyloc.vocabulary_path or "random")
    metadata["meridian.dim"] = str(describer.head.dim)
    return ExportSpec(describer.head, (tokens(2, 60),), [(tokens(1, 90),)], ["tokens"], ["descriptors"],
                      {"tokens": [0, 1]}, metadata)


def _sam(p: PerceptionConfig) -> nn.Module:
    from meridian_torch.perception.neural.sam.model import load_sam

    c = p.aerial_segmenter.sam
    return load_sam(c.architecture, c.weights_path, c.random_weights_seed, "perception.aerial_segmenter.sam")


def _sam_metadata(p: PerceptionConfig, model: str) -> dict[str, str]:
    c = p.aerial_segmenter.sam
    return {"meridian.model": model, "meridian.architecture": c.architecture,
            "meridian.weights": weights_label(c.weights_path, c.random_weights_seed)}


def _sam_encoder(p: PerceptionConfig, g: torch.Generator) -> ExportSpec:
    from meridian_torch.perception.neural.sam.model import SamImageEncoderExport

    sam = _sam(p)
    s = sam.image_size
    # the encoder sees normalized images: roughly zero-mean, unit-variance values
    return ExportSpec(
        SamImageEncoderExport(sam),
        (torch.randn(2, 3, s, s, generator=g),),
        [(torch.randn(1, 3, s, s, generator=g),)],
        ["images"], ["embeddings"], {"images": [0]}, _sam_metadata(p, "sam-encoder"),
    )


def _sam_decoder(p: PerceptionConfig, g: torch.Generator) -> ExportSpec:
    from meridian_torch.perception.neural.sam.model import SamPromptDecoderExport

    sam = _sam(p)
    a = sam.architecture
    embeddings = torch.randn(1, a.prompt_embed_dim, a.embedding_size, a.embedding_size, generator=g)

    def prompts(n: int, t: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        coords = torch.rand(n, t, 2, generator=g) * a.image_size
        return embeddings, coords, torch.randint(0, 2, (n, t), generator=g)

    return ExportSpec(
        SamPromptDecoderExport(sam), prompts(3, 2), [prompts(5, 3)],
        ["image_embeddings", "point_coords", "point_labels"], ["masks", "iou_predictions"],
        {"point_coords": [0, 1], "point_labels": [0, 1]}, _sam_metadata(p, "sam-decoder"),
    )


EXPORTABLE_MODELS: dict[str, Callable[[PerceptionConfig, torch.Generator], ExportSpec]] = {
    "dinov2-dense": _dinov2_dense,
    "anyloc-facet": _anyloc_facet,
    "vlad-head": _vlad_head,
    "sam-encoder": _sam_encoder,
    "sam-decoder": _sam_decoder,
}


def export_spec(name: str, perception: PerceptionConfig, seed: int = 0) -> ExportSpec:
    """The module, inputs and names for exporting model `name` (see EXPORTABLE_MODELS)."""
    if name not in EXPORTABLE_MODELS:
        raise ValueError(f"unknown model {name!r}; exportable: {', '.join(EXPORTABLE_MODELS)}")
    return EXPORTABLE_MODELS[name](perception, torch.Generator().manual_seed(seed))


def export_model(
    name: str, perception: PerceptionConfig, out: str | os.PathLike[str], exporter: Exporter | None = None
) -> ExportReport:
    """Export model `name` as configured in `perception` to `out`, checked against eager torch.

    `exporter` overrides the model's default exporter ("legacy" for all of them today).
    """
    spec = export_spec(name, perception)
    return export_checked(
        spec.module, spec.example_inputs, out, input_names=spec.input_names, output_names=spec.output_names,
        dynamic_axes=spec.dynamic_axes, check_inputs=spec.check_inputs, atol=_ATOL, rtol=_RTOL,
        metadata=spec.metadata, exporter=exporter or spec.exporter,
    )

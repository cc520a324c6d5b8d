"""Build perception back ends from their configs; new back ends register a builder here.

Each builder maps a config block to explicit constructor arguments, so back-end classes never
see config objects. OpenCV, scikit-image (and later model code) are imported only when a back end
is built.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from meridian_torch.config.perception import (
    AnyLocConfig,
    DescriptorConfig,
    GlobalDescriptorConfig,
    PixelFeatureConfig,
    SegmenterConfig,
)
from meridian_torch.perception.protocols import GlobalDescriber, SegmentDescriber, Segmenter

if TYPE_CHECKING:
    from meridian_torch.config import PerceptionConfig
    from meridian_torch.perception.neural.anyloc import AnyLocFacet

__all__ = [
    "SEGMENTER_BUILDERS",
    "SEGMENT_DESCRIBER_BUILDERS",
    "GLOBAL_DESCRIBER_BUILDERS",
    "build_segmenter",
    "build_segment_describer",
    "build_global_describer",
    "build_anyloc_facet",
    "build_ground_perception",
]


def _classical_segmenter(cfg: SegmenterConfig) -> Segmenter:
    from meridian_torch.perception.classical.segmenter import ClassicalSegmenter

    return ClassicalSegmenter(**cfg.classical.model_dump())


def _sam_segmenter(cfg: SegmenterConfig) -> Segmenter:
    from meridian_torch.perception.neural.sam.automatic import AutomaticMaskGenerator, SamSegmenter
    from meridian_torch.perception.neural.sam.model import load_sam

    c = cfg.sam
    sam = load_sam(c.architecture, c.weights_path, c.random_weights_seed, what="perception.*_segmenter.sam")
    generator = AutomaticMaskGenerator(
        sam, **c.model_dump(exclude={"architecture", "weights_path", "random_weights_seed", "downsample_factor"})
    )
    return SamSegmenter(generator, downsample_factor=c.downsample_factor)


def _fastsam_segmenter(cfg: SegmenterConfig) -> Segmenter:
    from meridian_torch.errors import ConfigError
    from meridian_torch.perception.neural.fastsam import FastSamSegmenter

    c = cfg.fastsam
    params = c.model_dump(exclude={"weights_path", "random_weights_seed"})
    if c.weights_path is not None:
        return FastSamSegmenter.from_file(c.weights_path, **params)
    if c.random_weights_seed is not None:  # tests and CI: a tiny random graph of the same signature
        from meridian_torch.export.tiny_yolo_seg import tiny_yolo_seg_session

        session, source = tiny_yolo_seg_session(c.random_weights_seed, c.imgsz)
        return FastSamSegmenter(session, source, **params)
    raise ConfigError("perception.*_segmenter.fastsam.weights_path: set it to a FastSAM .onnx file (models/README.md)")


def _pixel_features(cfg: PixelFeatureConfig) -> Any:
    from meridian_torch.perception.classical.pixel_features import PixelFeatures

    return PixelFeatures(**cfg.model_dump(exclude={"colour_weight", "texture_weight"}))


def _classical_segment_describer(cfg: DescriptorConfig) -> SegmentDescriber:
    from meridian_torch.perception.classical.describers import ColourTextureDescriber

    c = cfg.classical
    return ColourTextureDescriber(_pixel_features(c), colour_weight=c.colour_weight, texture_weight=c.texture_weight)


def _classical_global_describer(cfg: GlobalDescriptorConfig) -> GlobalDescriber:
    from meridian_torch.perception.classical.describers import ColourTextureGlobalDescriber

    c = cfg.classical
    return ColourTextureGlobalDescriber(
        _pixel_features(c),
        pyramid_levels=cfg.pyramid_levels,
        gem_p=cfg.gem_p,
        colour_weight=c.colour_weight,
        texture_weight=c.texture_weight,
    )


def _dinov2_segment_describer(cfg: DescriptorConfig) -> SegmentDescriber:
    from meridian_torch.perception.neural.describers import DinoSegmentDescriber
    from meridian_torch.perception.neural.dinov2 import DinoDenseFeatures
    from meridian_torch.perception.neural.runtime_cache import shared_dinov2

    c = cfg.dinov2
    backbone = shared_dinov2(c.architecture, c.weights_path, c.random_weights_seed, "perception.descriptor.dinov2")
    return DinoSegmentDescriber(DinoDenseFeatures(backbone), short_side_px=c.short_side_px)


def build_anyloc_facet(cfg: AnyLocConfig) -> AnyLocFacet:
    """The AnyLoc token extractor (`AnyLocFacet`) of `cfg`, without its vocabulary."""
    from meridian_torch.errors import ConfigError
    from meridian_torch.perception.neural.anyloc import AnyLocFacet
    from meridian_torch.perception.neural.dinov2 import ARCHITECTURES
    from meridian_torch.perception.neural.runtime_cache import shared_dinov2

    what = "perception.global_descriptor.anyloc"
    depth = ARCHITECTURES[cfg.architecture].depth
    if cfg.layer >= depth:  # checked before a large model is loaded
        raise ConfigError(f"{what}.layer: {cfg.layer} but {cfg.architecture} has blocks 0..{depth - 1}")
    backbone = shared_dinov2(cfg.architecture, cfg.weights_path, cfg.random_weights_seed, what)
    return AnyLocFacet(backbone, cfg.layer, cfg.facet)


def _anyloc_global_describer(cfg: GlobalDescriptorConfig) -> GlobalDescriber:
    import torch

    from meridian_torch.errors import ConfigError, ModelWeightsError
    from meridian_torch.perception.neural.anyloc import VladHead, load_vocabulary
    from meridian_torch.perception.neural.describers import AnyLocGlobalDescriber

    c = cfg.anyloc
    facet = build_anyloc_facet(c)
    if c.vocabulary_path is not None:
        vocabulary = load_vocabulary(c.vocabulary_path)
        vocabulary.check_fits(c.vocabulary_path, dim=facet.dim, architecture=c.architecture, layer=c.layer, facet=c.facet)
        centers = vocabulary.centers
        if centers.shape[0] != c.num_clusters:
            raise ModelWeightsError(
                f"{c.vocabulary_path}: {centers.shape[0]} cluster centres, but "
                f"perception.global_descriptor.anyloc.num_clusters is {c.num_clusters}"
            )
    elif c.random_weights_seed is not None:  # tests and CI: random unit centres, like the random weights
        generator = torch.Generator().manual_seed(c.random_weights_seed)
        centers = torch.nn.functional.normalize(torch.randn(c.num_clusters, facet.dim, generator=generator), dim=1)
    else:
        raise ConfigError(
            "perception.global_descriptor.anyloc.vocabulary_path: set it to AnyLoc's c_centers.pt "
            "or to a file written by `meridian-torch fit-vocabulary`"
        )
    return AnyLocGlobalDescriber(facet, VladHead(centers), resize_short_side_px=c.resize_short_side_px)


def _gem_global_describer(cfg: GlobalDescriptorConfig) -> GlobalDescriber:
    from meridian_torch.perception.neural.describers import GemGlobalDescriber
    from meridian_torch.perception.neural.dinov2 import DinoDenseFeatures
    from meridian_torch.perception.neural.runtime_cache import shared_dinov2

    c = cfg.gem
    backbone = shared_dinov2(c.architecture, c.weights_path, c.random_weights_seed, "perception.global_descriptor.gem")
    return GemGlobalDescriber(DinoDenseFeatures(backbone), short_side_px=c.short_side_px, p=c.p)


SEGMENTER_BUILDERS: dict[str, Callable[[SegmenterConfig], Segmenter]] = {
    "classical": _classical_segmenter,
    "sam": _sam_segmenter,
    "fastsam": _fastsam_segmenter,
}
SEGMENT_DESCRIBER_BUILDERS: dict[str, Callable[[DescriptorConfig], SegmentDescriber]] = {
    "classical": _classical_segment_describer,
    "dinov2": _dinov2_segment_describer,
}
GLOBAL_DESCRIBER_BUILDERS: dict[str, Callable[[GlobalDescriptorConfig], GlobalDescriber]] = {
    "classical": _classical_global_describer,
    "anyloc": _anyloc_global_describer,
    "gem": _gem_global_describer,
}


def build_segmenter(cfg: SegmenterConfig) -> Segmenter:
    """The segmenter named by `cfg.backend`."""
    return SEGMENTER_BUILDERS[cfg.backend](cfg)


def build_segment_describer(cfg: DescriptorConfig) -> SegmentDescriber:
    """The per-segment describer named by `cfg.backend`."""
    return SEGMENT_DESCRIBER_BUILDERS[cfg.backend](cfg)


def build_global_describer(cfg: GlobalDescriptorConfig) -> GlobalDescriber:
    """The image describer named by `cfg.backend`."""
    return GLOBAL_DESCRIBER_BUILDERS[cfg.backend](cfg)


def _onnx_segment_describer(p: PerceptionConfig) -> SegmentDescriber:
    from meridian_torch.perception.neural.onnx_backends import OnnxDinoSegmentDescriber, load_graph

    c = p.descriptor.dinov2
    graph = load_graph(p.onnx.dinov2_dense_path, "perception.onnx.dinov2_dense_path",
                       {"meridian.model": "dinov2-dense", "meridian.architecture": c.architecture})
    return OnnxDinoSegmentDescriber(graph, short_side_px=c.short_side_px)


def _onnx_global_describer(p: PerceptionConfig) -> GlobalDescriber:
    from meridian_torch.perception.neural.onnx_backends import (
        OnnxAnyLocGlobalDescriber,
        OnnxGemGlobalDescriber,
        load_graph,
    )

    if p.global_descriptor.backend == "gem":
        c = p.global_descriptor.gem
        graph = load_graph(p.onnx.dinov2_dense_path, "perception.onnx.dinov2_dense_path",
                           {"meridian.model": "dinov2-dense", "meridian.architecture": c.architecture})
        return OnnxGemGlobalDescriber(graph, short_side_px=c.short_side_px, p=c.p)
    a = p.global_descriptor.anyloc
    expect = {"meridian.architecture": a.architecture, "meridian.layer": str(a.layer), "meridian.facet": a.facet}
    facet = load_graph(p.onnx.anyloc_facet_path, "perception.onnx.anyloc_facet_path",
                       expect | {"meridian.model": "anyloc-facet"})
    head = load_graph(p.onnx.vlad_head_path, "perception.onnx.vlad_head_path", expect | {"meridian.model": "vlad-head"})
    return OnnxAnyLocGlobalDescriber(facet, head, resize_short_side_px=a.resize_short_side_px)


def build_ground_perception(
    p: PerceptionConfig, *, global_descriptor: bool = True
) -> tuple[Segmenter, SegmentDescriber, GlobalDescriber | None]:
    """The ground pipeline's segmenter, segment describer and global describer (None with
    `global_descriptor=False`: nothing will read frame descriptors, so no model is loaded for them).

    With `p.ground_engine == "onnx"` no torch model runs: neural describers run their exported
    graphs (`p.onnx`) in onnxruntime, FastSAM is an ONNX graph anyway, and the classical back
    ends have no model; SAM, which has no onnxruntime path here, is a ConfigError.
    """
    if p.ground_engine == "torch":
        return (build_segmenter(p.ground_segmenter), build_segment_describer(p.descriptor),
                build_global_describer(p.global_descriptor) if global_descriptor else None)
    from meridian_torch.errors import ConfigError

    # every back end must be named here: a new neural one must not silently run torch onboard
    for key, backend, allowed in (
        ("ground_segmenter", p.ground_segmenter.backend, ("fastsam", "classical")),
        ("descriptor", p.descriptor.backend, ("dinov2", "classical")),
        ("global_descriptor", p.global_descriptor.backend, ("anyloc", "gem", "classical")),
    ):
        if backend not in allowed:
            raise ConfigError(f"perception.{key}.backend: {backend!r} has no onnxruntime path; with "
                              f"perception.ground_engine onnx use one of {', '.join(allowed)}")
    segmenter = build_segmenter(p.ground_segmenter)
    describer = (_onnx_segment_describer(p) if p.descriptor.backend == "dinov2"
                 else build_segment_describer(p.descriptor))
    if not global_descriptor:
        return segmenter, describer, None
    global_describer = (build_global_describer(p.global_descriptor) if p.global_descriptor.backend == "classical"
                        else _onnx_global_describer(p))
    return segmenter, describer, global_describer

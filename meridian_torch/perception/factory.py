"""Build perception back ends from their configs; new back ends register a builder here.

Each builder maps a config block to explicit constructor arguments, so back-end classes never
see config objects. OpenCV, scikit-image (and later model code) are imported only when a back end
is built.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from meridian_torch.perception.config import (
    DescriptorConfig,
    GlobalDescriptorConfig,
    PixelFeatureConfig,
    SegmenterConfig,
)
from meridian_torch.perception.protocols import GlobalDescriber, SegmentDescriber, Segmenter

__all__ = [
    "SEGMENTER_BUILDERS",
    "SEGMENT_DESCRIBER_BUILDERS",
    "GLOBAL_DESCRIBER_BUILDERS",
    "build_segmenter",
    "build_segment_describer",
    "build_global_describer",
]


def _classical_segmenter(cfg: SegmenterConfig) -> Segmenter:
    from meridian_torch.perception.classical import ClassicalSegmenter

    return ClassicalSegmenter(**cfg.classical.model_dump())


def _pixel_features(cfg: PixelFeatureConfig) -> Any:
    from meridian_torch.perception.classical import PixelFeatures

    return PixelFeatures(**cfg.model_dump(exclude={"colour_weight", "texture_weight"}))


def _classical_segment_describer(cfg: DescriptorConfig) -> SegmentDescriber:
    from meridian_torch.perception.classical import ColourTextureDescriber

    c = cfg.classical
    return ColourTextureDescriber(_pixel_features(c), colour_weight=c.colour_weight, texture_weight=c.texture_weight)


def _classical_global_describer(cfg: GlobalDescriptorConfig) -> GlobalDescriber:
    from meridian_torch.perception.classical import ColourTextureGlobalDescriber

    c = cfg.classical
    return ColourTextureGlobalDescriber(
        _pixel_features(c),
        pyramid_levels=cfg.pyramid_levels,
        gem_p=cfg.gem_p,
        colour_weight=c.colour_weight,
        texture_weight=c.texture_weight,
    )


SEGMENTER_BUILDERS: dict[str, Callable[[SegmenterConfig], Segmenter]] = {"classical": _classical_segmenter}
SEGMENT_DESCRIBER_BUILDERS: dict[str, Callable[[DescriptorConfig], SegmentDescriber]] = {
    "classical": _classical_segment_describer
}
GLOBAL_DESCRIBER_BUILDERS: dict[str, Callable[[GlobalDescriptorConfig], GlobalDescriber]] = {
    "classical": _classical_global_describer
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

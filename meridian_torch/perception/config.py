"""Validated configuration of the perception back ends (segmenter, segment and global describers).

Each config names a `backend` and carries one block per back end, so neural back ends add a block
and a `Literal` value without touching the classical ones. Only pydantic is imported here.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from meridian_torch.sim.config import StrictModel

__all__ = [
    "ClassicalSegmenterConfig",
    "SegmenterConfig",
    "PixelFeatureConfig",
    "DescriptorConfig",
    "GlobalDescriptorConfig",
]


class ClassicalSegmenterConfig(StrictModel):
    """Over-segmentation plus region-adjacency merging at a fixed working resolution.

    Aerial images are resampled to `working_meters_per_pixel`, so every size below is in metres
    and a scene gives segments of similar area whatever the input resolution. Ground frames
    (meters_per_pixel None) are resampled so their longer side is `ground_working_size_px` and are
    then treated as if each working pixel were `working_meters_per_pixel` wide; only the minimum
    segment area is given separately, as a fraction of the frame.
    """

    oversegmentation: Literal["felzenszwalb", "slic"] = Field(
        default="felzenszwalb", description="initial over-segmentation algorithm (scikit-image)"
    )
    working_meters_per_pixel: float = Field(
        default=0.3, gt=0, description="resolution at which aerial images are segmented, metres per pixel"
    )
    ground_working_size_px: int = Field(
        default=320, ge=32, description="longer side, in pixels, to which ground frames are resampled"
    )
    felzenszwalb_scale_m2: float = Field(
        default=5.0, gt=0, description="Felzenszwalb scale (prefers larger components), in square metres"
    )
    smoothing_sigma_m: float = Field(
        default=0.2, ge=0, description="Gaussian pre-smoothing of the over-segmentation, metres"
    )
    superpixel_size_m: float = Field(default=1.5, gt=0, description="SLIC superpixel side length, metres")
    slic_compactness: float = Field(default=10.0, gt=0, description="SLIC colour/space trade-off (Lab units)")
    merge_threshold: float = Field(
        default=10.0, gt=0, description="adjacent regions merge while their dissimilarity (Lab units) is below this"
    )
    merge_levels: int = Field(
        default=4, ge=1, description="hierarchical merging runs at this many increasing thresholds up to merge_threshold"
    )
    lightness_weight: float = Field(
        default=1.0, ge=0, description="weight of the Lab lightness difference relative to the a/b (chroma) difference"
    )
    texture_weight: float = Field(
        default=0.5, ge=0, description="weight of the local-contrast (texture) difference in the dissimilarity"
    )
    boundary_weight: float = Field(
        default=0.5, ge=0, description="weight of the mean colour step across the shared border in the dissimilarity"
    )
    min_segment_area_m2: float = Field(
        default=2.0, ge=0, description="aerial regions smaller than this are merged into their most similar neighbour"
    )
    ground_min_segment_fraction: float = Field(
        default=0.002, ge=0, lt=1, description="ground-frame minimum segment area, fraction of the frame"
    )


class SegmenterConfig(StrictModel):
    """Which segmentation back end to build, and its parameters."""

    backend: Literal["classical"] = Field(default="classical", description="segmentation back end")
    classical: ClassicalSegmenterConfig = Field(
        default_factory=ClassicalSegmenterConfig, description="parameters of the classical back end"
    )


class PixelFeatureConfig(StrictModel):
    """Per-pixel colour and texture features that the classical describers pool.

    Colour is a soft hue histogram from brightness-normalized opponent chromaticity plus one
    achromatic bin, so shading and exposure changes between aerial and ground views cancel out.
    Texture is a soft histogram of gradient magnitude relative to the local brightness.
    """

    hue_bins: int = Field(default=12, ge=4, description="bins of the circular hue histogram")
    saturation_knee: float = Field(
        default=0.12, gt=0, description="chromaticity saturation at which a pixel counts as fully chromatic"
    )
    texture_bins: int = Field(default=4, ge=2, description="bins of the relative-gradient histogram")
    texture_max: float = Field(
        default=0.6, gt=0, description="relative gradient magnitude mapped to the last texture bin"
    )
    texture_smoothing_px: float = Field(
        default=1.0, ge=0, description="Gaussian sigma applied before the gradients, pixels"
    )
    colour_weight: float = Field(default=1.0, ge=0, description="weight of the colour block in the descriptor")
    texture_weight: float = Field(default=0.4, ge=0, description="weight of the texture block in the descriptor")


class DescriptorConfig(StrictModel):
    """Which per-segment describer to build, and its parameters."""

    backend: Literal["classical"] = Field(default="classical", description="segment description back end")
    classical: PixelFeatureConfig = Field(
        default_factory=PixelFeatureConfig, description="parameters of the classical back end"
    )


class GlobalDescriptorConfig(StrictModel):
    """Which image (place-recognition) describer to build, and its parameters."""

    backend: Literal["classical"] = Field(default="classical", description="global description back end")
    classical: PixelFeatureConfig = Field(
        default_factory=PixelFeatureConfig, description="per-pixel features of the classical back end"
    )
    pyramid_levels: int = Field(
        default=1,
        ge=1,
        le=4,
        description="spatial pyramid levels (1 = whole image only, rotation invariant; 2 adds a 2x2 grid, ...)",
    )
    gem_p: float = Field(default=3.0, ge=1, description="generalized-mean exponent of the pooling (1 = average)")

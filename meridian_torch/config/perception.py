"""Validated configuration of the perception back ends (segmenter, segment and global describers).

Each config names a `backend` and carries one block per back end, so neural back ends add a block
and a `Literal` value without touching the classical ones. Only pydantic is imported here.
"""

from __future__ import annotations

from typing import Any, Literal, get_args

from pydantic import Field

from meridian_torch.config.base import StrictModel

__all__ = [
    "ModelWeightsConfig",
    "ClassicalSegmenterConfig",
    "SamSegmenterConfig",
    "FastSamConfig",
    "SegmenterConfig",
    "PixelFeatureConfig",
    "Dinov2Architecture",
    "Dinov2DescriptorConfig",
    "DescriptorConfig",
    "AnyLocConfig",
    "GemConfig",
    "GlobalDescriptorConfig",
    "OnnxGraphsConfig",
    "active_backend_dict",
]

# DINOv2 ViT-S/B/L/G with patch 14; "_reg" adds 4 register tokens; "tiny" is for tests and CI.
Dinov2Architecture = Literal[
    "vits14", "vitb14", "vitl14", "vitg14", "vits14_reg", "vitb14_reg", "vitl14_reg", "vitg14_reg", "tiny", "tiny_reg"
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


class ModelWeightsConfig(StrictModel):
    """Where a model's weights come from: a local file (never downloaded; models/README.md lists
    them), or (tests and CI only) random weights from a seed."""

    weights_path: str | None = Field(default=None, description="local weights file (the model's class says which kind)")
    random_weights_seed: int | None = Field(
        default=None, description="tests/CI only: random weights from this seed when weights_path is null"
    )


class SamSegmenterConfig(ModelWeightsConfig):
    """Segment Anything's automatic mask generator (reference aerial segmenter: ViT-L), from an
    official sam_vit_*.pth checkpoint.

    Generator defaults are the reference's aerial settings (SAM defaults where it sets none); the
    official crop layers and small-region clean-up are off in the reference and not implemented.
    """

    architecture: Literal["vit_b", "vit_l", "vit_h", "tiny"] = Field(
        default="vit_l", description="SAM image encoder size (reference: vit_l, sam_vit_l_0b3195.pth); tiny: tests only"
    )
    downsample_factor: float = Field(
        default=5.0, ge=1, description="images are shrunk by this factor per axis (bilinear) before SAM (reference: 5)"
    )
    points_per_side: int = Field(default=32, ge=1, description="prompt grid is points_per_side^2 points (SAM default)")
    points_per_batch: int = Field(default=64, ge=1, description="prompts per mask-decoder call, across images")
    encoder_batch_size: int = Field(
        default=1, ge=1, description="images per image-encoder call (ViT-L global attention: ~2 GB per image)"
    )
    pred_iou_thresh: float = Field(default=0.85, description="keep masks whose predicted IoU is above this (reference)")
    stability_score_thresh: float = Field(
        default=0.85, description="keep masks whose stability score is at least this (reference)"
    )
    stability_score_offset: float = Field(
        default=1.0, gt=0, description="logit offset of the stability score's two thresholds (SAM default)"
    )
    box_nms_thresh: float = Field(
        default=0.7, gt=0, le=1, description="box IoU above which the lower-scored duplicate is dropped (SAM default)"
    )


class FastSamConfig(ModelWeightsConfig):
    """FastSAM (YOLOv8-seg) exported to ONNX by its owner (e.g. models/FastSAM-x.onnx), run with
    onnxruntime (reference ground segmenter); random weights are a tiny stand-in graph.

    Letterboxing, confidence filter, NMS and prototype masks are ours.
    """

    imgsz: int = Field(default=1024, ge=32, description="frames are letterboxed to fit this size, px (reference: 1024)")
    conf: float = Field(default=0.2, ge=0, le=1, description="minimum detection confidence (reference: 0.2)")
    iou: float = Field(default=0.9, gt=0, le=1, description="NMS box IoU above which the weaker box goes (reference: 0.9)")
    max_det: int = Field(default=300, ge=1, description="at most this many masks per frame (YOLO default)")
    stride: int = Field(default=32, ge=1, description="dynamic-size graphs: letterbox canvas is a multiple of this")


class SegmenterConfig(StrictModel):
    """Which segmentation back end to build, and its parameters."""

    backend: Literal["classical", "sam", "fastsam"] = Field(default="classical", description="segmentation back end")
    classical: ClassicalSegmenterConfig = Field(
        default_factory=ClassicalSegmenterConfig, description="parameters of the classical back end"
    )
    sam: SamSegmenterConfig = Field(
        default_factory=SamSegmenterConfig, description="parameters of the Segment Anything back end"
    )
    fastsam: FastSamConfig = Field(
        default_factory=FastSamConfig, description="parameters of the FastSAM (ONNX) back end"
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


class _Dinov2Weights(ModelWeightsConfig):
    """Which DINOv2 to load: an official (facebookresearch) or Hugging Face checkpoint file
    (.pth/.pt/.safetensors), or seeded random weights. Blocks naming the same model share one
    instance."""

    architecture: Dinov2Architecture = Field(default="vitl14", description="DINOv2 backbone")


class Dinov2DescriptorConfig(_Dinov2Weights):
    """DINOv2 final patch features averaged over each mask (reference: dinov2-large, short side 256)."""

    short_side_px: int = Field(
        default=256, ge=14, description="images are resized to this short side (both sides multiples of 14)"
    )


class DescriptorConfig(StrictModel):
    """Which per-segment describer to build, and its parameters."""

    backend: Literal["classical", "dinov2"] = Field(default="classical", description="segment description back end")
    classical: PixelFeatureConfig = Field(
        default_factory=PixelFeatureConfig, description="parameters of the classical back end"
    )
    dinov2: Dinov2DescriptorConfig = Field(
        default_factory=Dinov2DescriptorConfig, description="parameters of the DINOv2 back end"
    )


class AnyLocConfig(_Dinov2Weights):
    """AnyLoc: L2-normalized facet tokens of one DINOv2 block, VLAD over a fitted vocabulary.

    Paper: ViT-G/14, block 31, value facet, 32 clusters (AnyLoc's urban c_centers.pt).
    """

    architecture: Dinov2Architecture = Field(default="vitg14", description="DINOv2 backbone (paper: vitg14)")
    layer: int = Field(default=31, ge=0, description="0-based block whose facet is read (paper: 31)")
    facet: Literal["query", "key", "value", "token"] = Field(default="value", description="attention facet (paper: value)")
    num_clusters: int = Field(default=32, ge=1, description="vocabulary size fitted by fit-vocabulary (paper: 32)")
    vocabulary_path: str | None = Field(
        default=None,
        description="cluster centres: AnyLoc's c_centers.pt or a fit-vocabulary file (random unit centres "
        "from random_weights_seed if null, tests only)",
    )
    resize_short_side_px: int | None = Field(
        default=None, ge=14, description="null: native resolution centre-cropped to multiples of 14 (AnyLoc)"
    )


class GemConfig(_Dinov2Weights):
    """DINO-GeM: generalized mean of DINOv2 final patch features (the reference's fast option)."""

    short_side_px: int = Field(default=256, ge=14, description="images are resized to this short side")
    p: float = Field(default=3.0, ge=1, description="generalized-mean exponent (reference: 3)")


class GlobalDescriptorConfig(StrictModel):
    """Which image (place-recognition) describer to build, and its parameters."""

    backend: Literal["classical", "anyloc", "gem"] = Field(
        default="classical", description="global description back end"
    )
    classical: PixelFeatureConfig = Field(
        default_factory=PixelFeatureConfig, description="per-pixel features of the classical back end"
    )
    anyloc: AnyLocConfig = Field(default_factory=AnyLocConfig, description="parameters of the AnyLoc-VLAD back end")
    gem: GemConfig = Field(default_factory=GemConfig, description="parameters of the DINOv2-GeM back end")
    pyramid_levels: int = Field(
        default=1,
        ge=1,
        le=4,
        description="spatial pyramid levels (1 = whole image only, rotation invariant; 2 adds a 2x2 grid, ...)",
    )
    gem_p: float = Field(default=3.0, ge=1, description="generalized-mean exponent of the pooling (1 = average)")


class OnnxGraphsConfig(StrictModel):
    """Graphs written by `meridian-torch export` that the ground pipeline runs with onnxruntime when
    `perception.ground_engine` is onnx (the segmenter is then FastSAM, itself an ONNX graph, or classical)."""

    dinov2_dense_path: str | None = Field(
        default=None, description="dinov2-dense graph of descriptor.dinov2 (also used by global_descriptor gem)"
    )
    anyloc_facet_path: str | None = Field(default=None, description="anyloc-facet graph of global_descriptor.anyloc")
    vlad_head_path: str | None = Field(default=None, description="vlad-head graph of global_descriptor.anyloc")


def active_backend_dict(block: StrictModel) -> dict[str, Any]:
    """A segmenter/describer config as JSON without the blocks of back ends it does not use.

    Map and submap files store (and compare) this, so adding or changing an unused back end's
    options never invalidates them.
    """
    data = block.model_dump(mode="json")
    names = get_args(type(block).model_fields["backend"].annotation)
    return {key: value for key, value in data.items() if key not in names or key == block.backend}


class PerceptionConfig(StrictModel):
    """Back ends of segmentation and description; aerial and ground share the describers so
    that their descriptors are comparable."""

    aerial_segmenter: SegmenterConfig = SegmenterConfig()
    ground_segmenter: SegmenterConfig = SegmenterConfig()
    descriptor: DescriptorConfig = DescriptorConfig()
    global_descriptor: GlobalDescriptorConfig = GlobalDescriptorConfig()
    ground_engine: Literal["torch", "onnx"] = Field(
        default="torch",
        description="onnx: the ground pipeline's segmenter and describers run exported graphs with onnxruntime only",
    )
    onnx: OnnxGraphsConfig = OnnxGraphsConfig()


__all__ += ["PerceptionConfig"]

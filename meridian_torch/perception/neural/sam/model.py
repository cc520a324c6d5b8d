"""Segment Anything models: architectures by name, builders, strict loading of the official
`sam_vit_{b,l,h}_*.pth` files, and the two modules the ONNX export wraps.

Nothing is downloaded: `load_sam` reads a local checkpoint whose keys and shapes must match the
architecture exactly, or (tests and CI only) initializes from a seed.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from meridian_torch.perception.neural.sam.image_encoder import ImageEncoderViT
from meridian_torch.perception.neural.sam.mask_decoder import MaskDecoder, TwoWayTransformer
from meridian_torch.perception.neural.sam.prompt_encoder import PromptEncoder
from meridian_torch.perception.neural.weights import initialize_weights

__all__ = [
    "SamArchitecture",
    "SAM_ARCHITECTURES",
    "Sam",
    "build_sam",
    "load_sam",
    "SamImageEncoderExport",
    "SamPromptDecoderExport",
    "resize_8bit",
]


@dataclass(frozen=True)
class SamArchitecture:
    """Every size of a SAM model; the official models differ only in the encoder fields."""

    encoder_embed_dim: int
    encoder_depth: int
    encoder_num_heads: int
    encoder_global_attn_indexes: tuple[int, ...]
    encoder_window_size: int = 14
    image_size: int = 1024
    patch_size: int = 16
    prompt_embed_dim: int = 256
    mask_in_chans: int = 16
    decoder_depth: int = 2
    decoder_num_heads: int = 8
    decoder_mlp_dim: int = 2048
    iou_head_hidden_dim: int = 256

    @property
    def embedding_size(self) -> int:
        """Side of the image-embedding grid."""
        return self.image_size // self.patch_size


SAM_ARCHITECTURES: dict[str, SamArchitecture] = {
    "vit_b": SamArchitecture(768, 12, 12, (2, 5, 8, 11)),
    "vit_l": SamArchitecture(1024, 24, 16, (5, 11, 17, 23)),
    "vit_h": SamArchitecture(1280, 32, 16, (7, 15, 23, 31)),
    # tests and CI: every code path of the real models (windows with padding, global blocks,
    # relative positions, two decoder layers) at a size that runs in milliseconds
    "tiny": SamArchitecture(
        encoder_embed_dim=32,
        encoder_depth=2,
        encoder_num_heads=2,
        encoder_global_attn_indexes=(1,),
        encoder_window_size=3,
        image_size=128,
        patch_size=16,
        prompt_embed_dim=32,
        mask_in_chans=8,
        decoder_depth=2,
        decoder_num_heads=2,
        decoder_mlp_dim=64,
        iou_head_hidden_dim=32,
    ),
}

# normalization of 0..255 RGB, as the official models were trained
_PIXEL_MEAN = (123.675, 116.28, 103.53)
_PIXEL_STD = (58.395, 57.12, 57.375)


class Sam(nn.Module):
    """Image encoder, prompt encoder and mask decoder with the official parameter names."""

    def __init__(self, architecture: SamArchitecture) -> None:
        super().__init__()
        a = architecture
        self.architecture = a
        self.image_encoder = ImageEncoderViT(
            img_size=a.image_size,
            patch_size=a.patch_size,
            embed_dim=a.encoder_embed_dim,
            depth=a.encoder_depth,
            num_heads=a.encoder_num_heads,
            global_attn_indexes=a.encoder_global_attn_indexes,
            window_size=a.encoder_window_size,
            out_chans=a.prompt_embed_dim,
        )
        self.prompt_encoder = PromptEncoder(
            a.prompt_embed_dim, a.embedding_size, a.image_size, a.mask_in_chans
        )
        self.mask_decoder = MaskDecoder(
            a.prompt_embed_dim,
            TwoWayTransformer(a.decoder_depth, a.prompt_embed_dim, a.decoder_num_heads, a.decoder_mlp_dim),
            iou_head_hidden_dim=a.iou_head_hidden_dim,
        )
        # not in the checkpoints (the official model registers them non-persistent too)
        self.register_buffer("pixel_mean", torch.tensor(_PIXEL_MEAN).view(3, 1, 1), persistent=False)
        self.register_buffer("pixel_std", torch.tensor(_PIXEL_STD).view(3, 1, 1), persistent=False)

    @property
    def image_size(self) -> int:
        return self.architecture.image_size

    def input_size(self, height: int, width: int) -> tuple[int, int]:
        """Size (h, w) to which an image is resized so its longer side is `image_size` (official rounding)."""
        scale = self.image_size / max(height, width)
        return int(height * scale + 0.5), int(width * scale + 0.5)

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W) in [0, 1] -> encoder input (B, 3, S, S): resized, normalized, zero-padded.

        As the official predictor, which takes 8-bit images: pixels are rounded to 8-bit levels,
        the longer side is resized to S = image_size exactly as Pillow's 8-bit bilinear resize
        does (`resize_8bit`), and the padding is added after normalization, bottom and right.
        """
        h, w = self.input_size(*images.shape[-2:])
        levels = (images * 255.0).round().clamp(0, 255)
        if (h, w) != tuple(images.shape[-2:]):
            levels = resize_8bit(levels, (h, w))
        x = (levels - self.pixel_mean) / self.pixel_std
        return F.pad(x, (0, self.image_size - w, 0, self.image_size - h))

    def decode_points(
        self, image_embeddings: torch.Tensor, coords: torch.Tensor, labels: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Point prompts -> all mask logits (N, 4, 4h, 4w) at the low resolution and IoU predictions (N, 4).

        Args:
            image_embeddings: (1 or N, C, h, w) encoder output, one per prompt or shared.
            coords: (N, T, 2) points (x, y) in encoder-input pixels.
            labels: (N, T) point labels (1 positive, 0 negative, -1 padding).
        """
        sparse, dense = self.prompt_encoder(coords, labels)
        image_pe = self.prompt_encoder.dense_positional_encoding()
        return self.mask_decoder(image_embeddings, image_pe, sparse, dense)


_PRECISION_BITS = 22  # Pillow's fixed-point precision for 8-bit resampling


def _pillow_bilinear_weights(in_size: int, out_size: int) -> torch.Tensor:
    """(out_size, in_size) integer weights (float64) of Pillow's 8-bit bilinear resample along one axis.

    Pillow widens the triangle filter by the shrink factor (antialiasing), normalizes each output's
    taps to sum 1, then rounds them to `_PRECISION_BITS` fixed point.
    """
    scale = in_size / out_size
    filter_scale = max(scale, 1.0)
    support = filter_scale  # the bilinear filter's support is 1
    centres = (torch.arange(out_size, dtype=torch.float64) + 0.5) * scale
    first = (centres - support + 0.5).floor().clamp(min=0)  # (int) truncation of non-negative values
    last = (centres + support + 0.5).floor().clamp(max=in_size)
    x = torch.arange(in_size, dtype=torch.float64)
    taps = (1 - ((x[None] - centres[:, None] + 0.5) / filter_scale).abs()).clamp(min=0)
    taps = torch.where((x[None] >= first[:, None]) & (x[None] < last[:, None]), taps, 0)
    taps = taps / taps.sum(dim=1, keepdim=True)
    return (taps * (1 << _PRECISION_BITS) + 0.5).floor()


def resize_8bit(levels: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Resize 8-bit levels (B, C, H, W) (integers 0..255 as floats) like Pillow's bilinear resize.

    Pillow resizes horizontally, rounds to 8 bits, then vertically; with its integer weights the
    result is bit-exact in float64 (sums stay far below 2^53).
    """
    def axis_pass(x: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        summed = x @ weights.T.to(x.device)
        return torch.floor((summed + (1 << (_PRECISION_BITS - 1))) / (1 << _PRECISION_BITS)).clamp(0, 255)

    h, w = levels.shape[-2:]
    x = levels.double()
    if w != size[1]:
        x = axis_pass(x, _pillow_bilinear_weights(w, size[1]))
    if h != size[0]:
        x = axis_pass(x.transpose(-1, -2), _pillow_bilinear_weights(h, size[0])).transpose(-1, -2)
    return x.to(levels.dtype)


def build_sam(architecture: str | SamArchitecture) -> Sam:
    """An uninitialized SAM model of a named architecture ("vit_b", "vit_l", "vit_h", "tiny")."""
    if isinstance(architecture, str):
        if architecture not in SAM_ARCHITECTURES:
            raise ValueError(f"unknown SAM architecture {architecture!r}; known: {sorted(SAM_ARCHITECTURES)}")
        architecture = SAM_ARCHITECTURES[architecture]
    return Sam(architecture)


def load_sam(
    architecture: str | SamArchitecture,
    weights_path: str | os.PathLike[str] | None,
    random_weights_seed: int | None,
    what: str = "sam",
) -> Sam:
    """SAM in eval mode, the official checkpoint `weights_path` loaded strictly (or seeded random weights)."""
    sam = build_sam(architecture)
    initialize_weights(sam, weights_path, random_weights_seed, what)
    return sam


class SamImageEncoderExport(nn.Module):
    """Export view of the encoder: normalized, padded images (B, 3, S, S) -> embeddings (B, C, S/16, S/16)."""

    def __init__(self, sam: Sam) -> None:
        super().__init__()
        self.image_encoder = sam.image_encoder

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.image_encoder(images)


class SamPromptDecoderExport(nn.Module):
    """Export view of prompt encoder + mask decoder.

    (image_embeddings (1 or N, C, h, w), point_coords (N, T, 2) float in encoder-input pixels,
    point_labels (N, T) int64) -> (mask logits (N, K, 4h, 4w), iou predictions (N, K)), where K is
    3 (the multimask outputs the automatic generator uses) or 1 with `multimask_output=False`.
    The padding point is appended inside, so callers pass only their own points.
    """

    def __init__(self, sam: Sam, multimask_output: bool = True) -> None:
        super().__init__()
        self.sam = sam
        self.outputs = slice(1, None) if multimask_output else slice(0, 1)

    def forward(
        self, image_embeddings: torch.Tensor, point_coords: torch.Tensor, point_labels: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        masks, iou = self.sam.decode_points(image_embeddings, point_coords, point_labels)
        return masks[:, self.outputs], iou[:, self.outputs]

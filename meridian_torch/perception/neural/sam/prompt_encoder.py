"""SAM prompt encoder: random-Fourier positional encoding of point prompts, learnt point-type
embeddings, and the dense (mask) prompt path.

Parameter names follow the official checkpoints (`prompt_encoder.*`). Point labels are
-1 (padding, "not a point"), 0 (negative), 1 (positive), 2 and 3 (box corners); the forward
uses table look-ups and `torch.where` instead of in-place boolean indexing, so it exports to ONNX.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from meridian_torch.perception.neural.sam.image_encoder import LayerNorm2d

__all__ = ["PositionEmbeddingRandom", "PromptEncoder"]


class PositionEmbeddingRandom(nn.Module):
    """Positional encoding with random spatial frequencies (a fixed Gaussian matrix)."""

    def __init__(self, num_pos_feats: int) -> None:
        super().__init__()
        self.register_buffer("positional_encoding_gaussian_matrix", torch.randn(2, num_pos_feats))

    def encode(self, coords_unit: torch.Tensor) -> torch.Tensor:
        """(..., 2) coordinates in [0, 1] (x, y) -> (..., 2 * num_pos_feats) [sin, cos] features."""
        proj = (2 * coords_unit - 1) @ self.positional_encoding_gaussian_matrix
        proj = 2 * math.pi * proj
        return torch.cat([torch.sin(proj), torch.cos(proj)], dim=-1)

    def dense(self, h: int, w: int) -> torch.Tensor:
        """(C, h, w) encoding of the centres of an h x w grid."""
        matrix = self.positional_encoding_gaussian_matrix
        ys = (torch.arange(h, device=matrix.device, dtype=matrix.dtype) + 0.5) / h
        xs = (torch.arange(w, device=matrix.device, dtype=matrix.dtype) + 0.5) / w
        grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # (h, w, 2) as (x, y)
        return self.encode(grid).permute(2, 0, 1)


class PromptEncoder(nn.Module):
    """Embeds point prompts (sparse) and supplies the no-mask dense embedding."""

    def __init__(
        self, embed_dim: int, image_embedding_size: int, input_image_size: int, mask_in_chans: int
    ) -> None:
        super().__init__()
        self.embed_dim = embed_dim
        self.image_embedding_size = image_embedding_size
        self.input_image_size = input_image_size
        self.pe_layer = PositionEmbeddingRandom(embed_dim // 2)
        # positive/negative point, then the two box corners
        self.point_embeddings = nn.ModuleList(nn.Embedding(1, embed_dim) for _ in range(4))
        self.not_a_point_embed = nn.Embedding(1, embed_dim)
        # Mask prompts are never used; the layers stay so the official checkpoint loads strictly.
        self.mask_downscaling = nn.Sequential(
            nn.Conv2d(1, mask_in_chans // 4, kernel_size=2, stride=2),
            LayerNorm2d(mask_in_chans // 4),
            nn.GELU(),
            nn.Conv2d(mask_in_chans // 4, mask_in_chans, kernel_size=2, stride=2),
            LayerNorm2d(mask_in_chans),
            nn.GELU(),
            nn.Conv2d(mask_in_chans, embed_dim, kernel_size=1),
        )
        self.no_mask_embed = nn.Embedding(1, embed_dim)

    def dense_positional_encoding(self) -> torch.Tensor:
        """(1, C, h, w) positional encoding of the image-embedding grid."""
        return self.pe_layer.dense(self.image_embedding_size, self.image_embedding_size)[None]

    def embed_points(self, coords: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """Coordinates (N, T, 2) in encoder-input pixels (x, y), labels (N, T) int -> (N, T, C)."""
        unit = (coords.float() + 0.5) / self.input_image_size  # pixel centres, then [0, 1]
        pe = self.pe_layer.encode(unit)
        table = torch.cat([e.weight for e in self.point_embeddings], dim=0)  # (4, C)
        embedding = pe + table[labels.clamp(min=0).long()]
        return torch.where((labels == -1)[..., None], self.not_a_point_embed.weight, embedding)

    def no_mask_dense_embedding(self) -> torch.Tensor:
        """(1, C, h, w) dense embedding used when no mask prompt is given."""
        size = self.image_embedding_size
        return self.no_mask_embed.weight.reshape(1, -1, 1, 1).expand(1, -1, size, size)

    def forward(self, coords: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Point prompts -> sparse (N, T + 1, C) with the padding point appended, dense (1, C, h, w).

        The padding point (label -1) is what the official model appends when no box is given.
        """
        pad_coords = torch.zeros_like(coords[:, :1])
        pad_labels = torch.full_like(labels[:, :1], -1)
        coords = torch.cat([coords, pad_coords], dim=1)
        sparse = self.embed_points(coords, torch.cat([labels, pad_labels], dim=1))
        return sparse, self.no_mask_dense_embedding()

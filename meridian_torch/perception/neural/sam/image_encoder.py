"""SAM image encoder: a plain ViT with windowed and global attention, decomposed relative
position terms and a convolutional neck (the ViTDet backbone of Segment Anything).

Parameter names follow the official `sam_vit_*.pth` checkpoints (`image_encoder.*`). The encoder
always sees square `img_size` inputs (images are padded), so every relative-position index table
is fixed at construction and the forward has no data-dependent control flow (ONNX-friendly).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["LayerNorm2d", "MLPBlock", "ImageEncoderViT"]


class LayerNorm2d(nn.Module):
    """LayerNorm over the channel axis of (B, C, H, W) maps."""

    def __init__(self, num_channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(num_channels))
        self.bias = nn.Parameter(torch.zeros(num_channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = x.mean(1, keepdim=True)
        var = (x - mean).pow(2).mean(1, keepdim=True)
        x = (x - mean) / torch.sqrt(var + self.eps)
        return self.weight[:, None, None] * x + self.bias[:, None, None]


class MLPBlock(nn.Module):
    """Two linear layers with an activation in between (`lin1`, `lin2`)."""

    def __init__(self, dim: int, hidden_dim: int, activation: type[nn.Module] = nn.GELU) -> None:
        super().__init__()
        self.lin1 = nn.Linear(dim, hidden_dim)
        self.lin2 = nn.Linear(hidden_dim, dim)
        self.act = activation()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.lin2(self.act(self.lin1(x)))


def _relative_index(size: int) -> torch.Tensor:
    """(size, size) int64 table: row i, column j holds i - j + size - 1 (an index into rel_pos)."""
    coords = torch.arange(size)
    return coords[:, None] - coords[None, :] + (size - 1)


class Attention(nn.Module):
    """Multi-head self-attention over an (h, w) token grid with decomposed relative positions.

    The attention logit of query (i, j) and key (k, l) gets q . Rh[i - k] + q . Rw[j - l]
    (MViTv2), with one learnt table per axis of length 2 * size - 1.
    """

    def __init__(self, dim: int, num_heads: int, grid_size: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.rel_pos_h = nn.Parameter(torch.zeros(2 * grid_size - 1, self.head_dim))
        self.rel_pos_w = nn.Parameter(torch.zeros(2 * grid_size - 1, self.head_dim))
        self.register_buffer("rel_index", _relative_index(grid_size), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, h, w, C) -> (N, h, w, C); h = w = grid_size."""
        n, h, w, c = x.shape
        qkv = self.qkv(x).reshape(n, h * w, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)  # (N, heads, h*w, head_dim)
        r_q = q.reshape(n, self.num_heads, h, w, self.head_dim)
        rel_h = torch.einsum("nmhwc,hkc->nmhwk", r_q, self.rel_pos_h[self.rel_index])
        rel_w = torch.einsum("nmhwc,wkc->nmhwk", r_q, self.rel_pos_w[self.rel_index])
        # explicit attention (not F.scaled_dot_product_attention): a position bias would be as
        # large as the attention matrix anyway, and the explicit form exports with both ONNX exporters
        attn = ((q * self.head_dim**-0.5) @ k.transpose(-2, -1)).reshape(n, self.num_heads, h, w, h, w)
        attn = attn + rel_h[..., :, None] + rel_w[..., None, :]
        attn = attn.reshape(n, self.num_heads, h * w, h * w).softmax(dim=-1)
        out = (attn @ v).permute(0, 2, 1, 3).reshape(n, h, w, c)
        return self.proj(out)


class Block(nn.Module):
    """Pre-norm transformer block; `window_size` 0 means global attention."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, window_size: int, grid_size: int) -> None:
        super().__init__()
        self.window_size = window_size
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads, window_size if window_size > 0 else grid_size)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = MLPBlock(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = x
        x = self.norm1(x)
        if self.window_size > 0:
            b, h, w, c = x.shape
            s = self.window_size
            pad_h, pad_w = -h % s, -w % s
            # windows are zero-padded at the bottom/right, as in the official model
            x = F.pad(x, (0, 0, 0, pad_w, 0, pad_h))
            hp, wp = h + pad_h, w + pad_w
            x = x.reshape(b, hp // s, s, wp // s, s, c).transpose(2, 3).reshape(-1, s, s, c)
            x = self.attn(x)
            x = x.reshape(b, hp // s, wp // s, s, s, c).transpose(2, 3).reshape(b, hp, wp, c)[:, :h, :w]
        else:
            x = self.attn(x)
        x = shortcut + x
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    def __init__(self, patch_size: int, in_chans: int, embed_dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(in_chans, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).permute(0, 2, 3, 1)  # (B, h, w, C)


class ImageEncoderViT(nn.Module):
    """Normalized, padded images (B, 3, img_size, img_size) -> embeddings (B, out_chans, h, w).

    h = w = img_size / patch_size (64 for the official models).
    """

    def __init__(
        self,
        img_size: int,
        patch_size: int,
        embed_dim: int,
        depth: int,
        num_heads: int,
        global_attn_indexes: Sequence[int],
        window_size: int,
        out_chans: int,
        mlp_ratio: float = 4.0,
    ) -> None:
        super().__init__()
        self.img_size = img_size
        grid_size = img_size // patch_size
        self.patch_embed = PatchEmbed(patch_size, 3, embed_dim)
        self.pos_embed = nn.Parameter(torch.zeros(1, grid_size, grid_size, embed_dim))
        self.blocks = nn.ModuleList(
            Block(embed_dim, num_heads, mlp_ratio, 0 if i in global_attn_indexes else window_size, grid_size)
            for i in range(depth)
        )
        self.neck = nn.Sequential(
            nn.Conv2d(embed_dim, out_chans, kernel_size=1, bias=False),
            LayerNorm2d(out_chans),
            nn.Conv2d(out_chans, out_chans, kernel_size=3, padding=1, bias=False),
            LayerNorm2d(out_chans),
        )

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = self.patch_embed(images) + self.pos_embed
        for block in self.blocks:
            x = block(x)
        return self.neck(x.permute(0, 3, 1, 2))

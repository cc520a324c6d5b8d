"""DINOv2 vision transformers (patch 14) with the facebookresearch/dinov2 state-dict layout.

The module tree mirrors the official `DinoVisionTransformer` (hub models, `block_chunks=0`), so an
official checkpoint (`dinov2_vit{s,b,l,g}14[_reg4]_pretrain.pth`) loads with `load_strict`.
Hugging Face `facebook/dinov2-*` files are renamed by `convert_hf_state_dict` first.

Everything downstream reads features through explicit methods instead of forward hooks:
`intermediate_layers` (outputs of chosen blocks), `facet` (query / key / value of a block's attention
input projection, or the block's output token) and `dense_features` (final normalized patch grid).
Forward passes take tensors only and are traceable with a dynamic image size: the position
embedding is resampled with bicubic matrices built from `torch.arange`, not Python arithmetic on
the input shape.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from meridian_torch.errors import ConfigError
from meridian_torch.perception.neural.weights import initialize_weights, load_strict, read_checkpoint

__all__ = [
    "ARCHITECTURES",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "Facet",
    "VitArchitecture",
    "DinoVisionTransformer",
    "DinoDenseFeatures",
    "imagenet_normalize",
    "build_dinov2",
    "load_dinov2",
    "convert_hf_state_dict",
    "is_hf_state_dict",
    "bicubic_resampling_matrix",
    "resize_to_patch_multiple",
    "center_crop_to_patch_multiple",
]

PATCH_SIZE = 14
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

Facet = Literal["query", "key", "value", "token"]


@dataclass(frozen=True)
class VitArchitecture:
    """Size parameters of one DINOv2 backbone; `pos_grid` is the side of the trained position grid."""

    embed_dim: int
    depth: int
    num_heads: int
    ffn: Literal["mlp", "swiglu"] = "mlp"
    num_register_tokens: int = 0
    pos_grid: int = 37  # the hub models were trained at 518 px = 37 patches


def _with_registers(arch: VitArchitecture) -> VitArchitecture:
    return VitArchitecture(arch.embed_dim, arch.depth, arch.num_heads, arch.ffn, 4, arch.pos_grid)


_PLAIN = {
    "vits14": VitArchitecture(384, 12, 6),
    "vitb14": VitArchitecture(768, 12, 12),
    "vitl14": VitArchitecture(1024, 24, 16),
    "vitg14": VitArchitecture(1536, 40, 24, ffn="swiglu"),
    # tests and CI only: same layout, a few thousand parameters per block
    "tiny": VitArchitecture(48, 3, 3, pos_grid=4),
}
ARCHITECTURES: dict[str, VitArchitecture] = {
    **_PLAIN,
    **{f"{name}_reg": _with_registers(arch) for name, arch in _PLAIN.items()},
}


class PatchEmbed(nn.Module):
    """Non-overlapping 14x14 patches -> tokens; pixels past the last whole patch are ignored."""

    def __init__(self, embed_dim: int, patch_size: int = PATCH_SIZE) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> (B, D, H // 14, W // 14)."""
        return self.proj(images)


class Attention(nn.Module):
    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.attend(self.qkv(x))

    def attend(self, qkv: torch.Tensor) -> torch.Tensor:
        """Attention from the packed input projection (B, N, 3D) -> (B, N, D)."""
        b, n, _ = qkv.shape
        q, k, v = qkv.reshape(b, n, 3, self.num_heads, -1).permute(2, 0, 3, 1, 4).unbind(0)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(b, n, -1))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class SwiGLUFFN(nn.Module):
    """ViT-G's feed-forward: one packed input projection `w12`, SiLU(first half) * second half, `w3`."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        hidden = (int(hidden * 2 / 3) + 7) // 8 * 8  # the official sizing rule (4096 for ViT-G)
        self.w12 = nn.Linear(dim, 2 * hidden)
        self.w3 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x1, x2 = self.w12(x).chunk(2, dim=-1)
        return self.w3(F.silu(x1) * x2)


class LayerScale(nn.Module):
    def __init__(self, dim: int, init_value: float = 1e-5) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), init_value))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Block(nn.Module):
    def __init__(self, dim: int, num_heads: int, ffn: str, layer_scale: bool) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads)
        self.ls1 = LayerScale(dim) if layer_scale else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = SwiGLUFFN(dim, 4 * dim) if ffn == "swiglu" else Mlp(dim, 4 * dim)
        self.ls2 = LayerScale(dim) if layer_scale else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.finish(x, self.attn.qkv(self.norm1(x)))

    def finish(self, x: torch.Tensor, qkv: torch.Tensor) -> torch.Tensor:
        """The block output given its input `x` and the attention input projection `qkv` of `x`."""
        x = x + self.ls1(self.attn.attend(qkv))
        return x + self.ls2(self.mlp(self.norm2(x)))


def _cubic_taps(t: torch.Tensor) -> torch.Tensor:
    """Weights of the 4 taps at offsets -1, 0, 1, 2 for fractional positions t (PyTorch's A = -0.75)."""
    a = -0.75

    def near(x: torch.Tensor) -> torch.Tensor:  # |x| <= 1
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x: torch.Tensor) -> torch.Tensor:  # 1 < |x| < 2
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return torch.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], dim=-1)


def bicubic_resampling_matrix(n_out: int, n_in: int, offset: torch.Tensor) -> torch.Tensor:
    """(n_out, n_in) matrix A such that A @ v resamples v like F.interpolate(mode="bicubic").

    The scale factor is (n_out + offset) / n_in, as in DINOv2's position-embedding interpolation
    (offset 0.1; offset 0 is a plain resize to n_out). `offset` is a scalar tensor that sets the
    dtype; the output size enters only through `torch.arange`, so tracing keeps `n_out` symbolic.
    """
    dst = torch.arange(n_out, dtype=offset.dtype, device=offset.device)
    n = dst[-1] + 1  # n_out as a tensor
    src = (dst + 0.5) * (n_in / (n + offset)) - 0.5
    start = torch.floor(src)
    weights = _cubic_taps(src - start)  # (n_out, 4)
    taps = (start[:, None] + torch.arange(-1, 3, device=offset.device)).clamp(0, n_in - 1)
    cols = torch.arange(n_in, dtype=offset.dtype, device=offset.device)
    return ((taps[..., None] == cols).to(weights.dtype) * weights[..., None]).sum(dim=1)


class DinoVisionTransformer(nn.Module):
    """DINOv2 ViT, patch 14. Inputs are ImageNet-normalized images (B, 3, H, W).

    Tokens are [CLS, registers..., patches...]; only CLS and patches get position embeddings.
    Images whose sides are not multiples of 14 lose their last partial patch row/column.
    """

    def __init__(
        self,
        *,
        embed_dim: int,
        depth: int,
        num_heads: int,
        ffn: Literal["mlp", "swiglu"] = "mlp",
        num_register_tokens: int = 0,
        pos_grid: int = 37,
        layer_scale: bool = True,
        interpolate_offset: float = 0.1,
    ) -> None:
        super().__init__()
        self.embed_dim = embed_dim
        self.num_register_tokens = num_register_tokens
        self.num_prefix_tokens = 1 + num_register_tokens
        self.pos_grid = pos_grid
        self.interpolate_offset = interpolate_offset
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + pos_grid * pos_grid, embed_dim))
        if num_register_tokens:
            self.register_tokens = nn.Parameter(torch.zeros(1, num_register_tokens, embed_dim))
        self.mask_token = nn.Parameter(torch.zeros(1, embed_dim))  # training only; kept for strict loading
        self.patch_embed = PatchEmbed(embed_dim)
        self.blocks = nn.ModuleList(Block(embed_dim, num_heads, ffn, layer_scale) for _ in range(depth))
        self.norm = nn.LayerNorm(embed_dim, eps=1e-6)

    @property
    def depth(self) -> int:
        return len(self.blocks)

    def patch_position_embedding(self, h: int, w: int) -> torch.Tensor:
        """(h * w, D) position embeddings of an h x w patch grid, resampled bicubically.

        As in the official model the trained grid is used unchanged when h = w = pos_grid, and
        otherwise resampled with scale (h + 0.1) / pos_grid (a historical offset that checkpoints
        were trained with). Both cases are one tensor expression, so a traced graph keeps h, w dynamic.
        """
        m = self.pos_grid
        dtype = torch.promote_types(self.pos_embed.dtype, torch.float32)  # resample half precision in float32
        grid = self.pos_embed[0, 1:].to(dtype).reshape(m, m, -1)
        rows = torch.arange(h, device=grid.device)
        cols = torch.arange(w, device=grid.device)
        native = ((rows[-1:] + 1 == m) & (cols[-1:] + 1 == m)).to(grid.dtype)[0]
        offset = self.interpolate_offset * (1.0 - native)
        resample_y = bicubic_resampling_matrix(h, m, offset)
        resample_x = bicubic_resampling_matrix(w, m, offset)
        out = torch.einsum("ip,pqd,jq->ijd", resample_y, grid, resample_x)
        return out.reshape(-1, grid.shape[-1]).to(self.pos_embed.dtype)

    def prepare_tokens(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> (B, 1 + R + h*w, D) tokens entering the first block."""
        x = self.patch_embed(images)
        b, _, h, w = x.shape
        pos = self.patch_position_embedding(h, w)
        patches = x.flatten(2).transpose(1, 2) + pos
        cls = (self.cls_token + self.pos_embed[:, :1]).expand(b, -1, -1)
        parts = [cls]
        if self.num_register_tokens:
            parts.append(self.register_tokens.expand(b, -1, -1))
        return torch.cat([*parts, patches], dim=1)

    def _check_layer(self, layer: int) -> int:
        if not -self.depth <= layer < self.depth:
            raise ValueError(f"layer {layer} out of range for a {self.depth}-block model")
        return layer % self.depth

    def patch_grid(self, tokens: torch.Tensor, images: torch.Tensor) -> torch.Tensor:
        """Patch tokens (B, 1 + R + h*w, D) -> (B, D, h, w), prefix tokens dropped."""
        h, w = images.shape[-2] // PATCH_SIZE, images.shape[-1] // PATCH_SIZE
        patches = tokens[:, self.num_prefix_tokens :]
        return patches.transpose(1, 2).reshape(patches.shape[0], -1, h, w)

    def intermediate_layers(
        self, images: torch.Tensor, layers: Sequence[int], norm: bool = True
    ) -> list[torch.Tensor]:
        """Outputs of the blocks `layers` (0-based, negative from the end) as (B, D, h, w) grids.

        `norm` applies the final LayerNorm, as the official `get_intermediate_layers(norm=True)`.
        Blocks after the deepest requested one are not run.
        """
        wanted = sorted({self._check_layer(i) for i in layers})
        x = self.prepare_tokens(images)
        found = {}
        for i, block in enumerate(self.blocks[: wanted[-1] + 1]):
            x = block(x)
            if i in wanted:
                found[i] = self.patch_grid(self.norm(x) if norm else x, images)
        return [found[self._check_layer(i)] for i in layers]

    def dense_features(self, images: torch.Tensor) -> torch.Tensor:
        """Final normalized patch tokens (B, D, h, w), the Hugging Face `last_hidden_state` patches."""
        return self.intermediate_layers(images, [-1], norm=True)[0]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.dense_features(images)

    def facet(self, images: torch.Tensor, layer: int, facet: Facet) -> torch.Tensor:
        """Patch tokens (B, h*w, D) of one facet of block `layer`; blocks after it are not run.

        query / key / value are the thirds of the attention input projection (heads concatenated,
        as AnyLoc reads them); token is the block output. Prefix tokens are dropped.
        """
        layer = self._check_layer(layer)
        x = self.prepare_tokens(images)
        for block in self.blocks[:layer]:
            x = block(x)
        block = self.blocks[layer]
        qkv = block.attn.qkv(block.norm1(x))
        if facet == "token":
            out = block.finish(x, qkv)
        else:
            d = self.embed_dim
            part = {"query": 0, "key": 1, "value": 2}[facet]
            out = qkv[..., part * d : (part + 1) * d]
        return out[:, self.num_prefix_tokens :]


def imagenet_normalize(images: torch.Tensor) -> torch.Tensor:
    """RGB in [0, 1] -> ImageNet mean/std normalized (the DINOv2 training convention)."""
    mean = torch.tensor(IMAGENET_MEAN, device=images.device, dtype=images.dtype).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=images.device, dtype=images.dtype).view(1, 3, 1, 1)
    return (images - mean) / std


class DinoDenseFeatures(nn.Module):
    """Export wrapper: RGB images in [0, 1] (B, 3, H, W) -> final dense patch features (B, D, H//14, W//14).

    Resizing (`resize_to_patch_multiple`) happens before; ImageNet normalization happens here.
    """

    def __init__(self, backbone: DinoVisionTransformer) -> None:
        super().__init__()
        self.backbone = backbone

    @property
    def dim(self) -> int:
        return self.backbone.embed_dim

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.backbone.dense_features(imagenet_normalize(images))


def resize_to_patch_multiple(images: torch.Tensor, short_side_px: int) -> torch.Tensor:
    """Resize (bicubic, antialiased, clamped to [0, 1]) so the short side is about `short_side_px`.

    Both sides are rounded to multiples of 14, so the patch grid covers the whole image and maps
    back onto it exactly (the aspect ratio changes by at most 7 px over the short side).
    """
    h, w = images.shape[-2:]
    scale = short_side_px / min(h, w)
    size = tuple(max(1, round(n * scale / PATCH_SIZE)) * PATCH_SIZE for n in (h, w))
    if size == (h, w):
        return images
    return F.interpolate(images, size=size, mode="bicubic", align_corners=False, antialias=True).clamp(0, 1)


def center_crop_to_patch_multiple(images: torch.Tensor) -> torch.Tensor:
    """Centre crop to the largest multiples of 14 in each side (AnyLoc's input convention)."""
    h, w = images.shape[-2:]
    if h < PATCH_SIZE or w < PATCH_SIZE:
        raise ValueError(f"image of {h}x{w} px is smaller than one {PATCH_SIZE}x{PATCH_SIZE} patch")
    ch, cw = h // PATCH_SIZE * PATCH_SIZE, w // PATCH_SIZE * PATCH_SIZE
    top, left = (h - ch) // 2, (w - cw) // 2
    return images[..., top : top + ch, left : left + cw]


def build_dinov2(architecture: str) -> DinoVisionTransformer:
    """A randomly initialized DINOv2 of the named architecture (see ARCHITECTURES), in eval mode."""
    try:
        arch = ARCHITECTURES[architecture]
    except KeyError:
        known = ", ".join(sorted(ARCHITECTURES))
        raise ValueError(f"unknown DINOv2 architecture {architecture!r}; known: {known}") from None
    return DinoVisionTransformer(
        embed_dim=arch.embed_dim,
        depth=arch.depth,
        num_heads=arch.num_heads,
        ffn=arch.ffn,
        num_register_tokens=arch.num_register_tokens,
        pos_grid=arch.pos_grid,
    ).eval()


_HF_RENAMES = [
    (r"^embeddings\.cls_token$", "cls_token"),
    (r"^embeddings\.mask_token$", "mask_token"),
    (r"^embeddings\.position_embeddings$", "pos_embed"),
    (r"^embeddings\.register_tokens$", "register_tokens"),
    (r"^embeddings\.patch_embeddings\.projection\.", "patch_embed.proj."),
    (r"^encoder\.layer\.(\d+)\.attention\.output\.dense\.", r"blocks.\1.attn.proj."),
    (r"^encoder\.layer\.(\d+)\.layer_scale(\d)\.lambda1$", r"blocks.\1.ls\2.gamma"),
    (r"^encoder\.layer\.(\d+)\.mlp\.weights_in\.", r"blocks.\1.mlp.w12."),
    (r"^encoder\.layer\.(\d+)\.mlp\.weights_out\.", r"blocks.\1.mlp.w3."),
    (r"^encoder\.layer\.(\d+)\.", r"blocks.\1."),  # norm1, norm2, mlp.fc1, mlp.fc2
    (r"^layernorm\.", "norm."),
]
_HF_QKV = re.compile(r"^encoder\.layer\.(\d+)\.attention\.attention\.(query|key|value)\.(weight|bias)$")


def is_hf_state_dict(state: dict[str, torch.Tensor]) -> bool:
    return any(k.startswith(("embeddings.", "dinov2.embeddings.")) for k in state)


def convert_hf_state_dict(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename a Hugging Face `Dinov2Model` (or `Dinov2WithRegistersModel`) state dict to the official layout.

    Separate query/key/value projections are packed into `attn.qkv` (in that order). Keys that
    have no official counterpart keep their name, so strict loading reports them.
    """
    state = {k.removeprefix("dinov2."): v for k, v in state.items()}
    out: dict[str, torch.Tensor] = {}
    qkv: dict[tuple[str, str], dict[str, torch.Tensor]] = {}
    for key, value in state.items():
        if match := _HF_QKV.match(key):
            layer, part, kind = match.groups()
            qkv.setdefault((layer, kind), {})[part] = value
            continue
        for pattern, replacement in _HF_RENAMES:
            new, count = re.subn(pattern, replacement, key)
            if count:
                key = new
                break
        out[key] = value
    for (layer, kind), parts in qkv.items():
        if set(parts) != {"query", "key", "value"}:
            for part, value in parts.items():  # incomplete: leave the keys for strict loading to report
                out[f"encoder.layer.{layer}.attention.attention.{part}.{kind}"] = value
            continue
        out[f"blocks.{layer}.attn.qkv.{kind}"] = torch.cat([parts[p] for p in ("query", "key", "value")], dim=0)
    return out


def load_dinov2(
    architecture: str,
    weights_path: str | os.PathLike[str] | None,
    random_weights_seed: int | None,
    what: str,
) -> DinoVisionTransformer:
    """Build `architecture` and load a local official or Hugging Face checkpoint strictly (or seed it)."""
    if weights_path is None:
        if random_weights_seed is None:  # fail before building a large model
            raise ConfigError(f"{what}: set weights_path to a local checkpoint file (see models/README.md)")
        return initialize_weights(build_dinov2(architecture), None, random_weights_seed, what)
    state = read_checkpoint(weights_path)  # a missing file fails before the model is built
    if is_hf_state_dict(state):
        state = convert_hf_state_dict(state)
    model = build_dinov2(architecture)
    load_strict(model, state, weights_path)
    return model.eval()

"""Putative associations between one ground submap and P aerial patches (K_prim semantic neighbours).

Points are only ever associated with points and lines with lines. Every association is a pair
(ground index, aerial index) in a *unified per-side index space*: points come first, then lines.

- ground side: index `g < n_ground_points` is `ground.points_xy[g]`, otherwise it is
  `ground.line_endpoints[g - n_ground_points]`;
- aerial side: index `a < n_aerial_points` is `aerial.points_xy[p, a]`, otherwise it is
  `aerial.line_endpoints[p, a - n_aerial_points]`, where `n_aerial_points` is the *padded*
  point width of the batch (the same for every patch).

The association axis is laid out in two blocks shared by all patches: columns
`[0, n_point_assoc)` are point associations and `[n_point_assoc, m)` line associations. Inside
each block a patch's valid associations come first, sorted by (ground index, aerial index);
padding entries are invalid, carry the index -1 and cosine 0. The fixed block layout lets the
affinity evaluate each primitive-type combination only on its own sub-matrix.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F

from meridian_torch.matching.kernels import knn_picks
from meridian_torch.matching.particle_noise import mix, uniform
from meridian_torch.types import LineKind, PrimitiveBatch, PrimitiveSet

__all__ = ["Associations", "putative_associations", "line_keep_mask"]

Direction = Literal["ground_to_aerial", "union"]


@dataclass(frozen=True)
class Associations:
    """Putative associations of one ground submap against P aerial patches.

    Attributes:
        pairs: (P, m, 2) int64, (ground index, aerial index) in the unified index spaces
            (points first, then lines; see the module docstring); -1 where invalid.
        is_line: (P, m) bool, True for line-line associations (columns >= n_point_assoc).
        valid: (P, m) bool, False for padding.
        cosine: (P, m) cosine similarity of the two descriptors (0 where invalid).
        n_point_assoc: width of the point block of the association axis.
        n_ground_points: number of ground points (offset of ground line indices).
        n_aerial_points: padded number of aerial points (offset of aerial line indices).
    """

    pairs: torch.Tensor
    is_line: torch.Tensor
    valid: torch.Tensor
    cosine: torch.Tensor
    n_point_assoc: int
    n_ground_points: int
    n_aerial_points: int

    def __post_init__(self) -> None:
        n_patches, m = self.valid.shape
        if tuple(self.pairs.shape) != (n_patches, m, 2):
            raise ValueError(f"Associations.pairs: expected shape {(n_patches, m, 2)}, got {tuple(self.pairs.shape)}")
        for name in ("is_line", "cosine"):
            if tuple(getattr(self, name).shape) != (n_patches, m):
                raise ValueError(f"Associations.{name}: expected shape {(n_patches, m)}, got {tuple(getattr(self, name).shape)}")
        if not 0 <= self.n_point_assoc <= m:
            raise ValueError(f"Associations.n_point_assoc must lie in [0, {m}], got {self.n_point_assoc}")

    @property
    def num_patches(self) -> int:
        return int(self.valid.shape[0])

    @property
    def size(self) -> int:
        """m, the length of the association axis (padding included)."""
        return int(self.valid.shape[1])


def line_keep_mask(endpoints: torch.Tensor, kinds: torch.Tensor, min_length_m: float) -> torch.Tensor:
    """Lines usable for matching: segments at least `min_length_m` long; rays and infinite lines
    are kept whatever their length, unless their two defining points coincide (no direction).

    Shapes: endpoints (..., 2, 2), kinds (...) -> (...) bool.
    """
    length = (endpoints[..., 1, :] - endpoints[..., 0, :]).norm(dim=-1)
    long_enough = torch.where(kinds == int(LineKind.SEGMENT), length >= min_length_m, torch.ones_like(length, dtype=torch.bool))
    return long_enough & (length > 0)


# Fixed salt of the tie-break hash (independent of every generator).
_TIE_SALT = 0x7135

# (patch, ground, aerial) similarities ranked at once. All 609 patches of a map before its fix
# took up to 1.8 GiB in one piece; a patch's pairs do not depend on the other patches, so chunks
# give the same pairs (the similarity product may round differently in the last bit).
_SIMILARITY_ELEMENTS = 1 << 22


def _type_pairs(
    ground_desc: torch.Tensor,
    ground_ok: torch.Tensor,
    aerial_desc: torch.Tensor,
    aerial_ok: torch.Tensor,
    k: int,
    direction: Direction,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`_chunk_pairs` over chunks of patches, padded to the widest chunk (same result, bounded memory)."""
    step = max(1, _SIMILARITY_ELEMENTS // max(1, ground_ok.shape[0] * aerial_ok.shape[1]))
    chunks = [
        _chunk_pairs(ground_desc, ground_ok, aerial_desc[p : p + step], aerial_ok[p : p + step], k, direction)
        for p in range(0, max(aerial_ok.shape[0], 1), step)  # one (empty) chunk without patches
    ]
    width = max(c[0].shape[1] for c in chunks)

    def pad(x: torch.Tensor, value: float | bool) -> torch.Tensor:
        shape = (x.shape[0], width - x.shape[1], *x.shape[2:])
        return torch.cat([x, x.new_full(shape, value)], dim=1)

    return (
        torch.cat([pad(c[0], -1) for c in chunks]),
        torch.cat([pad(c[1], False) for c in chunks]),
        torch.cat([pad(c[2], 0.0) for c in chunks]),
    )


def tie_break_jitter(n_ground: int, n_aerial: int, device: torch.device) -> torch.Tensor:
    """(G, A) float64 in [0, 2^-40): a fixed hash of each (ground, aerial) index pair.

    Added to similarities rounded to float32, it orders exact ties (primitives of one segment
    share its descriptor) without reordering distinct values above 2^-16: each ground primitive
    takes its own pseudo-random share of a tied segment's primitives, the same whatever the
    batch (`torch.topk` orders ties by padded width). Above a cosine near 0.5 float64 keeps only
    ~13 bits of it, so a few ties remain (KITTI 09, one submap against 609 patches: 22 of 28 014
    ground-line rows tied at the k-th place); the compiled picks give those to the lower index.
    """
    g = torch.arange(n_ground, device=device, dtype=torch.int64)[:, None]
    a = torch.arange(n_aerial, device=device, dtype=torch.int64)[None, :]
    return uniform(mix((g << 32) + a + _TIE_SALT), torch.float64) * 2.0**-40


def _chunk_pairs(
    ground_desc: torch.Tensor,
    ground_ok: torch.Tensor,
    aerial_desc: torch.Tensor,
    aerial_ok: torch.Tensor,
    k: int,
    direction: Direction,
    compiled: bool | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """K-NN pairs of one primitive type for all patches at once. `compiled` (default: on CPU
    tensors) ranks and picks in one compiled pass (`kernels.knn_picks`), else through torch's topk
    and sorts (other devices): the same pairs, but for exact ties of the ranked values, which the
    compiled pass gives to the lower index and topk to its own order.

    Shapes: ground_desc (G, D), ground_ok (G,), aerial_desc (P, A, D), aerial_ok (P, A) ->
    pairs (P, mt, 2) local indices (-1 in padding), valid (P, mt), cosine (P, mt).
    """
    n_patches, n_aerial = aerial_ok.shape
    n_ground = ground_ok.shape[0]
    # A matrix product rounds equal columns differently by position and batch shape: computed in
    # float64 and rounded to float32, equal descriptors tie exactly, and the jitter orders them
    # (float32 + float64 adds the exact float32 value).
    cosine = torch.einsum(
        "gd,pad->pga", F.normalize(ground_desc.double(), dim=-1), F.normalize(aerial_desc.double(), dim=-1)
    )
    jitter = tie_break_jitter(n_ground, n_aerial, cosine.device)
    union = direction == "union"
    if cosine.device.type == "cpu" if compiled is None else compiled:
        flat, counts = knn_picks(cosine.numpy(), jitter.numpy(), ground_ok.numpy(), aerial_ok.numpy(),
                                 min(k, n_aerial), min(k, n_ground) if union else 0)
        width = int(counts.max()) if n_patches else 0
        counts, flat = torch.from_numpy(counts), torch.from_numpy(flat[:, :width])
    else:
        flat, counts, width = _topk_picks(cosine, jitter, ground_ok, aerial_ok, k, union)
    valid = torch.arange(width, device=cosine.device)[None, :] < counts[:, None]
    order = flat.masked_fill(~valid, 0)
    ground_index, aerial_index = order // max(n_aerial, 1), order % max(n_aerial, 1)
    pairs = torch.stack([ground_index, aerial_index], dim=-1).masked_fill(~valid[..., None], -1)
    # Indexed where einsum left it: flattening its (strided) output first copied all P G A values.
    cos = cosine[torch.arange(n_patches, device=cosine.device)[:, None], ground_index, aerial_index]
    cos = cos.to(ground_desc.dtype).masked_fill(~valid, 0.0)
    return pairs, valid, cos


def _topk_picks(
    cosine: torch.Tensor, jitter: torch.Tensor, ground_ok: torch.Tensor, aerial_ok: torch.Tensor, k: int, union: bool
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """`kernels.knn_picks` as torch ops: flat picks (P, W) ascending (padding beyond the counts),
    counts (P,) and W."""
    n_patches, n_ground, n_aerial = cosine.shape
    ranked = cosine.float() + jitter
    ranked.masked_fill_(~ground_ok[None, :, None], float("-inf")).masked_fill_(~aerial_ok[:, None, :], float("-inf"))
    # The picks as flat (ground-major) indices g * A + a; k is clipped to the size of the other
    # side, and picks that land on unusable pairs are dropped below.
    device, n_pairs = cosine.device, n_ground * n_aerial
    picks = [torch.zeros(n_patches, 0, dtype=torch.int64, device=device)]  # none when k clips to 0
    k_aerial = min(k, n_aerial)
    if k_aerial > 0:
        top = ranked.topk(k_aerial, dim=2).indices
        picks.append((top + n_aerial * torch.arange(n_ground, device=device)[:, None]).flatten(1))
    k_ground = min(k, n_ground)
    union = union and k_ground > 0
    if union:
        top = ranked.topk(k_ground, dim=1).indices
        picks.append((top * n_aerial + torch.arange(n_aerial, device=device)).flatten(1))
    flat = torch.cat(picks, dim=1)
    usable = ground_ok[flat // max(n_aerial, 1)] & aerial_ok.gather(1, flat % max(n_aerial, 1))
    # Each patch's selected pairs first, in ascending flat order, then the rest (as n_pairs).
    flat = flat.masked_fill(~usable, n_pairs).sort(dim=1).values
    if union:  # a pair picked from both sides once
        flat[:, 1:].masked_fill_(flat[:, 1:] == flat[:, :-1], n_pairs)
        flat = flat.sort(dim=1).values
    counts = (flat < n_pairs).sum(dim=1)
    width = int(counts.max()) if counts.numel() > 0 else 0
    return flat[:, :width], counts, width


def putative_associations(
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    *,
    k_prim: int,
    direction: Direction,
    min_line_length_m: float,
) -> Associations:
    """Semantic K-NN associations of one ground submap against every patch of `aerial`.

    "ground_to_aerial": for every ground primitive its `k_prim` most cosine-similar aerial
    primitives of the same type (the paper's K_prim). "union": additionally, for every aerial
    primitive its `k_prim` most similar ground primitives; duplicates are merged. Finite lines
    (segments) shorter than `min_line_length_m` take part on neither side.

    Args:
        ground: the ground submap (Ng points, Ngl lines, descriptors of dimension D).
        aerial: P padded aerial patches (Na points, Nal lines, same D).
        k_prim: neighbours per primitive (clipped to the number of candidates).
        direction: "ground_to_aerial" or "union".
        min_line_length_m: minimum segment length.

    Returns:
        Associations with pairs (P, m, 2), m = n_point_assoc + line block width.
    """
    if k_prim < 1:
        raise ValueError(f"k_prim must be >= 1, got {k_prim}")
    if direction not in ("ground_to_aerial", "union"):
        raise ValueError(f"direction must be 'ground_to_aerial' or 'union', got {direction!r}")
    device, dtype = aerial.points_xy.device, aerial.points_xy.dtype
    ground = ground.to(device=device, dtype=dtype)

    n_ground_points = int(ground.points_xy.shape[0])
    n_aerial_points = int(aerial.points_xy.shape[1])
    ground_point_ok = torch.ones(n_ground_points, dtype=torch.bool, device=device)
    ground_line_ok = line_keep_mask(ground.line_endpoints, ground.line_kinds, min_line_length_m)
    aerial_line_ok = aerial.line_valid & line_keep_mask(aerial.line_endpoints, aerial.line_kinds, min_line_length_m)

    pt_pairs, pt_valid, pt_cos = _type_pairs(
        ground.point_descriptors, ground_point_ok, aerial.point_descriptors, aerial.point_valid, k_prim, direction
    )
    ln_pairs, ln_valid, ln_cos = _type_pairs(
        ground.line_descriptors, ground_line_ok, aerial.line_descriptors, aerial_line_ok, k_prim, direction
    )
    offsets = torch.tensor([n_ground_points, n_aerial_points], device=device)
    ln_pairs = torch.where(ln_valid[..., None], ln_pairs + offsets, ln_pairs)

    n_point_assoc = int(pt_pairs.shape[1])
    valid = torch.cat([pt_valid, ln_valid], dim=1)
    is_line = torch.zeros_like(valid)
    is_line[:, n_point_assoc:] = True
    return Associations(
        pairs=torch.cat([pt_pairs, ln_pairs], dim=1),
        is_line=is_line,
        valid=valid,
        cosine=torch.cat([pt_cos, ln_cos], dim=1),
        n_point_assoc=n_point_assoc,
        n_ground_points=n_ground_points,
        n_aerial_points=n_aerial_points,
    )

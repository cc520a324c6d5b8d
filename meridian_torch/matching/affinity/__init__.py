"""Batched data-association affinity (consistency graph) M_DA of P aerial patches at once.

For associations i = (ground g_i, aerial a_i) and j the entry is
`M_ij = cbrt(s_ij * q_i * q_j)` (the paper's geometric mean GM(s, q_i, q_j)), where q is the
unary semantic score and s the pairwise geometric consistency:

- point-point: distance invariance |(|a_i - a_j|) - (|g_i - g_j|)|, zero when either map's
  points are closer than `min_point_separation_m`;
- line-line: sqrt(s_theta * s_t); s_theta compares the angles between the two lines in each
  map (near-parallel same-map pairs are rejected), s_t compares the gaps between the closest
  points of the bounded lines (segments / rays / infinite lines), with the distance sigma
  inflated by tan(sigma_theta) times the mean lever arm from each line's reference point;
  with `parallel_line_pairs = "separation"`, pairs near-parallel in both maps are scored by
  the angle kernel and the invariance of the perpendicular separation of the two lines
  instead (ground submaps of roads consist mostly of such pairs);
- point-line: along-line and across-line offsets of the point from its nearest point N on the
  line, scored with sigma/sqrt(2) (+ lever-arm inflation across), and capped by the
  point-point score of (p, N).

The kernel is f(c; sigma, eps) = exp(-c^2 / 2 sigma^2) if c <= eps else 0. Entries of pairs
that share a ground or an aerial primitive, and entries <= `affinity_eps`, are zero; the
diagonal is 1 for valid associations; padding rows and columns are zero.

Known-rotation mode (`rotation_prior`, the yaw of T_world_odom per patch): the ground
primitives are first rotated by the prior (both frames are right-handed, so no reflection),
every point-point test is then also done per axis with sigma and eps inflated by
|mean axis offset| * sin(rotation_uncertainty), and each line association's unary score gains
an absolute-direction term.

The reference "line min-distance" veto (near-parallel lines closer than min_dist) is not
repeated in 'reject' mode: near-parallel same-map line pairs are already rejected by the angle
test; in 'separation' mode it zeroes near-parallel pairs separated by less than min_dist.

Reference points of lines (lever arms): segment midpoint, ray start, midpoint of the two
points that define an infinite line.

Evaluation: the geometry of every *primitive* pair (point-line offsets, line-line closest
points, angles, lever arms) is computed once per side (P * A^2 aerial, G^2 ground pairs) and
only gathered per association pair (P * m^2, m ~ K_prim * G). Association pairs are visited in
row blocks over the upper triangle (peak memory bounded by `AffinityConfig.block_pairs`); in
each block a cheap necessary condition (one table lookup per side: point distances, point-line
distances, line angles; plus q_i q_j) selects the few per cent of pairs that can score
non-zero, and the exact scores run on those only, as flat index lists. This made the bench case
(P = 25, m = 2000) about 15x faster than scoring every pair. On the CPU one compiled (numba) pass
does the same pair by pair without block-sized intermediates (`compiled`: the same entries in
the same order, values within a few float32 ulps; 4x less CPU for a KITTI 09 submap).
`affinity_matrix` returns a dense (P, m, m) tensor, `affinity_matrix_sparse` a coalesced sparse
COO (P, m, m) tensor and `affinity` picks the form by `AffinityConfig.dense_max_m` (the
measurement behind the default: README, Why the defaults).

Modules: `lines` (bounded-line geometry), `scores` (the kernel, primitive-pair tables and pair
scores), `gather` (the associations' geometry, gate tables and unary scores), `blocks` (the
gated row-block evaluation), `compiled` (numba kernels for CPU tensors: the entries, the
line-pair tables); this one holds the entry points. Names with a leading underscore are
internal to the package.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from meridian_torch.config.matching import AffinityConfig
from meridian_torch.matching.affinity.blocks import _entries
from meridian_torch.matching.affinity.gather import _gather
from meridian_torch.matching.affinity.lines import closest_points_between_lines, nearest_point_on_line
from meridian_torch.matching.affinity.scores import kernel
from meridian_torch.matching.associations import Associations
from meridian_torch.types import PrimitiveBatch, PrimitiveSet

__all__ = [
    "AffinityEntries",
    "affinity",
    "affinity_entries",
    "affinity_matrix",
    "affinity_matrix_sparse",
    "unary_scores",
    "kernel",
    "nearest_point_on_line",
    "closest_points_between_lines",
]


def unary_scores(
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    assoc: Associations,
    cfg: AffinityConfig,
    *,
    rotation_prior: torch.Tensor | None = None,
) -> torch.Tensor:
    """q_DA of every association, (P, m): the cosine scaled over [cosine_min, cosine_max]
    (zero at or below cosine_min); with a rotation prior, line associations combine it with
    the absolute-direction term f(angle; sigma_theta + unc, eps_theta + unc) as
    sqrt(angle * cosine). Zero for padding."""
    return _gather(ground, aerial, assoc, cfg, rotation_prior).q


def affinity_matrix(
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    assoc: Associations,
    cfg: AffinityConfig,
    *,
    rotation_prior: torch.Tensor | None = None,
) -> torch.Tensor:
    """Dense affinity of every patch's associations.

    Args:
        ground: the ground submap the associations were built from.
        aerial: the P aerial patches.
        assoc: associations from `putative_associations` (m columns).
        cfg: scoring parameters.
        rotation_prior: (P,) yaw of T_world_odom per patch, or None for free rotation.

    Returns:
        (P, m, m) symmetric, in [0, 1], unit diagonal on valid associations, zero elsewhere
        on padding; dtype and device of `aerial`.
    """
    gat = _gather(ground, aerial, assoc, cfg, rotation_prior)
    n_patches, m = gat.valid.shape
    index, value = _entries(gat, cfg)
    out = gat.q.new_zeros(n_patches, m, m)
    out[index[:, 0], index[:, 1], index[:, 2]] = value
    out[index[:, 0], index[:, 2], index[:, 1]] = value
    out.diagonal(dim1=1, dim2=2).copy_(gat.valid)
    return out


@dataclass(frozen=True)
class AffinityEntries:
    """The non-zero strict upper triangle of P affinity matrices (m, m), unit diagonal implied.

    index: (n, 3) int64 (patch, i, j) with i < j; value: (n,) in (affinity_eps, 1]; valid:
    (P, m) bool, the associations that get the unit diagonal.
    """

    index: torch.Tensor
    value: torch.Tensor
    valid: torch.Tensor

    @property
    def shape(self) -> tuple[int, int, int]:
        n_patches, m = self.valid.shape
        return (n_patches, m, m)

    def to_sparse(self) -> torch.Tensor:
        """Symmetric coalesced sparse COO (P, m, m) with the unit diagonal on valid associations."""
        # Coalesced order is by the flat index (p * m + i) * m + j; every entry occurs once (upper,
        # lower, diagonal), so sorting the flat indices is all coalesce() would do.
        _, m, _ = self.shape
        patch, i, j = self.index.unbind(1)
        diag = self.valid.nonzero()
        flat = torch.cat([(patch * m + i) * m + j, (patch * m + j) * m + i, (diag[:, 0] * m + diag[:, 1]) * m + diag[:, 1]])
        flat, order = flat.sort()
        val = torch.cat([self.value, self.value, self.value.new_ones(diag.shape[0])])[order]
        idx = torch.stack([flat // (m * m), flat // m % m, flat % m])
        return torch.sparse_coo_tensor(idx, val, self.shape, is_coalesced=True, check_invariants=False)


def affinity_entries(
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    assoc: Associations,
    cfg: AffinityConfig,
    *,
    rotation_prior: torch.Tensor | None = None,
) -> AffinityEntries:
    """The affinity as its non-zero upper-triangle entries (what `affinity_matrix_sparse`
    assembles; consumers that prune first skip building the full symmetric matrix)."""
    gat = _gather(ground, aerial, assoc, cfg, rotation_prior)
    index, value = _entries(gat, cfg)
    return AffinityEntries(index, value, gat.valid)


def affinity_matrix_sparse(
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    assoc: Associations,
    cfg: AffinityConfig,
    *,
    rotation_prior: torch.Tensor | None = None,
) -> torch.Tensor:
    """The same matrix as `affinity_matrix` as a coalesced sparse COO tensor (P, m, m).

    Only the non-zero entries (> affinity_eps, both triangles, plus the unit diagonal of valid
    associations) are stored; peak memory is one row block plus the non-zeros.
    """
    return affinity_entries(ground, aerial, assoc, cfg, rotation_prior=rotation_prior).to_sparse()


def affinity(
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    assoc: Associations,
    cfg: AffinityConfig,
    *,
    rotation_prior: torch.Tensor | None = None,
) -> torch.Tensor:
    """Dense (P, m, m) when m <= cfg.dense_max_m, otherwise sparse COO (P, m, m)."""
    build = affinity_matrix if assoc.size <= cfg.dense_max_m else affinity_matrix_sparse
    return build(ground, aerial, assoc, cfg, rotation_prior=rotation_prior)

"""From sampled inlier sets to the L weighted SE(2) hypotheses of every patch.

Every unique set of every patch is registered (ground submap = source, aerial patch =
destination, so the result is T_world_odom): on the CPU each set in one compiled pass over its
mask (`registration_kernels`), elsewhere all in one batched `register_se2` call. Sets whose
registration is invalid are dropped. The rest are clustered per patch greedily in J order
(reference `Registerer2D.cluster_hypotheses`): a set joins the first earlier cluster
representative within `translation_m` (Euclidean) and `rotation_deg` (wrapped yaw difference),
otherwise it founds a cluster. A cluster weighs the summed particle counts of its members; the
`n_hypotheses` heaviest clusters are kept, each reported by its representative's pose and
associations, with probability = weight / n_particles (counts of discarded sets are lost, so the
probabilities of a patch sum to at most 1).

On the CPU the greedy clustering is one compiled walk over the sets, comparing each only with
the representatives before it. On other devices it is vectorised: with `close` the (P, S, S)
pairwise-proximity matrix, the representatives are the fixed point of rep = valid & ~any_{j <
i}(close_ij & rep_j), iterated from rep = valid. Entry i is final after at most i + 1 sweeps
and the fixed point is the greedy result; in practice a few sweeps suffice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from meridian_torch.config.matching import RegistrationConfig
from meridian_torch.core.timing import stage
from meridian_torch.geometry.se2 import rotation_matrix, se2_matrix, wrap_angle
from meridian_torch.geometry.vectors import squared_norm2
from meridian_torch.matching.associations import Associations
from meridian_torch.matching.kernels import greedy_clusters
from meridian_torch.matching.particles import InlierSets
from meridian_torch.matching.registration import RegistrationResult, register_se2
from meridian_torch.matching.registration_kernels import register_set_masks
from meridian_torch.types import PrimitiveBatch, PrimitiveSet

__all__ = ["Hypotheses", "register_sets", "cluster_hypotheses"]


@dataclass(frozen=True)
class Hypotheses:
    """L hypotheses T_world_odom per patch, heaviest first; padded entries have valid False.

    Attributes:
        T_world_odom: (P, L, 3, 3) maps ground odom x-y (metres) into world x-y (metres).
        theta: (P, L) yaw of T_world_odom, radians in [-pi, pi).
        t: (P, L, 2) translation of T_world_odom, metres.
        probability: (P, L) cluster weight / n_particles (sums to <= 1 per patch; verification
            replaces it by the share of the submap aligned beyond chance), 0 on padding.
        association_mask: (P, L, m) bool, the representative set's associations (index `pairs`).
        objective: (P, L) J of the representative set (0 on padding).
        valid: (P, L) bool.
        pairs: (P, m, 2) int64 (ground index, aerial index) of the associations, unified index
            spaces of `matching.associations` (points first, then lines).
    """

    T_world_odom: Tensor
    theta: Tensor
    t: Tensor
    probability: Tensor
    association_mask: Tensor
    objective: Tensor
    valid: Tensor
    pairs: Tensor


def _association_geometry(
    ground: PrimitiveSet, aerial: PrimitiveBatch, assoc: Associations
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Endpoints of every association: points (P, n_pt, 2) x 2 sides, lines (P, n_ln, 2, 2) x 2.

    The association axis is [point block | line block] (see `matching.associations`); padding
    indices (-1) are clamped to 0 and must be masked by the caller's weights.
    """
    dtype, device = aerial.points_xy.dtype, aerial.points_xy.device
    ground = ground.to(device=device, dtype=dtype)
    k = assoc.n_point_assoc
    g_pt, a_pt = assoc.pairs[:, :k, 0].clamp_min(0), assoc.pairs[:, :k, 1].clamp_min(0)
    g_ln = (assoc.pairs[:, k:, 0] - assoc.n_ground_points).clamp_min(0)
    a_ln = (assoc.pairs[:, k:, 1] - assoc.n_aerial_points).clamp_min(0)
    # Empty primitive tables get one zero row so that gathering clamped padding indices works.
    ground_pts = torch.cat([ground.points_xy, ground.points_xy.new_zeros(1, 2)])
    ground_lns = torch.cat([ground.line_endpoints, ground.line_endpoints.new_zeros(1, 2, 2)])
    aerial_pts = torch.cat([aerial.points_xy, aerial.points_xy.new_zeros(len(aerial), 1, 2)], 1)
    aerial_lns = torch.cat([aerial.line_endpoints, aerial.line_endpoints.new_zeros(len(aerial), 1, 2, 2)], 1)
    src_pt = ground_pts[g_pt]
    dst_pt = aerial_pts.gather(1, a_pt[..., None].expand(-1, -1, 2))
    src_ln = ground_lns[g_ln]
    dst_ln = aerial_lns.gather(1, a_ln[..., None, None].expand(-1, -1, 2, 2))
    return src_pt, dst_pt, src_ln, dst_ln


def register_sets(
    sets: InlierSets,
    assoc: Associations,
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    config: RegistrationConfig | None = None,
    compiled: bool | None = None,
) -> RegistrationResult:
    """Register all P x S sets; the result's fields are shaped (P, S, ...).

    Points come from the set's point associations, lines from its line associations (unit
    weights; everything else weight 0). `valid` is also False for padded sets. `compiled`
    (default: on CPU tensors) registers each set in one compiled pass over its mask
    (`registration_kernels`, float64 inside: the same results to rounding), else torch's
    batched ops (other devices, and the reference).
    """
    cfg = config or RegistrationConfig()
    if sets.masks.device.type == "cpu" if compiled is None else compiled:
        return _register_sets_compiled(sets, assoc, ground, aerial, cfg)
    n_patches, n_sets, m = sets.masks.shape
    k = assoc.n_point_assoc
    src_pt, dst_pt, src_ln, dst_ln = _association_geometry(ground, aerial, assoc)
    dtype = src_pt.dtype
    B = n_patches * n_sets

    used = sets.masks & assoc.valid[:, None, :]
    patch = torch.arange(n_patches, device=used.device).repeat_interleave(n_sets)[:, None]

    def members(used: Tensor) -> tuple[Tensor, Tensor]:
        """Unit weights (B, width) and indices (B, width) of each set's few members, instead of
        all m associations; index n (one past the end) marks padding (weight 0)."""
        used = used.reshape(B, -1)
        n = used.shape[1]
        # Each set's members in ascending order: the nonzeros are listed row by row (counted
        # from them too: a bool sum over the rows cost 10x the nonzero).
        row, column = used.nonzero(as_tuple=True)
        count = torch.bincount(row, minlength=B)
        width = max(int(count.max()) if len(row) else 0, 1)
        slot = torch.arange(len(row), device=used.device) - (torch.cumsum(count, 0) - count)[row]
        index = torch.full((B, width), n, dtype=torch.int64, device=used.device)
        index[row, slot] = column
        return (index < n).to(dtype), index

    def take(geometry: Tensor, index: Tensor) -> Tensor:
        padded = torch.cat([geometry, geometry.new_zeros(n_patches, 1, *geometry.shape[2:])], 1)
        return padded[patch, index]

    w_pt, i_pt = members(used[..., :k])
    w_ln, i_ln = members(used[..., k:])
    src_pt_c, dst_pt_c, src_ln_c, dst_ln_c = take(src_pt, i_pt), take(dst_pt, i_pt), take(src_ln, i_ln), take(dst_ln, i_ln)
    result = register_se2(src_pt_c, dst_pt_c, w_pt, src_ln_c, dst_ln_c, w_ln, config=cfg)
    shaped = {name: getattr(result, name).reshape(n_patches, n_sets, *getattr(result, name).shape[1:])
              for name in result.__dataclass_fields__}
    shaped["valid"] = shaped["valid"] & sets.valid
    return RegistrationResult(**shaped)


def _register_sets_compiled(
    sets: InlierSets, assoc: Associations, ground: PrimitiveSet, aerial: PrimitiveBatch, cfg: RegistrationConfig
) -> RegistrationResult:
    """`register_sets` by `registration_kernels.register_set_masks` (CPU tensors)."""
    dtype = aerial.points_xy.dtype
    info = torch.finfo(dtype)
    ground = ground.to(device=aerial.points_xy.device, dtype=dtype)
    arrays = [
        x.contiguous().numpy()
        for x in (
            sets.masks, assoc.valid, assoc.pairs, ground.points_xy, ground.line_endpoints, aerial.points_xy,
            aerial.line_endpoints,
        )
    ]
    theta, t, valid, condition, gap, point_residual, line_residual = (
        torch.from_numpy(a)
        for a in register_set_masks(
            *arrays[:3], assoc.n_point_assoc, assoc.n_ground_points, assoc.n_aerial_points, *arrays[3:],
            cfg.line_direction_weight, cfg.information_eps, cfg.ambiguity_eps, cfg.n_angle_samples,
            cfg.newton_iterations, float(info.eps), float(info.tiny),
        )
    )
    theta = theta.to(dtype)
    return RegistrationResult(
        theta=theta,
        R=rotation_matrix(theta),
        t=t.to(dtype),
        valid=valid & sets.valid,
        condition=condition.to(dtype),
        ambiguity_gap=gap.to(dtype),
        point_residual=point_residual.to(dtype),
        line_residual=line_residual.to(dtype),
    )


def _representatives(
    reg: RegistrationResult, counts: Tensor, translation_m: float, rotation_deg: float, compiled: bool | None = None
) -> tuple[Tensor, Tensor]:
    """The greedy cluster representatives (P, S) bool of the valid registrations and their weights
    (P, S) int64: each valid set's count goes to the first representative close to it (itself,
    if it is one). `compiled` (default: on CPU tensors) walks the sets once and compares only
    the pairs the walk needs (`kernels.greedy_clusters`; the (P, S, S) comparisons were 2/3 of
    the clustering), else torch's fixed-point sweeps over all pairs (other devices): the same."""
    ok = reg.valid
    if ok.device.type == "cpu" if compiled is None else compiled:
        limits = torch.tensor([translation_m, math.radians(rotation_deg), math.pi, 2.0 * math.pi], dtype=reg.t.dtype)
        arrays = [x.contiguous().numpy() for x in (reg.t, reg.theta, ok, counts, limits)]
        return tuple(torch.from_numpy(a) for a in greedy_clusters(*arrays))
    dt = squared_norm2(reg.t[:, :, None, :] - reg.t[:, None, :, :]).sqrt()
    dtheta = wrap_angle(reg.theta[:, :, None] - reg.theta[:, None, :]).abs()
    close = (dt <= translation_m) & (dtheta <= math.radians(rotation_deg))
    rep = _greedy_representatives(close, ok)
    joins = close & rep[:, None, :] & ok[:, :, None]
    cluster = torch.where(joins.any(-1), joins.to(torch.int8).argmax(-1), 0)
    weight = torch.zeros_like(counts).scatter_add_(1, cluster, torch.where(ok, counts, 0))
    return rep, torch.where(rep, weight, 0)


def _greedy_representatives(close: Tensor, valid: Tensor) -> Tensor:
    """(P, S) bool: greedy cluster representatives in index order (see the module docstring),
    by torch's fixed-point sweeps over (P, S, S)."""
    earlier = torch.ones(close.shape[-2:], dtype=torch.bool, device=close.device).tril(diagonal=-1)
    blocked_by = close & earlier & valid[:, None, :] & valid[:, :, None]
    rep = valid.clone()
    for _ in range(valid.shape[1] + 1):  # the fixed point is reached after at most S + 1 sweeps
        new = valid & ~(blocked_by & rep[:, None, :]).any(-1)
        if torch.equal(new, rep):
            break
        rep = new
    return rep


def cluster_hypotheses(
    sets: InlierSets,
    assoc: Associations,
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    *,
    n_hypotheses: int,
    translation_m: float,
    rotation_deg: float,
    registration: RegistrationConfig | None = None,
) -> Hypotheses:
    """Register, cluster and rank the inlier sets of P patches into L = n_hypotheses hypotheses.

    Args:
        sets: unique sets per patch sorted by J descending (`sample_inlier_sets` or the CLIPPER
            path), masks (P, S, m).
        assoc: the associations the sets index (m columns).
        ground: the ground submap (odom frame, metres).
        aerial: the P aerial patches (world frame, metres).
        n_hypotheses: L, clusters kept per patch (output is always padded to L).
        translation_m, rotation_deg: cluster radius of the greedy clustering.
        registration: `register_se2` parameters.

    Returns:
        `Hypotheses` with L = n_hypotheses.
    """
    with stage("registration"):
        reg = register_sets(sets, assoc, ground, aerial, registration)
    with stage("clustering"):
        return _cluster(sets, reg, assoc, n_hypotheses, translation_m, rotation_deg)


def _cluster(
    sets: InlierSets, reg: RegistrationResult, assoc: Associations, n_hypotheses: int, translation_m: float,
    rotation_deg: float,
) -> Hypotheses:
    """`cluster_hypotheses` after the registration."""
    n_patches, n_sets = sets.masks.shape[:2]
    rep, weight = _representatives(reg, sets.counts, translation_m, rotation_deg)

    # Heaviest clusters first; ties keep J order (the stable sort runs on J-ordered sets).
    order = torch.sort(torch.where(rep, weight, -1), dim=1, descending=True, stable=True).indices
    L = n_hypotheses
    if n_sets < L:
        order = torch.cat([order, order.new_zeros(n_patches, L - n_sets)], 1)
    order = order[:, :L]
    valid = rep.gather(1, order) & (torch.arange(L, device=order.device) < n_sets)
    theta = reg.theta.gather(1, order).masked_fill(~valid, 0.0)
    t = reg.t.gather(1, order[..., None].expand(-1, -1, 2)).masked_fill(~valid[..., None], 0.0)
    # Whole rows by indexing: a gather of (P, L, m) bools through an expanded index cost 3x.
    masks = sets.masks[torch.arange(n_patches, device=order.device)[:, None], order]
    masks &= valid[..., None]
    return Hypotheses(
        T_world_odom=se2_matrix(theta, t),
        theta=theta,
        t=t,
        probability=(weight.gather(1, order) * valid).to(t.dtype) / sets.n_particles,
        association_mask=masks,
        objective=sets.objective.gather(1, order).masked_fill(~valid, 0.0),
        valid=valid,
        pairs=assoc.pairs,
    )

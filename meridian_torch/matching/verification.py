"""Geometric verification of hypotheses: how much of the whole submap a pose lays on the patch.

A hypothesis comes from a few associations (3-6 on rendered submaps, where about 2 % of the
putative associations are true), so its particle mass says little about the rest of the submap.
Its alignment does: moved by T_world_odom, each ground line is cut into equal pieces of at most
`line_piece_m`, and a piece counts its length x (1 - d^2 / line_distance_m^2), d the distance of
its midpoint to the nearest aerial line of the patch whose direction is within `line_angle_deg`
(to that line's segment between its endpoints); a ground point counts
point_weight_m x (1 - d^2 / point_distance_m^2), d the distance to the nearest aerial point.
Beyond the distances nothing counts. Pieces, not whole lines, so that a road border shifted past
the end of its aerial counterpart (a junction, a building corner) loses the part that
overhangs; graded, not all-or-nothing, so that of two poses laying the same lines on the map
the closer one wins. Descriptors play no part: this is the check the sparse, descriptor-driven
associations cannot make.

`reweight_hypotheses` turns the alignment into the ranking: probability = particle mass x
alignment, rescaled so a patch keeps the total mass it had (probabilities still sum to <= 1).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from meridian_torch.matching.config import VerificationConfig
from meridian_torch.matching.hypotheses import Hypotheses
from meridian_torch.types import PrimitiveBatch, PrimitiveSet

__all__ = ["alignment_score", "line_pieces", "near_parallel_pairs", "reweight_hypotheses"]


def _squared_segment_distance(p: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """Squared distance from points p (K, 2) to segments a-b (K, 2)."""
    ab = b - a
    t = ((p - a) * ab).sum(-1) / ab.square().sum(-1).clamp_min(1e-12)
    return (a + t.clamp(0.0, 1.0)[:, None] * ab - p).square().sum(-1)


def line_pieces(endpoints: Tensor, piece_m: float) -> Tensor:
    """(N, 2, 2) segments -> (Q, 2, 2): each cut into ceil(length / piece_m) equal pieces, in order."""
    length = (endpoints[:, 1] - endpoints[:, 0]).norm(dim=-1)
    count = torch.ceil(length / piece_m).clamp_min(1).long()
    line = torch.repeat_interleave(torch.arange(len(endpoints), device=endpoints.device), count)
    first = torch.cumsum(count, 0) - count
    j = torch.arange(len(line), device=endpoints.device) - first[line]
    a, b = endpoints[line, 0], endpoints[line, 1]
    k = count[line].to(endpoints.dtype)
    f0 = (j.to(endpoints.dtype) / k)[:, None]
    f1 = ((j + 1).to(endpoints.dtype) / k)[:, None]
    return torch.stack([a + f0 * (b - a), a + f1 * (b - a)], 1)


def _sign_free_angle(u: Tensor) -> Tensor:
    """Direction angle of unit vectors (..., 2) modulo pi, in [0, pi)."""
    return torch.remainder(torch.atan2(u[..., 1], u[..., 0]), math.pi)


def near_parallel_pairs(u: Tensor, au: Tensor, line_valid: Tensor, angle_deg: float) -> tuple[Tensor, Tensor]:
    """Every ground direction u[p, h, n] (P, H, N, 2) and valid aerial direction au[p, m]
    (P, M, 2) (unit vectors, signs free) with |u . au| >= cos(angle_deg), as flat indices
    ((p H + h) N + n, p M + m): `(einsum(u, au).abs() >= cos).nonzero()` in another order and
    form, without the (P, H, N, M) product
    (verification's cost on real patches). Aerial lines are sorted by angle once per patch; each
    ground direction takes its circular window of angle_deg + 1e-3 rad (at most two disjoint
    ranges) by binary search, a strict superset as angles are exact to ~1e-7, and the exact
    test runs on those candidates only."""
    n_patches, n_aerial = au.shape[:2]
    cos_min = math.cos(math.radians(angle_deg))
    psi = _sign_free_angle(au).masked_fill(~line_valid, math.inf)  # invalid lines sort last
    psi_sorted, order = torch.sort(psi, dim=1, stable=True)
    alpha = _sign_free_angle(u).reshape(n_patches, -1)  # (P, Q) queries
    half = math.radians(angle_deg) + 1e-3
    zero, pi = alpha.new_zeros(alpha.shape), alpha.new_full(alpha.shape, math.pi)
    if 2 * half >= math.pi:  # every direction is within the window
        windows = [(zero, pi)]
    else:  # [lo, hi] within [0, pi), plus the part wrapping around either end (never both)
        lo, hi = alpha - half, alpha + half
        windows = [(lo.clamp_min(0.0), hi.clamp_max(math.pi)), (lo + math.pi, pi), (zero, hi - math.pi)]
    starts, counts = [], []
    for w_lo, w_hi in windows:
        start = torch.searchsorted(psi_sorted, w_lo.contiguous(), side="left")
        starts.append(start)
        counts.append((torch.searchsorted(psi_sorted, w_hi.contiguous(), side="right") - start).clamp_min(0))
    start, count = torch.stack(starts, -1).reshape(-1), torch.stack(counts, -1).reshape(-1)  # (P * Q * W,)
    window = torch.repeat_interleave(torch.arange(len(count), device=u.device), count)
    position = torch.arange(len(window), device=u.device) + (start - torch.cumsum(count, 0) + count)[window]
    query = window // len(windows)
    patch = query // alpha.shape[1]
    line = order.reshape(-1).index_select(0, patch * n_aerial + position) + patch * n_aerial
    dot = (u.reshape(-1, 2).index_select(0, query) * au.reshape(-1, 2).index_select(0, line)).sum(-1)
    keep = dot.abs() >= cos_min
    return query[keep], line[keep]


def alignment_score(
    T_world_odom: Tensor, ground: PrimitiveSet, aerial: PrimitiveBatch, config: VerificationConfig
) -> Tensor:
    """(P, H) alignment (closeness-weighted metres of ground line + weighted points) of H poses per patch.

    Args:
        T_world_odom: (P, H, 3, 3) poses mapping ground odom x-y into the world, per patch.
        ground: the submap (odom frame, metres).
        aerial: the P padded patches (world frame, metres).
        config: tolerances and the point weight.
    """
    dtype, device = T_world_odom.dtype, T_world_odom.device
    ground = ground.to(device=device, dtype=dtype)
    R, t = T_world_odom[..., :2, :2], T_world_odom[..., :2, 2]
    score = T_world_odom.new_zeros(T_world_odom.shape[:2])
    if len(ground.line_endpoints) and aerial.line_endpoints.shape[1]:
        pieces = line_pieces(ground.line_endpoints, config.line_piece_m)
        d = pieces[:, 1] - pieces[:, 0]  # (N, 2)
        length = d.norm(dim=-1)
        u = d / length[:, None].clamp_min(1e-12)
        mid = torch.einsum("phij,nj->phni", R, pieces.mean(1)) + t[:, :, None]  # (P, H, N, 2)
        u_world = torch.einsum("phij,nj->phni", R, u)
        A = aerial.line_endpoints.to(dtype)  # (P, M, 2, 2)
        ad = A[:, :, 1] - A[:, :, 0]
        au = ad / ad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        piece, line = near_parallel_pairs(u_world, au, aerial.line_valid, config.line_angle_deg)
        ends = A.reshape(-1, 4).index_select(0, line)
        d2 = _squared_segment_distance(mid.reshape(-1, 2).index_select(0, piece), ends[:, :2], ends[:, 2:])
        closeness = (1.0 - d2 / config.line_distance_m**2).clamp_min(0.0)
        on_line = closeness.new_zeros(mid.shape[:3].numel()).scatter_reduce(0, piece, closeness, "amax").view(mid.shape[:3])
        score = score + (on_line * length).sum(-1)
    if len(ground.points_xy) and aerial.points_xy.shape[1]:
        p = torch.einsum("phij,nj->phni", R, ground.points_xy) + t[:, :, None]  # (P, H, N, 2)
        dist2 = (p[:, :, :, None] - aerial.points_xy.to(dtype)[:, None, None]).square().sum(-1)
        closeness = (1.0 - dist2 / config.point_distance_m**2).clamp_min(0.0) * aerial.point_valid[:, None, None, :]
        score = score + config.point_weight_m * closeness.amax(-1).sum(-1)
    return score


def _take(h: Hypotheses, order: Tensor, probability: Tensor) -> Hypotheses:
    def g(x: Tensor) -> Tensor:
        index = order.reshape(*order.shape, *(1,) * (x.dim() - 2)).expand(*order.shape, *x.shape[2:])
        return x.gather(1, index)

    return Hypotheses(
        T_world_odom=g(h.T_world_odom),
        theta=g(h.theta),
        t=g(h.t),
        probability=g(probability),
        association_mask=g(h.association_mask),
        objective=g(h.objective),
        valid=g(h.valid),
        pairs=h.pairs,
    )


def reweight_hypotheses(
    hypotheses: Hypotheses,
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    config: VerificationConfig,
    n_hypotheses: int,
) -> Hypotheses:
    """Rank (P, H) hypotheses by mass x alignment and keep the best `n_hypotheses` <= H per patch.

    Probabilities become mass x alignment rescaled to the patch's total mass over the H inputs
    (so they still sum to <= 1); a patch whose hypotheses all align nowhere keeps its masses.
    Alignment is computed a few patches of similar size at a time, about `config.chunk_pairs`
    (pose, ground primitive, aerial primitive) triples per chunk (memory).
    """
    h = hypotheses
    if n_hypotheses > h.valid.shape[1]:
        raise ValueError(f"n_hypotheses = {n_hypotheses} > the {h.valid.shape[1]} hypotheses given per patch")
    mass = torch.where(h.valid, h.probability, 0.0)
    n_ground = max(len(line_pieces(ground.line_endpoints, config.line_piece_m)), len(ground.points_xy), 1)
    # Patches by size (largest first) so that each chunk is padded only to patches like its own.
    size = torch.maximum(*aerial.used_lengths()).clamp_min(1)
    by_size = torch.argsort(size, descending=True, stable=True)
    score = mass.new_zeros(mass.shape)
    c0 = 0
    while c0 < len(by_size):
        chunk = max(1, config.chunk_pairs // (h.valid.shape[1] * n_ground * int(size[by_size[c0]])))
        part = by_size[c0 : c0 + chunk]
        score[part] = alignment_score(h.T_world_odom[part], ground, aerial.select(part).trimmed(), config)
        c0 += chunk
    weight = mass * score
    total_weight = weight.sum(1, keepdim=True)
    probability = torch.where(
        total_weight > 0, weight * mass.sum(1, keepdim=True) / total_weight.clamp_min(1e-30), mass
    )
    order = torch.sort(torch.where(h.valid, probability, -1.0), dim=1, descending=True, stable=True).indices
    return _take(h, order[:, :n_hypotheses], probability)

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

`reweight_hypotheses` turns the alignment into the ranking. A pose can lay part of a submap on
any patch by chance, more on a patch dense with lines, so the score is the alignment beyond
chance: minus the submap's mean alignment at fixed poses spread over the patch
(`chance_alignment`), as a fraction of what the submap could align at most. Unlike particle
mass, which each patch's sampler spreads over its own clusters, this compares across patches
(README: Why the defaults, `matching.verification`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from meridian_torch.config.matching import VerificationConfig
from meridian_torch.geometry.se2 import rotation_matrix, se2_matrix
from meridian_torch.geometry.segments import squared_segment_distance
from meridian_torch.geometry.vectors import dot2, squared_norm2
from meridian_torch.matching.hypotheses import Hypotheses
from meridian_torch.matching.kernels import alignment_scores, near_line_closeness, near_pairs
from meridian_torch.types import PrimitiveBatch, PrimitiveSet

__all__ = [
    "alignment_score", "chance_alignment", "line_pieces", "piece_closeness", "reweight_hypotheses",
    "segments_near_points",
]


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


def segments_near_points(points: Tensor, ends: Tensor, valid: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Pairs of a point points[p, q] (P, Q, 2) and a valid segment ends[p, m] (P, M, 2, 2) of
    the same patch as flat indices (p Q + q, p M + m), ascending: every pair closer than
    `radius`, and some farther ones. A grid of radius / 2 apart samples along every segment,
    each registered in the 3 x 3 cells of 1.5 radius around its own; a point takes its cell's
    segments. Exhaustive because a point within radius of a segment is within 1.25 radius of a
    sample, less than one cell (verification's cost on real patches was the (pose, piece, aerial
    line) product, of which a few per cent lie that close). Compiled, on the CPU: as torch ops
    the grid's index arithmetic over every sample and point was half of verification."""
    arrays = [t.detach().cpu().contiguous().numpy() for t in (points.to(torch.float64), ends.to(torch.float64), valid)]
    query, segment = near_pairs(*arrays, float(radius))
    return torch.from_numpy(query).to(points.device), torch.from_numpy(segment).to(points.device)


def piece_closeness(
    mid: Tensor, u_piece: Tensor, ends: Tensor, u_line: Tensor, valid: Tensor, config: VerificationConfig,
    compiled: bool | None = None,
) -> Tensor:
    """(P, Q) closeness of pieces (midpoints mid (P, Q, 2), unit directions u_piece (P, Q, 2)) to
    the nearest valid aerial line of their patch (ends (P, M, 2, 2), unit directions u_line
    (P, M, 2), valid (P, M)) within `line_angle_deg`: max(1 - d^2 / line_distance_m^2, 0), 0
    without one; only the `segments_near_points` candidates are measured. `compiled` (default:
    on CPU tensors) scores them while walking its grid (`kernels.near_line_closeness`), bitwise
    the torch expressions run on other devices: those were ~10 passes over ~100k pairs per
    chunk, two thirds of verification's time."""
    cos_tol = math.cos(math.radians(config.line_angle_deg))
    if mid.device.type == "cpu" if compiled is None else compiled:
        constants = torch.tensor([cos_tol, 1e-12, 0.0, 1.0, config.line_distance_m**2], dtype=mid.dtype)
        arrays = [x.detach().contiguous().numpy() for x in (mid, u_piece, ends, u_line, valid)]
        return torch.from_numpy(near_line_closeness(*arrays, float(config.line_distance_m), constants.numpy()))
    piece, line = segments_near_points(mid, ends, valid, config.line_distance_m)
    parallel = dot2(u_piece.reshape(-1, 2)[piece], u_line.reshape(-1, 2)[line]).abs() >= cos_tol
    piece, line = piece[parallel], line[parallel]
    near = ends.reshape(-1, 2, 2)[line]
    d2 = squared_segment_distance(mid.reshape(-1, 2)[piece], near[:, 0], near[:, 1])
    closeness = (1.0 - d2 / config.line_distance_m**2).clamp_min(0.0)
    return closeness.new_zeros(mid.shape[:2].numel()).scatter_reduce(0, piece, closeness, "amax").view(mid.shape[:2])


def alignment_score(
    T_world_odom: Tensor, ground: PrimitiveSet, aerial: PrimitiveBatch, config: VerificationConfig,
    compiled: bool | None = None,
) -> Tensor:
    """(P, H) alignment (closeness-weighted metres of ground line + weighted points) of H poses per patch.

    Args:
        T_world_odom: (P, H, 3, 3) poses mapping ground odom x-y into the world, per patch.
        ground: the submap (odom frame, metres).
        aerial: the P padded patches (world frame, metres).
        config: tolerances and the point weight.
        compiled: (default: on CPU tensors) score every pose in one compiled pass
            (`kernels.alignment_scores`, float64 inside: equal to rounding), else torch's ops
            (other devices, and the reference).
    """
    dtype, device = T_world_odom.dtype, T_world_odom.device
    ground = ground.to(device=device, dtype=dtype)
    if device.type == "cpu" if compiled is None else compiled:
        return _compiled_alignment(T_world_odom, ground, aerial, config)
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
        on_line = piece_closeness(mid.flatten(1, 2), u_world.flatten(1, 2), A, au, aerial.line_valid, config)
        on_line = on_line.view(mid.shape[:3])
        score = score + (on_line * length).sum(-1)
    if len(ground.points_xy) and aerial.points_xy.shape[1]:
        p = torch.einsum("phij,nj->phni", R, ground.points_xy) + t[:, :, None]  # (P, H, N, 2)
        dist2 = squared_norm2(p[:, :, :, None] - aerial.points_xy.to(dtype)[:, None, None])
        closeness = (1.0 - dist2 / config.point_distance_m**2).clamp_min(0.0) * aerial.point_valid[:, None, None, :]
        score = score + config.point_weight_m * closeness.amax(-1).sum(-1)
    return score


def _compiled_alignment(
    T_world_odom: Tensor, ground: PrimitiveSet, aerial: PrimitiveBatch, config: VerificationConfig
) -> Tensor:
    """`alignment_score` by `kernels.alignment_scores` (CPU tensors)."""
    pieces = line_pieces(ground.line_endpoints, config.line_piece_m).to(torch.float64)
    d = pieces[:, 1] - pieces[:, 0]
    length = d.norm(dim=-1)
    ends = aerial.line_endpoints.to(torch.float64)
    ad = ends[:, :, 1] - ends[:, :, 0]
    arrays = [
        x.contiguous().numpy()
        for x in (
            T_world_odom.to(torch.float64), pieces.mean(1), d / length[:, None].clamp_min(1e-12), length,
            ground.points_xy.to(torch.float64), ends, ad / ad.norm(dim=-1, keepdim=True).clamp_min(1e-12),
            aerial.line_valid, aerial.points_xy.to(torch.float64), aerial.point_valid,
        )
    ]
    score = alignment_scores(
        *arrays, math.cos(math.radians(config.line_angle_deg)), config.line_distance_m, config.point_distance_m,
        config.point_weight_m,
    )
    return torch.from_numpy(score).to(T_world_odom.dtype)


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


def _chunked_alignment(
    T_world_odom: Tensor, ground: PrimitiveSet, aerial: PrimitiveBatch, config: VerificationConfig
) -> Tensor:
    """`alignment_score` by torch's ops, patches by size (largest first) in chunks of about
    `config.chunk_pairs` (pose, ground primitive, aerial primitive) triples, each chunk padded
    only to patches like its own."""
    n_poses = T_world_odom.shape[1]
    n_ground = max(len(line_pieces(ground.line_endpoints, config.line_piece_m)), len(ground.points_xy), 1)
    size = torch.maximum(*aerial.used_lengths()).clamp_min(1)
    by_size = torch.argsort(size, descending=True, stable=True)
    score = T_world_odom.new_zeros(T_world_odom.shape[:2])
    c0 = 0
    while c0 < len(by_size):
        chunk = max(1, config.chunk_pairs // (n_poses * n_ground * int(size[by_size[c0]])))
        part = by_size[c0 : c0 + chunk]
        score[part] = alignment_score(
            T_world_odom[part], ground, aerial.select(part).trimmed(), config, compiled=False
        )
        c0 += chunk
    return score


def chance_alignment(ground: PrimitiveSet, aerial: PrimitiveBatch, config: VerificationConfig) -> Tensor:
    """(P,) float64 mean alignment of the submap at fixed poses over each patch: its centre (that of
    its primitives' bounding box) put at the patch's centre and at the four points
    `chance_offset_m` from it along the diagonals, at `chance_yaws` evenly spaced yaws. The poses
    depend on the patch alone, so a patch's score does not depend on the batch."""
    f64, device = torch.float64, aerial.points_xy.device
    ground_xy = torch.cat([ground.points_xy, ground.line_endpoints.reshape(-1, 2)]).to(device=device, dtype=f64)
    aerial_xy = torch.cat([aerial.points_xy.to(f64), aerial.line_endpoints.to(f64).flatten(1, 2)], 1)
    if not len(ground_xy) or not aerial_xy.shape[:2].numel():
        return torch.zeros(len(aerial), dtype=f64, device=device)
    centre_odom = (ground_xy.amin(0) + ground_xy.amax(0)) / 2
    used = torch.cat([aerial.point_valid, aerial.line_valid.repeat_interleave(2, 1)], 1)[..., None]
    low = torch.where(used, aerial_xy, math.inf).amin(1)
    high = torch.where(used, aerial_xy, -math.inf).amax(1)
    centre_world = torch.where(used.any(1), (low + high) / 2, 0.0)  # (P, 2); empty patches score 0 anyway
    yaw = torch.arange(config.chance_yaws, dtype=f64, device=device) * (2 * math.pi / config.chance_yaws)
    diagonals = torch.tensor([[0, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=f64, device=device)
    t = (centre_world[:, None, None] + config.chance_offset_m * diagonals) - (rotation_matrix(yaw) @ centre_odom)[:, None]
    T = se2_matrix(yaw[None, :, None].expand(t.shape[:3]), t)  # (P, Y, 5, 3, 3)
    return _pose_scores(T.flatten(1, 2), ground, aerial, config).mean(1)


def _pose_scores(T_world_odom: Tensor, ground: PrimitiveSet, aerial: PrimitiveBatch, config: VerificationConfig) -> Tensor:
    """`alignment_score` of (P, H) poses: one compiled pass on the CPU (no (pose, primitive,
    primitive) tensors, so no chunks), else a few patches of similar size at a time."""
    if T_world_odom.device.type == "cpu":
        return alignment_score(T_world_odom, ground, aerial, config)
    return _chunked_alignment(T_world_odom, ground, aerial, config)


def reweight_hypotheses(
    hypotheses: Hypotheses,
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    config: VerificationConfig,
    n_hypotheses: int,
) -> Hypotheses:
    """Rank (P, H) hypotheses by their alignment beyond chance and keep the best `n_hypotheses` <= H
    per patch.

    probability becomes (alignment - `chance_alignment`) / the submap's whole weight (its line
    length + point_weight_m x its points), clipped to [0, 1]: the share of the submap the pose
    lays on the patch beyond chance, comparable across the patches of a call. Ties (0 beyond
    chance) keep the order of particle mass. On the CPU the alignment of every pose is one
    compiled pass; elsewhere it is computed a few patches of similar size at a time, about
    `config.chunk_pairs` (pose, ground primitive, aerial primitive) triples per chunk (memory).
    """
    h = hypotheses
    if n_hypotheses > h.valid.shape[1]:
        raise ValueError(f"n_hypotheses = {n_hypotheses} > the {h.valid.shape[1]} hypotheses given per patch")
    mass = torch.where(h.valid, h.probability, 0.0)
    score = _pose_scores(h.T_world_odom, ground, aerial, config)
    chance = chance_alignment(ground, aerial, config).to(score)
    whole = (ground.line_endpoints[:, 1] - ground.line_endpoints[:, 0]).norm(dim=-1).sum() + config.point_weight_m * len(
        ground.points_xy
    )
    probability = torch.where(h.valid, ((score - chance[:, None]) / whole.to(score).clamp_min(1e-12)).clamp(0.0, 1.0), 0.0)
    # Sorted by mass, then stably by the score: equal scores stay heaviest first.
    by_mass = torch.sort(torch.where(h.valid, mass, -1.0), dim=1, descending=True, stable=True).indices
    key = torch.where(h.valid, probability, -1.0).gather(1, by_mass)
    order = by_mass.gather(1, torch.sort(key, dim=1, descending=True, stable=True).indices)
    return _take(h, order[:, :n_hypotheses], probability)

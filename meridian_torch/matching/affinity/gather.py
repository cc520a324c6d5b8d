"""Gathering the associations' geometry: per-association indices and points, the primitive-pair
tables of both sides (aerial ones only over the primitives some association uses), the gate
tables, and the unary scores q (with the rotation prior's absolute-direction term)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from meridian_torch.config.matching import AffinityConfig
from meridian_torch.geometry.se2 import line_angle_between, wrap_line_angle
from meridian_torch.matching.affinity.compiled import _compiled_line_pair_table
from meridian_torch.matching.affinity.lines import _line_params
from meridian_torch.matching.affinity.scores import (
    _GATE_SLACK,
    _line_pair_table,
    _point_line_table,
    kernel,
)
from meridian_torch.matching.associations import Associations
from meridian_torch.types import PrimitiveBatch, PrimitiveSet


@dataclass(frozen=True)
class _Gathered:
    """Per-association indices and point coordinates, and the primitive-pair tables.

    Points: a_px, a_py, g_px, g_py (P, mp), ground already rotated by the prior. Local
    primitive indices within their type: a_pt, g_pt (P, mp), a_ln, g_ln (P, ml). Tables,
    flattened over their pair axes: a_pl (F, P * Ap * Al), g_pl (F, Gp * Gl),
    a_ll (F, P * Al * Al), g_ll (F, Gl * Gl). Gate tables (one scalar per primitive pair, see
    `_gate_tables`): a_pp_gate (P * Ap * Ap), g_pp_gate (Gp * Gp), and likewise for pl, ll.
    """

    a_px: torch.Tensor
    a_py: torch.Tensor
    g_px: torch.Tensor
    g_py: torch.Tensor
    a_pt: torch.Tensor
    g_pt: torch.Tensor
    a_ln: torch.Tensor
    g_ln: torch.Tensor
    a_pl: torch.Tensor
    g_pl: torch.Tensor
    a_ll: torch.Tensor
    g_ll: torch.Tensor
    a_pp_gate: torch.Tensor
    g_pp_gate: torch.Tensor
    a_pl_gate: torch.Tensor
    g_pl_gate: torch.Tensor
    a_ll_gate: torch.Tensor
    g_ll_gate: torch.Tensor
    n_aerial_points: int
    n_aerial_lines: int
    n_ground_points: int
    n_ground_lines: int
    cos_sin: tuple[torch.Tensor, torch.Tensor] | None  # (P,) each, with a rotation prior
    ground_idx: torch.Tensor  # (P, m) -1 in padding
    aerial_idx: torch.Tensor  # (P, m)
    valid: torch.Tensor  # (P, m)
    q: torch.Tensor  # (P, m) unary scores, 0 where invalid
    n_point_assoc: int


def _rotate(cos: torch.Tensor, sin: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return cos * x - sin * y, sin * x + cos * y


# Gate value of near-parallel line pairs = offset + scaled separation (see `_gate_tables`);
# float32 still resolves the slack at this magnitude for separations up to a few km.
_PARALLEL_GATE_OFFSET = 1e3


def _gate_tables(
    a_xy: torch.Tensor, g_xy: torch.Tensor, a_pl: torch.Tensor, g_pl: torch.Tensor, a_ll: torch.Tensor,
    g_ll: torch.Tensor, cfg: AffinityConfig,
) -> tuple[torch.Tensor, ...]:
    """Cheap necessary conditions of a non-zero score, one scalar per primitive pair and side.

    Point-point: the distance (NaN when closer than the minimum separation, so the gate fails);
    point-line: |p - N|, which every point-line score compares with eps_t (the capping
    point-point score of (p, N), whose eps is never inflated); line-line: the angle between
    the lines (NaN below the minimum line angle; in 'separation' mode near-parallel pairs carry
    their separation instead, see `line_pairs`). An association pair can score non-zero only
    if its aerial and ground values differ by at most eps_t (eps_theta for lines).
    """
    def without_self_pairs(value: torch.Tensor) -> torch.Tensor:
        # NaN fails every comparison. The diagonal (a primitive with itself, i.e. two
        # associations sharing it) is NaN, so the gate also enforces one-to-one. (value is new.)
        value.diagonal(dim1=-2, dim2=-1).fill_(float("nan"))
        return value.flatten()

    def same_type(value: torch.Tensor, minimum: float) -> torch.Tensor:
        return without_self_pairs(value.masked_fill(value < minimum, float("nan")))

    def distances(xy: torch.Tensor) -> torch.Tensor:
        return torch.hypot(xy[..., :, None, 0] - xy[..., None, :, 0], xy[..., :, None, 1] - xy[..., None, :, 1])

    def line_pairs(ll: torch.Tensor) -> torch.Tensor:
        min_angle = math.radians(cfg.min_line_angle_deg)
        if cfg.parallel_line_pairs == "reject":
            return same_type(ll[0], min_angle - _GATE_SLACK)
        # Near-parallel pairs: the separation in angle units (eps_t maps to eps_theta), shifted
        # far above every angle so that pairs parallel in one map only fail the gate too.
        scale = math.radians(cfg.epsilon_theta_deg) / cfg.epsilon_t_m
        too_close = ll[1] < cfg.min_point_separation_m - _GATE_SLACK
        parallel = ll[1].mul(scale).add_(_PARALLEL_GATE_OFFSET).masked_fill_(too_close, float("nan"))
        return without_self_pairs(torch.where(ll[0] < min_angle, parallel, ll[0]))

    # Point-line pairs never share a primitive (points and lines are indexed apart).
    return (
        same_type(distances(a_xy), cfg.min_point_separation_m - _GATE_SLACK),
        same_type(distances(g_xy), cfg.min_point_separation_m - _GATE_SLACK),
        torch.hypot(a_pl[0], a_pl[1]).flatten(),
        torch.hypot(g_pl[0], g_pl[1]).flatten(),
        line_pairs(a_ll),
        line_pairs(g_ll),
    )


def _used(index: torch.Tensor, valid: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Primitives (of one type, n >= 1 per patch) that valid associations use: (P, U) their
    indices in ascending order (padded with unused ones, U >= 1), and `index` (P, k) renumbered
    into that list (0 where invalid)."""
    n_patches = index.shape[0]
    index = torch.where(valid, index, n)
    flags = torch.zeros(n_patches, n + 1, dtype=torch.bool, device=index.device).scatter_(1, index, True)[:, :n]
    width = max(int(flags.sum(1).max()), 1)
    used = torch.sort(flags.to(torch.int8), dim=1, descending=True, stable=True).indices[:, :width]
    rank = torch.cumsum(flags, 1) - 1
    return used, torch.where(valid, rank.gather(1, index.clamp_max(n - 1)), 0)


def _with_dummy(x: torch.Tensor) -> torch.Tensor:
    """(P, n, ...) with one zero row appended when n = 0, so that index 0 can be gathered."""
    return x if x.shape[1] else x.new_zeros(x.shape[0], 1, *x.shape[2:])


def _gather(
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    assoc: Associations,
    cfg: AffinityConfig,
    rotation_prior: torch.Tensor | None,
    compiled: bool | None = None,
) -> _Gathered:
    """The associations' geometry and tables; compiled: build the line-pair tables with the numba
    pass (`compiled`; default: for CPU tensors) instead of the torch ops (the same numbers)."""
    device, dtype = aerial.points_xy.device, aerial.points_xy.dtype
    ground = ground.to(device=device, dtype=dtype)
    n_patches, mp = assoc.num_patches, assoc.n_point_assoc
    if aerial.points_xy.shape[0] != n_patches:
        raise ValueError(f"aerial batch has {aerial.points_xy.shape[0]} patches, associations {n_patches}")
    valid = assoc.valid.to(device)
    g_idx = torch.where(valid, assoc.pairs[..., 0].to(device), -1)
    a_idx = torch.where(valid, assoc.pairs[..., 1].to(device), -1)
    batch = torch.arange(n_patches, device=device)[:, None]

    # Padding entries point at index 0 of their type; they always fail the conflict test.
    g_pt = g_idx[:, :mp].clamp_min(0)
    g_ln = (g_idx[:, mp:] - assoc.n_ground_points).clamp_min(0)
    # Aerial primitives that no association uses are left out of the tables (on rendered
    # submaps a patch's associations use ~80 of its ~470 lines: 30x fewer line pairs).
    a_src_xy, a_ends, a_kinds = (_with_dummy(x) for x in (aerial.points_xy, aerial.line_endpoints, aerial.line_kinds))
    used_pt, a_pt = _used(a_idx[:, :mp], valid[:, :mp], a_src_xy.shape[1])
    used_ln, a_ln = _used(a_idx[:, mp:] - assoc.n_aerial_points, valid[:, mp:], a_ends.shape[1])
    with_vectors = rotation_prior is not None

    # Tables over all primitive pairs of each side (aerial per patch, its used primitives).
    a_lines = _line_params(a_ends.gather(1, used_ln[..., None, None].expand(-1, -1, 2, 2)), a_kinds.gather(1, used_ln))
    g_lines = _line_params(ground.line_endpoints, ground.line_kinds)  # (Gl,)
    a_xy, g_xy = a_src_xy.gather(1, used_pt[..., None].expand(-1, -1, 2)), ground.points_xy
    a_pl = _point_line_table(a_xy[..., :, None, 0], a_xy[..., :, None, 1], a_lines.map_axis(-2), with_vectors)
    g_pl = _point_line_table(g_xy[..., :, None, 0], g_xy[..., :, None, 1], g_lines.map_axis(-2), with_vectors)
    parallel_below = math.radians(cfg.min_line_angle_deg) if cfg.parallel_line_pairs == "separation" else None
    if compiled is None:
        compiled = device.type == "cpu"
    if compiled:
        a_ll = _compiled_line_pair_table(a_lines, with_vectors, parallel_below)
        g_ll = _compiled_line_pair_table(g_lines, with_vectors, parallel_below)
    else:
        a_ll = _line_pair_table(a_lines.map_axis(-1), a_lines.map_axis(-2), with_vectors, parallel_below)
        g_ll = _line_pair_table(g_lines.map_axis(-1), g_lines.map_axis(-2), with_vectors, parallel_below)
    gates = _gate_tables(a_xy, g_xy, a_pl, g_pl, a_ll, g_ll, cfg)

    g_points = g_xy[g_pt]
    a_points = a_xy[batch, a_pt]
    g_px, g_py = g_points[..., 0], g_points[..., 1]
    c_lo, c_hi = cfg.cosine_min, cfg.cosine_max
    q = ((assoc.cosine.to(device=device, dtype=dtype) - c_lo) / (c_hi - c_lo)).clamp(0.0, 1.0)
    cos_sin = None
    if rotation_prior is not None:
        yaw = rotation_prior.to(device=device, dtype=dtype).reshape(n_patches, 1)
        cos, sin = torch.cos(yaw), torch.sin(yaw)
        g_px, g_py = _rotate(cos, sin, g_px, g_py)
        cos_sin = (cos[:, 0], sin[:, 0])
        # Absolute line direction must agree up to the remaining heading uncertainty.
        widen = math.radians(cfg.rotation_uncertainty_deg)
        a_phi = a_lines.angle()[batch, a_ln]
        g_phi = wrap_line_angle(g_lines.angle()[g_ln] + yaw)
        heading = kernel(
            line_angle_between(a_phi, g_phi),
            math.radians(cfg.sigma_theta_deg) + widen,
            math.radians(cfg.epsilon_theta_deg) + widen,
        )
        q = torch.cat([q[:, :mp], torch.sqrt(heading * q[:, mp:])], dim=1)
    return _Gathered(
        a_px=a_points[..., 0],
        a_py=a_points[..., 1],
        g_px=g_px,
        g_py=g_py,
        a_pt=a_pt,
        g_pt=g_pt,
        a_ln=a_ln,
        g_ln=g_ln,
        a_pl=a_pl.flatten(1),
        g_pl=g_pl.flatten(1),
        a_ll=a_ll.flatten(1),
        g_ll=g_ll.flatten(1),
        a_pp_gate=gates[0],
        g_pp_gate=gates[1],
        a_pl_gate=gates[2],
        g_pl_gate=gates[3],
        a_ll_gate=gates[4],
        g_ll_gate=gates[5],
        n_aerial_points=int(a_xy.shape[1]),
        n_aerial_lines=int(used_ln.shape[1]),
        n_ground_points=int(g_xy.shape[0]),
        n_ground_lines=int(ground.line_endpoints.shape[0]),
        cos_sin=cos_sin,
        ground_idx=g_idx,
        aerial_idx=a_idx,
        valid=valid,
        q=q.masked_fill(~valid, 0.0),
        n_point_assoc=mp,
    )

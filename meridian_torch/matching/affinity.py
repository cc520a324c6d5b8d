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
repeated: near-parallel same-map line pairs are already rejected by the angle test.

Reference points of lines (lever arms): segment midpoint, ray start, midpoint of the two
points that define an infinite line.

Evaluation: the geometry of every *primitive* pair (point-line offsets, line-line closest
points, angles, lever arms) is computed once per side (P * A^2 aerial, G^2 ground pairs) and
only gathered per association pair (P * m^2, m ~ K_prim * G). Association pairs are scored in
row blocks over the upper triangle, so peak memory stays bounded by
`AffinityConfig.block_pairs`. `affinity_matrix` returns a dense (P, m, m) tensor,
`affinity_matrix_sparse` a coalesced sparse COO (P, m, m) tensor and `affinity` picks the form
by `AffinityConfig.dense_max_m` (see its description for the measurement behind the default).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Iterator

import torch

from meridian_torch.matching.associations import Associations
from meridian_torch.matching.config import AffinityConfig
from meridian_torch.types import LineKind, PrimitiveBatch, PrimitiveSet

__all__ = [
    "affinity",
    "affinity_matrix",
    "affinity_matrix_sparse",
    "unary_scores",
    "kernel",
    "nearest_point_on_line",
    "closest_points_between_lines",
]

# The reference's C++ constants: lines count as parallel within 0.1 deg, a point lies on a
# bounded line if its parameter is within 1 mm of the line's extent.
PARALLEL_EPS_RAD = math.radians(0.1)
NEARBY_EPS_M = 1e-3


def kernel(c: torch.Tensor, sigma: torch.Tensor | float, eps: torch.Tensor | float) -> torch.Tensor:
    """f(c; sigma, eps) = exp(-c^2 / (2 sigma^2)) if c <= eps else 0 (c = eps is accepted).

    Shapes: c (...); sigma, eps broadcastable to c -> (...).
    """
    # exp only sees arguments inside the window: far-out c would yield denormal results, which
    # are very slow on some CPUs, and they are discarded anyway.
    c_in = torch.minimum(c, torch.as_tensor(eps, dtype=c.dtype, device=c.device))
    return torch.exp(-0.5 * (c_in / sigma).square()).masked_fill(c > eps, 0.0)


# --------------------------------------------------------------------------------------------
# Bounded-line geometry. Everything is written on separate x / y component tensors: the
# scoring runs on millions of pairs, and scalar tensors avoid the slow strided size-2 axis.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Lines:
    """Lines as origin + t * direction with t in [lo, hi]; all fields broadcast together.

    ox, oy: origin (endpoints[0]); dx, dy: unit direction; lo: 0 or -inf; hi: segment length
    or +inf; tref: parameter of the reference point used for lever arms.
    """

    ox: torch.Tensor
    oy: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    tref: torch.Tensor

    def map_axis(self, axis: int) -> "_Lines":
        """Insert a broadcasting axis at `axis` in every field."""
        return _Lines(*(getattr(self, f.name).unsqueeze(axis) for f in fields(self)))

    def point(self, t: torch.Tensor) -> torch.Tensor:
        """(..., 2) the point at parameter t."""
        return torch.stack([self.ox + t * self.dx, self.oy + t * self.dy], dim=-1)

    def angle(self) -> torch.Tensor:
        """Sign-less direction angle in [0, pi)."""
        return torch.remainder(torch.atan2(self.dy, self.dx), math.pi)


def _line_params(endpoints: torch.Tensor, kinds: torch.Tensor) -> _Lines:
    """Parametric form of lines given by endpoints (..., 2, 2) and LineKind codes (...).

    SEGMENT: t in [0, |e1 - e0|]; RAY: t in [0, inf) from e0 through e1; INFINITE: all t.
    Reference point: segment midpoint, ray start, midpoint of an infinite line's two points.
    """
    e0 = endpoints[..., 0, :]
    delta = endpoints[..., 1, :] - e0
    length = delta.norm(dim=-1)
    safe = length.clamp_min(torch.finfo(delta.dtype).tiny)
    infinite = kinds == int(LineKind.INFINITE)
    ray = kinds == int(LineKind.RAY)
    lo = torch.where(infinite, torch.full_like(length, float("-inf")), torch.zeros_like(length))
    hi = torch.where(kinds == int(LineKind.SEGMENT), length, torch.full_like(length, float("inf")))
    tref = torch.where(ray, torch.zeros_like(length), 0.5 * length)
    return _Lines(e0[..., 0], e0[..., 1], delta[..., 0] / safe, delta[..., 1] / safe, lo, hi, tref)


def _clamp(t: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    return torch.minimum(torch.maximum(t, lo), hi)


def nearest_point_on_line(points: torch.Tensor, endpoints: torch.Tensor, kinds: torch.Tensor) -> torch.Tensor:
    """Nearest point to `points` on bounded lines (segment / ray / infinite), batched: the
    orthogonal projection clamped to the segment or to the ray's start.

    Shapes: points (..., 2), endpoints (..., 2, 2), kinds (...) broadcastable -> (..., 2).
    """
    line = _line_params(endpoints, kinds)
    t = (points[..., 0] - line.ox) * line.dx + (points[..., 1] - line.oy) * line.dy
    return line.point(_clamp(t, line.lo, line.hi))


def _closest_params(l1: _Lines, l2: _Lines) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Parameters (s1 on l1, s2 on l2) of the closest points of two bounded 2D lines, and
    `meet` (the lines touch, so the gap is exactly zero); fields broadcast together.

    Non-parallel lines whose infinite-line intersection lies on both bounded lines meet there.
    Parallel lines where one is infinite: that line's reference point and its nearest point on
    the other line. Otherwise the best endpoint candidate (each finite endpoint of one line with
    its nearest point on the other), which is the exact minimum for disjoint convex sets in 2D.
    """
    wx, wy = l2.ox - l1.ox, l2.oy - l1.oy
    c12 = l1.dx * l2.dx + l1.dy * l2.dy
    x12 = l1.dx * l2.dy - l1.dy * l2.dx
    w_d1 = wx * l1.dx + wy * l1.dy
    w_d2 = wx * l2.dx + wy * l2.dy
    w_x_d1 = wx * l1.dy - wy * l1.dx
    w_x_d2 = wx * l2.dy - wy * l2.dx
    parallel = c12.abs() >= math.cos(PARALLEL_EPS_RAD)
    safe = torch.where(parallel, torch.ones_like(x12), x12)
    t1, t2 = w_x_d2 / safe, w_x_d1 / safe
    meet = (
        ~parallel
        & (t1 >= l1.lo - NEARBY_EPS_M)
        & (t1 <= l1.hi + NEARBY_EPS_M)
        & (t2 >= l2.lo - NEARBY_EPS_M)
        & (t2 <= l2.hi + NEARBY_EPS_M)
    )

    # Endpoint candidates as a running best. An endpoint at parameter e of line 1 is
    # -w + e d1 relative to o2: along-l2 parameter -w.d2 + e c12, across cross(w, d2) - e x12.
    # An endpoint of line 2 relative to o1: along w.d1 + e c12, across w x d1 - e x12.
    best_d = torch.full_like(t1, float("inf"))
    s1, s2 = t1, t2
    for t_own, first in ((l1.lo, True), (l1.hi, True), (l2.lo, False), (l2.hi, False)):
        finite = torch.isfinite(t_own)
        e = torch.where(finite, t_own, torch.zeros_like(t_own))
        if first:
            along, across, lo, hi = -w_d2 + e * c12, w_x_d2 - e * x12, l2.lo, l2.hi
        else:
            along, across, lo, hi = w_d1 + e * c12, w_x_d1 - e * x12, l1.lo, l1.hi
        near = _clamp(along, lo, hi)
        dist = (across.square() + (along - near).square()).masked_fill(~finite, float("inf"))
        better = dist < best_d
        best_d = torch.minimum(best_d, dist)
        s1 = torch.where(better, e if first else near, s1)
        s2 = torch.where(better, near if first else e, s2)

    # Parallel with an infinite line: the gap is the same everywhere, anchor it at the reference.
    inf1 = torch.isinf(l1.lo)
    par1 = torch.where(inf1, l1.tref, _clamp(w_d1 + l2.tref * c12, l1.lo, l1.hi))
    par2 = torch.where(inf1, _clamp(-w_d2 + l1.tref * c12, l2.lo, l2.hi), l2.tref)
    par_inf = parallel & (inf1 | torch.isinf(l2.lo))
    s1 = torch.where(meet, t1, torch.where(par_inf, par1, s1))
    s2 = torch.where(meet, t2, torch.where(par_inf, par2, s2))
    return s1, s2, meet


def closest_points_between_lines(
    endpoints_1: torch.Tensor, kinds_1: torch.Tensor, endpoints_2: torch.Tensor, kinds_2: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closest points of two bounded 2D lines (segment / ray / infinite), batched.

    Shapes: endpoints_k (..., 2, 2), kinds_k (...) broadcastable -> (c1, c2), each (..., 2):
    c1 lies on line 1, c2 on line 2 (both the intersection point when the lines touch).
    """
    l1, l2 = _line_params(endpoints_1, kinds_1), _line_params(endpoints_2, kinds_2)
    s1, s2, meet = _closest_params(l1, l2)
    c1 = l1.point(s1)
    return c1, torch.where(meet[..., None], c1, l2.point(s2))


# --------------------------------------------------------------------------------------------
# Scores (component form)
# --------------------------------------------------------------------------------------------


def _point_pair_score(
    ax: torch.Tensor,
    ay: torch.Tensor,
    gx: torch.Tensor,
    gy: torch.Tensor,
    delta: torch.Tensor | float,
    cfg: AffinityConfig,
    rotated: bool,
    min_separation: bool,
) -> torch.Tensor:
    """Distance-invariance score of an aerial offset (ax, ay) and a ground offset (gx, gy).

    delta inflates sigma (and, per axis, eps) for points derived from lines. With a rotation
    prior the ground offsets are already rotated and each axis is also tested, with sigma and
    eps widened by the mean |axis offset| * sin(rotation uncertainty).
    """
    len_a, len_g = torch.hypot(ax, ay), torch.hypot(gx, gy)
    score = kernel((len_a - len_g).abs(), cfg.sigma_t_m + delta, cfg.epsilon_t_m)
    if min_separation:
        too_close = (len_a < cfg.min_point_separation_m) | (len_g < cfg.min_point_separation_m)
        score = score.masked_fill(too_close, 0.0)
    if rotated:
        sin_unc = math.sin(math.radians(cfg.rotation_uncertainty_deg))
        axis_score = torch.ones_like(score)
        for a, g in ((ax, gx), (ay, gy)):
            widen = 0.5 * (a.abs() + g.abs()) * sin_unc
            # Each axis carries half the variance of a 2D distance: sigma^2 / 2 and eps / sqrt(2),
            # i.e. the kernel with sigma / sqrt(2) and eps / sqrt(2).
            axis_score = axis_score * kernel(
                (a - g).abs(),
                (cfg.sigma_t_m + delta + widen) / math.sqrt(2.0),
                (cfg.epsilon_t_m + delta + widen) / math.sqrt(2.0),
            )
        score = torch.minimum(score, axis_score)
    return score


def _angle_between(phi_1: torch.Tensor, phi_2: torch.Tensor) -> torch.Tensor:
    """Sign-less angle between two lines given their angles in [0, pi): in [0, pi/2]."""
    diff = (phi_1 - phi_2).abs()
    return torch.minimum(diff, math.pi - diff)


# --------------------------------------------------------------------------------------------
# Primitive-pair tables. Every association pair (i, j) reuses the geometry of its primitive
# pair on each side; there are far fewer primitive pairs (P * A^2 aerial, G^2 ground) than
# association pairs (P * m^2, m ~ k * G), so the geometry is computed once per primitive pair
# and only gathered per association pair. Fields are rotation invariant except the offset
# vectors (vx, vy), which are rotated per patch when a rotation prior is given.
# --------------------------------------------------------------------------------------------


def _line_pair_table(l_i: _Lines, l_j: _Lines, with_vectors: bool) -> torch.Tensor:
    """(F, ...) for every pair of lines: [angle, gap length, lever sum (, gap x, gap y)].

    The gap is c_i - c_j between the closest points (exactly zero where the lines touch); the
    lever sum is |ref_i - c_i| + |ref_j - c_j|.
    """
    s_i, s_j, meet = _closest_params(l_i, l_j)
    gx = (l_i.ox + s_i * l_i.dx - l_j.ox - s_j * l_j.dx).masked_fill(meet, 0.0)
    gy = (l_i.oy + s_i * l_i.dy - l_j.oy - s_j * l_j.dy).masked_fill(meet, 0.0)
    angle = _angle_between(l_i.angle(), l_j.angle())
    lever = (l_i.tref - s_i).abs() + (l_j.tref - s_j).abs()
    fields_ = [angle, torch.hypot(gx, gy), lever] + ([gx, gy] if with_vectors else [])
    return torch.stack(torch.broadcast_tensors(*fields_))


def _point_line_table(px: torch.Tensor, py: torch.Tensor, line: _Lines, with_vectors: bool) -> torch.Tensor:
    """(F, ...) for every (point, line) pair: [along, across, lever (, v x, v y)].

    With N the nearest point on the bounded line, p - N = along * d + across * normal: along
    is non-zero only past a segment end or behind a ray start. lever = |ref - N|.
    """
    wx, wy = px - line.ox, py - line.oy
    t = wx * line.dx + wy * line.dy
    t_near = _clamp(t, line.lo, line.hi)
    fields_ = [t - t_near, wx * line.dy - wy * line.dx, (line.tref - t_near).abs()]
    if with_vectors:
        fields_ += [wx - t_near * line.dx, wy - t_near * line.dy]
    return torch.stack(torch.broadcast_tensors(*fields_))


def _line_line_score(a: torch.Tensor, g: torch.Tensor, cfg: AffinityConfig, rotated: bool) -> torch.Tensor:
    """s = sqrt(s_theta * s_t) from gathered line-pair table fields a (aerial), g (ground)."""
    theta_a, theta_g = a[0], g[0]
    s_theta = kernel(
        (theta_a - theta_g).abs(), math.radians(cfg.sigma_theta_deg), math.radians(cfg.epsilon_theta_deg)
    )
    min_angle = math.radians(cfg.min_line_angle_deg)
    s_theta = s_theta.masked_fill((theta_a < min_angle) | (theta_g < min_angle), 0.0)
    delta = math.tan(math.radians(cfg.sigma_theta_deg)) * 0.25 * (a[2] + g[2]) if cfg.lever_arm_inflation else 0.0
    if rotated:
        s_t = _point_pair_score(a[3], a[4], g[3], g[4], delta, cfg, True, min_separation=False)
    else:
        # Only the gap lengths matter: pass them as vectors along x.
        zero = torch.zeros_like(theta_a)
        s_t = _point_pair_score(a[1], zero, g[1], zero, delta, cfg, False, min_separation=False)
    return torch.sqrt(s_theta * s_t)


def _point_line_score(a: torch.Tensor, g: torch.Tensor, cfg: AffinityConfig, rotated: bool) -> torch.Tensor:
    """Point-line score from gathered point-line table fields a (aerial), g (ground): the
    along / across split with sigma/sqrt(2) (+ delta across), capped by the point-point score
    of (p, N)."""
    delta = math.tan(math.radians(cfg.sigma_theta_deg)) * 0.5 * (a[2] + g[2]) if cfg.lever_arm_inflation else 0.0
    sigma, eps = cfg.sigma_t_m / math.sqrt(2.0), cfg.epsilon_t_m / math.sqrt(2.0)
    split = kernel((a[0].abs() - g[0].abs()).abs(), sigma, eps) * kernel(
        (a[1].abs() - g[1].abs()).abs(), sigma + delta, eps + delta
    )
    if rotated:
        pair = _point_pair_score(a[3], a[4], g[3], g[4], delta, cfg, True, min_separation=False)
    else:
        # |p - N| from its two orthogonal parts.
        pair = _point_pair_score(a[0], a[1], g[0], g[1], delta, cfg, False, min_separation=False)
    return torch.minimum(split, pair)


# --------------------------------------------------------------------------------------------
# Gathering the associations' geometry
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Gathered:
    """Per-association indices and point coordinates, and the primitive-pair tables.

    Points: a_px, a_py, g_px, g_py (P, mp), ground already rotated by the prior. Local
    primitive indices within their type: a_pt, g_pt (P, mp), a_ln, g_ln (P, ml). Tables,
    flattened over their pair axes: a_pl (F, P * Ap * Al), g_pl (F, Gp * Gl),
    a_ll (F, P * Al * Al), g_ll (F, Gl * Gl).
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
    n_aerial_points: int
    n_aerial_lines: int
    n_ground_lines: int
    cos_sin: tuple[torch.Tensor, torch.Tensor] | None  # (P, 1, 1) each, with a rotation prior
    ground_idx: torch.Tensor  # (P, m) -1 in padding
    aerial_idx: torch.Tensor  # (P, m)
    valid: torch.Tensor  # (P, m)
    q: torch.Tensor  # (P, m) unary scores, 0 where invalid
    n_point_assoc: int


def _rotate(cos: torch.Tensor, sin: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return cos * x - sin * y, sin * x + cos * y


def _gather(
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    assoc: Associations,
    cfg: AffinityConfig,
    rotation_prior: torch.Tensor | None,
) -> _Gathered:
    device, dtype = aerial.points_xy.device, aerial.points_xy.dtype
    ground = ground.to(device=device, dtype=dtype)
    n_patches, mp = assoc.num_patches, assoc.n_point_assoc
    if aerial.points_xy.shape[0] != n_patches:
        raise ValueError(f"aerial batch has {aerial.points_xy.shape[0]} patches, associations {n_patches}")
    valid = assoc.valid.to(device)
    g_idx = torch.where(valid, assoc.pairs[..., 0].to(device), -1)
    a_idx = torch.where(valid, assoc.pairs[..., 1].to(device), -1)
    batch = torch.arange(n_patches, device=device)[:, None]

    # Padding entries point at index 0 of their type; their scores are masked out at fusion.
    g_pt = g_idx[:, :mp].clamp_min(0)
    a_pt = a_idx[:, :mp].clamp_min(0)
    g_ln = (g_idx[:, mp:] - assoc.n_ground_points).clamp_min(0)
    a_ln = (a_idx[:, mp:] - assoc.n_aerial_points).clamp_min(0)
    with_vectors = rotation_prior is not None

    # Tables over all primitive pairs of each side (aerial per patch).
    a_lines = _line_params(aerial.line_endpoints, aerial.line_kinds)  # (P, Al)
    g_lines = _line_params(ground.line_endpoints, ground.line_kinds)  # (Gl,)
    a_xy, g_xy = aerial.points_xy, ground.points_xy
    a_pl = _point_line_table(a_xy[..., :, None, 0], a_xy[..., :, None, 1], a_lines.map_axis(-2), with_vectors)
    g_pl = _point_line_table(g_xy[..., :, None, 0], g_xy[..., :, None, 1], g_lines.map_axis(-2), with_vectors)
    a_ll = _line_pair_table(a_lines.map_axis(-1), a_lines.map_axis(-2), with_vectors)
    g_ll = _line_pair_table(g_lines.map_axis(-1), g_lines.map_axis(-2), with_vectors)

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
        cos_sin = (cos[..., None], sin[..., None])
        # Absolute line direction must agree up to the remaining heading uncertainty.
        widen = math.radians(cfg.rotation_uncertainty_deg)
        a_phi = a_lines.angle()[batch, a_ln]
        g_phi = torch.remainder(g_lines.angle()[g_ln] + yaw, math.pi)
        heading = kernel(
            _angle_between(a_phi, g_phi),
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
        n_aerial_points=int(a_xy.shape[1]),
        n_aerial_lines=int(aerial.line_endpoints.shape[1]),
        n_ground_lines=int(ground.line_endpoints.shape[0]),
        cos_sin=cos_sin,
        ground_idx=g_idx,
        aerial_idx=a_idx,
        valid=valid,
        q=q.masked_fill(~valid, 0.0),
        n_point_assoc=mp,
    )


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


# --------------------------------------------------------------------------------------------
# Blocked evaluation
# --------------------------------------------------------------------------------------------


def _rows(x: torch.Tensor, r0: int, r1: int) -> torch.Tensor:
    return x[:, r0:r1, None]


def _cols(x: torch.Tensor, c0: int) -> torch.Tensor:
    return x[:, None, c0:]


def _take(table: torch.Tensor, key: torch.Tensor, cos_sin: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor:
    """Table rows at key (P, r, c) -> (F, P, r, c); vector fields 3, 4 rotated per patch."""
    out = table.index_select(1, key.reshape(-1)).view(table.shape[0], *key.shape)
    if cos_sin is not None:
        vx, vy = _rotate(*cos_sin, out[3], out[4])
        out = torch.cat([out[:3], vx[None], vy[None]])
    return out


def _point_rows_scores(gat: _Gathered, r0: int, r1: int, cfg: AffinityConfig) -> torch.Tensor:
    """s for point-association rows [r0, r1) against columns [r0, m): (P, r, m - r0)."""
    mp, rotated = gat.n_point_assoc, gat.cos_sin is not None
    a_x, a_y = _rows(gat.a_px, r0, r1), _rows(gat.a_py, r0, r1)
    g_x, g_y = _rows(gat.g_px, r0, r1), _rows(gat.g_py, r0, r1)
    pp = _point_pair_score(
        a_x - gat.a_px[:, None, r0:mp],
        a_y - gat.a_py[:, None, r0:mp],
        g_x - gat.g_px[:, None, r0:mp],
        g_y - gat.g_py[:, None, r0:mp],
        0.0,
        cfg,
        rotated,
        min_separation=True,
    )
    n_patches = gat.a_pt.shape[0]
    patch = torch.arange(n_patches, device=gat.a_pt.device)[:, None, None]
    a_key = (patch * gat.n_aerial_points + _rows(gat.a_pt, r0, r1)) * gat.n_aerial_lines + _cols(gat.a_ln, 0)
    g_key = _rows(gat.g_pt, r0, r1) * gat.n_ground_lines + _cols(gat.g_ln, 0)
    # Ground tables are in the odom frame; only their vectors need the patch's prior rotation.
    pl = _point_line_score(_take(gat.a_pl, a_key, None), _take(gat.g_pl, g_key, gat.cos_sin), cfg, rotated)
    return torch.cat([pp, pl], dim=2)


def _line_rows_scores(gat: _Gathered, r0: int, r1: int, cfg: AffinityConfig) -> torch.Tensor:
    """s for line-association rows [r0, r1) against columns [r0, m): (P, r, m - r0)."""
    lr0, lr1 = r0 - gat.n_point_assoc, r1 - gat.n_point_assoc
    n_patches, n_al = gat.a_ln.shape[0], gat.n_aerial_lines
    patch = torch.arange(n_patches, device=gat.a_ln.device)[:, None, None]
    a_key = (patch * n_al + _rows(gat.a_ln, lr0, lr1)) * n_al + _cols(gat.a_ln, lr0)
    g_key = _rows(gat.g_ln, lr0, lr1) * gat.n_ground_lines + _cols(gat.g_ln, lr0)
    return _line_line_score(
        _take(gat.a_ll, a_key, None), _take(gat.g_ll, g_key, gat.cos_sin), cfg, gat.cos_sin is not None
    )


def _blocks(gat: _Gathered, cfg: AffinityConfig) -> Iterator[tuple[int, int, torch.Tensor]]:
    """(r0, r1, X[:, r0:r1, r0:]) over the upper triangle in row blocks of ~block_pairs pairs.

    X = s q_i q_j, so M = cbrt(X); one-to-one conflicts, entries with M <= affinity_eps,
    padding and the diagonal are zeroed. The cube root is left to the caller so that the
    sparse path takes it on the few non-zeros only. Entries left of the diagonal inside a
    block's own square are not used.
    """
    n_patches, m = gat.valid.shape
    mp = gat.n_point_assoc
    rows = max(1, cfg.block_pairs // max(1, n_patches * m))
    for start, stop in ((0, mp), (mp, m)):
        for r0 in range(start, stop, rows):
            r1 = min(r0 + rows, stop)
            s = _point_rows_scores(gat, r0, r1, cfg) if r0 < mp else _line_rows_scores(gat, r0, r1, cfg)
            conflict = (_rows(gat.ground_idx, r0, r1) == _cols(gat.ground_idx, r0)) | (
                _rows(gat.aerial_idx, r0, r1) == _cols(gat.aerial_idx, r0)
            )
            product = s * _rows(gat.q, r0, r1) * _cols(gat.q, r0)
            # Padding has index -1 on both sides, so it always "conflicts" and needs no own mask.
            yield r0, r1, product.masked_fill(conflict | (product <= cfg.affinity_eps**3), 0.0)


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
    out = gat.q.new_zeros(n_patches, m, m)
    for r0, r1, product in _blocks(gat, cfg):
        block = product.pow(1.0 / 3.0)
        # Keep the strict upper part of the block's own square, then mirror the block into the
        # (still empty) columns r0:r1 below it: no full-size temporaries.
        block[:, :, : r1 - r0] = block[:, :, : r1 - r0].triu(diagonal=1)
        out[:, r0:r1, r0:] = block
        out[:, r0:, r0:r1] += block.transpose(1, 2)
    out.diagonal(dim1=1, dim2=2).copy_(gat.valid)
    return out


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
    gat = _gather(ground, aerial, assoc, cfg, rotation_prior)
    n_patches, m = gat.valid.shape
    device = gat.q.device
    indices, values = [], []
    for r0, r1, product in _blocks(gat, cfg):
        row = torch.arange(r0, r1, device=device)[:, None]
        col = torch.arange(r0, m, device=device)[None, :]
        keep = (product > 0) & (col > row)[None]
        nz = keep.nonzero()
        indices.append(nz + torch.tensor([0, r0, r0], device=device))
        values.append(product[keep].pow(1.0 / 3.0))
    upper_idx = torch.cat(indices) if indices else torch.zeros(0, 3, dtype=torch.int64, device=device)
    upper_val = torch.cat(values) if values else gat.q.new_zeros(0)
    diag = gat.valid.nonzero()
    idx = torch.cat([upper_idx, upper_idx[:, [0, 2, 1]], torch.stack([diag[:, 0], diag[:, 1], diag[:, 1]], 1)])
    val = torch.cat([upper_val, upper_val, upper_val.new_ones(diag.shape[0])])
    return torch.sparse_coo_tensor(idx.T, val, (n_patches, m, m), check_invariants=False).coalesce()


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

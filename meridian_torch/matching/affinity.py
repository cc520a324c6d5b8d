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
(P = 25, m = 2000) about 15x faster than scoring every pair. `affinity_matrix` returns a dense (P, m, m) tensor,
`affinity_matrix_sparse` a coalesced sparse COO (P, m, m) tensor and `affinity` picks the form
by `AffinityConfig.dense_max_m` (see its description for the measurement behind the default).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from meridian_torch.config.matching import AffinityConfig
from meridian_torch.matching.associations import Associations
from meridian_torch.types import LineKind, PrimitiveBatch, PrimitiveSet

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


def _line_pair_table(l_i: _Lines, l_j: _Lines, with_vectors: bool, parallel_below: float | None) -> torch.Tensor:
    """(F, ...) for every pair of lines: [angle, gap length, lever (, gap x, gap y)].

    The gap is c_i - c_j between the closest points (exactly zero where the lines touch); the
    lever is |ref_i - c_i| + |ref_j - c_j|. Pairs whose angle is below `parallel_below` (None:
    no such pairs) get their separation instead: the part of w = ref_j - ref_i across the two
    lines, w - ((w.d_i) d_i + (w.d_j) d_j) / 2 (independent of the direction signs), and as
    lever sin(angle) * (|w.d_i| + |w.d_j|) / 2, how much the separation can change between
    where the two maps measure it.
    """
    s_i, s_j, meet = _closest_params(l_i, l_j)
    gx = (l_i.ox + s_i * l_i.dx - l_j.ox - s_j * l_j.dx).masked_fill(meet, 0.0)
    gy = (l_i.oy + s_i * l_i.dy - l_j.oy - s_j * l_j.dy).masked_fill(meet, 0.0)
    angle = _angle_between(l_i.angle(), l_j.angle())
    lever = (l_i.tref - s_i).abs() + (l_j.tref - s_j).abs()
    if parallel_below is not None:
        wx = l_j.ox + l_j.tref * l_j.dx - l_i.ox - l_i.tref * l_i.dx
        wy = l_j.oy + l_j.tref * l_j.dy - l_i.oy - l_i.tref * l_i.dy
        w_di, w_dj = wx * l_i.dx + wy * l_i.dy, wx * l_j.dx + wy * l_j.dy
        # Reversed signs so that the vector is c_i - c_j like the gap.
        sx = 0.5 * (w_di * l_i.dx + w_dj * l_j.dx) - wx
        sy = 0.5 * (w_di * l_i.dy + w_dj * l_j.dy) - wy
        parallel = angle < parallel_below
        gx, gy = torch.where(parallel, sx, gx), torch.where(parallel, sy, gy)
        lever = torch.where(parallel, torch.sin(angle) * 0.5 * (w_di.abs() + w_dj.abs()), lever)
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
    """s = sqrt(s_theta * s_t) from gathered line-pair table fields a (aerial), g (ground).

    Near-parallel pairs (angle below min_line_angle_deg) score 0 with parallel_line_pairs =
    'reject'; with 'separation', pairs near-parallel in both maps compare their separations
    (the table's gap fields) and pairs near-parallel in one map only score 0.
    """
    theta_a, theta_g = a[0], g[0]
    s_theta = kernel(
        (theta_a - theta_g).abs(), math.radians(cfg.sigma_theta_deg), math.radians(cfg.epsilon_theta_deg)
    )
    min_angle = math.radians(cfg.min_line_angle_deg)
    par_a, par_g = theta_a < min_angle, theta_g < min_angle
    separation = cfg.parallel_line_pairs == "separation"
    s_theta = s_theta.masked_fill((par_a != par_g) if separation else (par_a | par_g), 0.0)
    if cfg.lever_arm_inflation:
        delta = math.tan(math.radians(cfg.sigma_theta_deg)) * 0.25 * (a[2] + g[2])
        if separation:  # the parallel lever is already a distance (sin(angle) * offset)
            delta = torch.where(par_a, 0.5 * (a[2] + g[2]), delta)
    else:
        delta = 0.0
    if rotated:
        s_t = _point_pair_score(a[3], a[4], g[3], g[4], delta, cfg, True, min_separation=False)
    else:
        # Only the gap lengths matter: pass them as vectors along x.
        zero = torch.zeros_like(theta_a)
        s_t = _point_pair_score(a[1], zero, g[1], zero, delta, cfg, False, min_separation=False)
    if separation:
        # Like the reference's line min-distance veto: near-parallel lines this close are
        # likely two edges of one structure and say little about the pose.
        too_close = (a[1] < cfg.min_point_separation_m) | (g[1] < cfg.min_point_separation_m)
        s_t = s_t.masked_fill(par_a & too_close, 0.0)
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


# Gates compare rotation-invariant table values that the exact scores recompute from rotated
# or differently rounded inputs; this slack (metres or radians) keeps the gate a strict superset.
_GATE_SLACK = 1e-3
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
    def same_type(value: torch.Tensor, minimum: float) -> torch.Tensor:
        # NaN fails every comparison. The diagonal (a primitive with itself, i.e. two
        # associations sharing it) is NaN too, so the gate also enforces one-to-one.
        n = value.shape[-1]
        self_pair = torch.eye(n, dtype=torch.bool, device=value.device)
        return value.masked_fill((value < minimum) | self_pair, float("nan")).flatten()

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
        parallel = torch.where(too_close, float("nan"), _PARALLEL_GATE_OFFSET + scale * ll[1])
        return same_type(torch.where(ll[0] < min_angle, parallel, ll[0]), float("-inf"))

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
# Gated evaluation: a cheap necessary condition over all association pairs of a row block,
# the exact scores only on the survivors (a few per cent), as flat index lists.
# --------------------------------------------------------------------------------------------


def _take(table: torch.Tensor, key: torch.Tensor, cos_sin: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor:
    """Table columns at key (n,) -> (F, n); vector fields 3, 4 rotated by the per-entry (cos, sin)."""
    out = table.index_select(1, key)
    if cos_sin is not None:
        vx, vy = _rotate(*cos_sin, out[3], out[4])
        out = torch.cat([out[:3], vx[None], vy[None]])
    return out


def _pair_scores(gat: _Gathered, b: torch.Tensor, i: torch.Tensor, j: torch.Tensor, kind: str, cfg: AffinityConfig) -> torch.Tensor:
    """Exact s of the association pairs (b, i, j), flat (n,); kind 'pp', 'pl' (i point, j line) or 'll'."""
    rotated = gat.cos_sin is not None
    cos_sin = (gat.cos_sin[0][b], gat.cos_sin[1][b]) if rotated else None
    mp = gat.n_point_assoc
    if kind == "pp":
        return _point_pair_score(
            gat.a_px[b, i] - gat.a_px[b, j],
            gat.a_py[b, i] - gat.a_py[b, j],
            gat.g_px[b, i] - gat.g_px[b, j],
            gat.g_py[b, i] - gat.g_py[b, j],
            0.0,
            cfg,
            rotated,
            min_separation=True,
        )
    if kind == "pl":
        a_key = (b * gat.n_aerial_points + gat.a_pt[b, i]) * gat.n_aerial_lines + gat.a_ln[b, j - mp]
        g_key = gat.g_pt[b, i] * gat.n_ground_lines + gat.g_ln[b, j - mp]
        # Ground tables are in the odom frame; only their vectors need the patch's prior rotation.
        return _point_line_score(_take(gat.a_pl, a_key, None), _take(gat.g_pl, g_key, cos_sin), cfg, rotated)
    n_al = gat.n_aerial_lines
    a_key = (b * n_al + gat.a_ln[b, i - mp]) * n_al + gat.a_ln[b, j - mp]
    g_key = gat.g_ln[b, i - mp] * gat.n_ground_lines + gat.g_ln[b, j - mp]
    return _line_line_score(_take(gat.a_ll, a_key, None), _take(gat.g_ll, g_key, cos_sin), cfg, rotated)


def _gate(gat: _Gathered, r0: int, r1: int, c0: int, c1: int, kind: str, cfg: AffinityConfig) -> torch.Tensor:
    """(P, r1 - r0, c1 - c0) bool: pairs of rows [r0, r1) and columns [c0, c1) (strict upper
    triangle) that may score non-zero: the kind's table values within tolerance (which also
    excludes shared primitives)."""
    n_patches = gat.valid.shape[0]
    mp = gat.n_point_assoc
    patch = torch.arange(n_patches, device=gat.valid.device)[:, None, None]
    if kind == "pp":
        rows_a, cols_a, rows_g, cols_g = gat.a_pt[:, r0:r1], gat.a_pt[:, c0:c1], gat.g_pt[:, r0:r1], gat.g_pt[:, c0:c1]
        n_a, n_g, tol = (gat.n_aerial_points, gat.n_aerial_points), (gat.n_ground_points,) * 2, cfg.epsilon_t_m
        tables = gat.a_pp_gate, gat.g_pp_gate
    elif kind == "pl":
        rows_a, cols_a = gat.a_pt[:, r0:r1], gat.a_ln[:, c0 - mp : c1 - mp]
        rows_g, cols_g = gat.g_pt[:, r0:r1], gat.g_ln[:, c0 - mp : c1 - mp]
        n_a, n_g, tol = (gat.n_aerial_points, gat.n_aerial_lines), (gat.n_ground_points, gat.n_ground_lines), cfg.epsilon_t_m
        tables = gat.a_pl_gate, gat.g_pl_gate
    else:
        rows_a, cols_a = gat.a_ln[:, r0 - mp : r1 - mp], gat.a_ln[:, c0 - mp : c1 - mp]
        rows_g, cols_g = gat.g_ln[:, r0 - mp : r1 - mp], gat.g_ln[:, c0 - mp : c1 - mp]
        n_a, n_g = (gat.n_aerial_lines,) * 2, (gat.n_ground_lines,) * 2
        tol, tables = math.radians(cfg.epsilon_theta_deg), (gat.a_ll_gate, gat.g_ll_gate)
    # int32 keys and in-place arithmetic: this runs on every pair, so memory traffic is the cost.
    a_key = ((patch * n_a[0] + rows_a[:, :, None]) * n_a[1]).to(torch.int32) + cols_a[:, None, :].to(torch.int32)
    g_key = (rows_g[:, :, None] * n_g[1]).to(torch.int32) + cols_g[:, None, :].to(torch.int32)
    diff = tables[0].index_select(0, a_key.view(-1))
    diff.sub_(tables[1].index_select(0, g_key.view(-1))).abs_()
    ok = (diff <= tol + _GATE_SLACK).view(a_key.shape)
    # q_i q_j is not gated here: pairs with q = 0 (padding included) score 0 and are dropped after scoring.
    if c0 < r1:
        ok &= torch.arange(c0, c1, device=ok.device)[None, None, :] > torch.arange(r0, r1, device=ok.device)[None, :, None]
    return ok


def _entries(gat: _Gathered, cfg: AffinityConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Non-zero strict-upper-triangle entries: indices (n, 3) of (patch, i, j) and M values (n,).

    M = cbrt(s q_i q_j); one-to-one conflicts, entries with M <= affinity_eps and padding are
    left out. Rows are evaluated in blocks of ~block_pairs pairs, which bounds peak memory.
    """
    n_patches, m = gat.valid.shape
    mp = gat.n_point_assoc
    rows = max(1, cfg.block_pairs // max(1, n_patches * m))
    indices, values = [], []
    for start, stop in ((0, mp), (mp, m)):
        for r0 in range(start, stop, rows):
            r1 = min(r0 + rows, stop)
            spans = [(r0, mp, "pp"), (mp, m, "pl")] if r0 < mp else [(r0, m, "ll")]
            for c0, c1, kind in spans:
                if c1 <= c0:
                    continue
                nz = _gate(gat, r0, r1, c0, c1, kind, cfg).nonzero()
                b, i, j = nz[:, 0], nz[:, 1] + r0, nz[:, 2] + c0
                product = _pair_scores(gat, b, i, j, kind, cfg) * gat.q[b, i] * gat.q[b, j]
                keep = product > cfg.affinity_eps**3
                indices.append(torch.stack([b, i, j], 1)[keep])
                values.append(product[keep].pow(1.0 / 3.0))
    if not indices:
        return torch.zeros(0, 3, dtype=torch.int64, device=gat.q.device), gat.q.new_zeros(0)
    return torch.cat(indices), torch.cat(values)


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
        upper, diag = self.index, self.valid.nonzero()
        idx = torch.cat([upper, upper[:, [0, 2, 1]], torch.stack([diag[:, 0], diag[:, 1], diag[:, 1]], 1)])
        val = torch.cat([self.value, self.value, self.value.new_ones(diag.shape[0])])
        return torch.sparse_coo_tensor(idx.T, val, self.shape, check_invariants=False).coalesce()


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

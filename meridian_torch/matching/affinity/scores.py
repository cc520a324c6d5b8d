"""Scores of the affinity in component form: the kernel, the primitive-pair tables (the geometry
of every point-line and line-line pair of one map) and the pair scores that compare an aerial
and a ground table entry.

Every association pair (i, j) reuses the geometry of its primitive pair on each side; there
are far fewer primitive pairs (P * A^2 aerial, G^2 ground) than association pairs (P * m^2,
m ~ k * G), so the geometry is computed once per primitive pair and only gathered per
association pair. Table fields are rotation invariant except the offset vectors (vx, vy),
which are rotated per patch when a rotation prior is given.
"""

from __future__ import annotations

import math

import torch

from meridian_torch.config.matching import AffinityConfig
from meridian_torch.geometry.se2 import line_angle_between
from meridian_torch.matching.affinity.lines import _clamp, _closest_params, _Lines

__all__ = ["kernel"]

# Gates compare rotation-invariant table values that the exact scores recompute from rotated
# or differently rounded inputs; this slack (metres or radians) keeps the gate a strict superset.
_GATE_SLACK = 1e-3


def kernel(c: torch.Tensor, sigma: torch.Tensor | float, eps: torch.Tensor | float) -> torch.Tensor:
    """f(c; sigma, eps) = exp(-c^2 / (2 sigma^2)) if c <= eps else 0 (c = eps is accepted).

    Shapes: c (...); sigma, eps broadcastable to c -> (...).
    """
    # exp only sees arguments inside the window: far-out c would yield denormal results, which
    # are very slow on some CPUs, and they are discarded anyway.
    c_in = torch.minimum(c, torch.as_tensor(eps, dtype=c.dtype, device=c.device))
    return torch.exp(-0.5 * (c_in / sigma).square()).masked_fill(c > eps, 0.0)


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
    angle = line_angle_between(l_i.angle(), l_j.angle())
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

"""Batched SE(2) registration of associated points and lines (the reference's modified Arun).

`register_se2` estimates, for each of B association sets, the proper rigid transform
T_dst_src (dst ≈ R src + t) mapping the source (ground submap, odom x-y) into the destination
(aerial patch, world). In matching B = patches x particles, so everything is batched; there is
no Python loop over B.

Formulation. With u = (cos θ, sin θ) every residual is linear in x = (u, t):
- a point pair (p, q):        R p + t - q                                 (2 rows, weight w)
- a line pair, offset:        n_dst · (R a + t) - n_dst · b               (1 row, weight v)
- a line pair, direction:     n_dst · (R d_src)                           (1 row, weight v·λ)
where a, b are the midpoints of the given source / destination endpoints, d_src is the source
unit direction, n_dst the destination unit normal and λ = `line_direction_weight`. The offset
row is the point-to-line constraint, the direction row is sin of the angle between the rotated
source line and the destination line (its square is the doubled-angle Arun term of undirected
lines). The weighted least squares in x is reduced to θ alone by eliminating t (a 2x2 Schur
complement), which leaves a trigonometric polynomial f(θ) = a0 + a_c cos 2θ + a_s sin 2θ +
b_c cos θ + b_s sin θ that is minimised globally (angle grid + bracketed Newton). Consequences:
- Only proper rotations exist in this parametrisation (det R = +1 by construction); mirrored
  data gives a poor residual, never a reflection.
- Flipping the sign of a line direction flips the sign of its rows' residuals, which the squared
  loss ignores, so the per-line sign enumeration of the reference is unnecessary. What is left of
  the sign ambiguity is global: f can have a second local minimum (typically near θ* + π, e.g.
  lines only, all through one point). It is reported as `ambiguity_gap` = f(second) - f(best);
  a small gap means two rotations explain the data about equally well -> invalid.
- The solution is the global optimum of the joint points + point-to-line objective, so a
  Gauss-Newton refinement afterwards has nothing left to improve and is not done.

Lines are infinite for the purpose of the constraints: a segment's or ray's endpoints need not
correspond between source and destination.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from meridian_torch.config.matching import RegistrationConfig
from meridian_torch.geometry.se2 import rotation_matrix, se2_matrix, wrap_angle
from meridian_torch.geometry.vectors import cross2, dot2, squared_norm2

__all__ = ["RegistrationResult", "register_se2"]


@dataclass(frozen=True)
class RegistrationResult:
    """Per-set registration T_dst_src: dst ≈ R src + t. All fields have leading dimension B."""

    theta: torch.Tensor  # (B,) rotation angle, radians in [-pi, pi)
    R: torch.Tensor  # (B, 2, 2) R_dst_src, det = +1
    t: torch.Tensor  # (B, 2) t_dst_src, destination units
    valid: torch.Tensor  # (B,) bool: well determined (not degenerate, not ambiguous, finite)
    condition: torch.Tensor  # (B,) min(rotation info (weight m^2), smallest translation info (weight))
    ambiguity_gap: torch.Tensor  # (B,) cost of the second-best rotation minus the best; inf if none
    point_residual: torch.Tensor  # (B,) weighted RMS of ||R p + t - q||; 0 without points
    # (B,) weighted RMS distance of the mapped source endpoints to the destination lines; 0 without lines
    line_residual: torch.Tensor

    @property
    def T_dst_src(self) -> torch.Tensor:
        """(B, 3, 3) homogeneous transforms."""
        return se2_matrix(self.theta, self.t)


def register_se2(
    src_points: torch.Tensor,
    dst_points: torch.Tensor,
    point_weights: torch.Tensor,
    src_lines: torch.Tensor,
    dst_lines: torch.Tensor,
    line_weights: torch.Tensor,
    *,
    rotation_prior: torch.Tensor | None = None,
    config: RegistrationConfig | None = None,
) -> RegistrationResult:
    """Register B association sets of points and lines.

    Args:
        src_points, dst_points: (B, m, 2) associated points (source = ground, destination = aerial).
        point_weights: (B, m) non-negative weights; 0 marks unused / padded entries.
        src_lines, dst_lines: (B, k, 2, 2) two endpoints per associated line (any two distinct
            points of the line; kinds are irrelevant because constraints treat lines as infinite).
        line_weights: (B, k) non-negative weights; 0 marks unused / padded entries.
        rotation_prior: (B,) known rotation angles (radians); if given only t is solved.
        config: weights and thresholds; defaults to `RegistrationConfig()`.

    Returns:
        A `RegistrationResult`. Degenerate or ambiguous sets still get a (meaningless but finite
        where possible) transform, with `valid` False.
    """
    cfg = config or RegistrationConfig()
    B = _check_shapes(
        src_points, dst_points, point_weights, src_lines, dst_lines, line_weights, rotation_prior
    )
    dtype, device = src_points.dtype, src_points.device
    tiny = torch.finfo(dtype).tiny
    w = point_weights.to(dtype).clamp_min(0.0)
    v = line_weights.to(dtype).clamp_min(0.0)
    # Zero the unused entries: their weight is 0, but 0 * nan filler would still poison the sums.
    src_points, dst_points = (torch.where(w[..., None] > 0, x, 0.0) for x in (src_points, dst_points))
    src_lines, dst_lines = (torch.where(v[..., None, None] > 0, x, 0.0) for x in (src_lines, dst_lines))

    src_dir, src_ok = _unit_direction(src_lines)
    dst_dir, dst_ok = _unit_direction(dst_lines)
    # A zero-length line has no direction; it cannot constrain anything, so it is dropped.
    v = v * (src_ok & dst_ok).to(dtype)
    dst_normal = torch.stack([-dst_dir[..., 1], dst_dir[..., 0]], -1)
    src_mid, dst_mid = src_lines.mean(-2), dst_lines.mean(-2)

    # Centre both sides on their weighted reference points (points and line midpoints), as the
    # reference does: world coordinates can be UTM (~1e6 m), too large for float32 normal equations.
    W = w.sum(-1)
    total = (W + v.sum(-1)).clamp_min(tiny)
    c_src = ((w[..., None] * src_points).sum(1) + (v[..., None] * src_mid).sum(1)) / total[:, None]
    c_dst = ((w[..., None] * dst_points).sum(1) + (v[..., None] * dst_mid).sum(1)) / total[:, None]
    p, q = src_points - c_src[:, None], dst_points - c_dst[:, None]
    a, b = src_mid - c_src[:, None], dst_mid - c_dst[:, None]

    # Normal equations H x = g of the weighted least squares in x = (cos θ, sin θ, tx, ty); see the
    # module docstring for the rows. The point rows (p_x, -p_y, 1, 0) and (p_y, p_x, 0, 1) with
    # targets q_x, q_y are summed in closed form so that no (B, m, 4) Jacobian is materialised.
    p_sq = (w * squared_norm2(p)).sum(-1)
    p_sum, q_sum = (w[..., None] * p).sum(1), (w[..., None] * q).sum(1)
    zeros_b = W.new_zeros(B)
    H = torch.stack(
        [
            torch.stack([p_sq, zeros_b, p_sum[:, 0], p_sum[:, 1]], -1),
            torch.stack([zeros_b, p_sq, -p_sum[:, 1], p_sum[:, 0]], -1),
            torch.stack([p_sum[:, 0], -p_sum[:, 1], W, zeros_b], -1),
            torch.stack([p_sum[:, 1], p_sum[:, 0], zeros_b, W], -1),
        ],
        -2,
    )
    g = torch.stack([(w * dot2(p, q)).sum(-1), (w * cross2(p, q)).sum(-1), q_sum[:, 0], q_sum[:, 1]], -1)
    offset_rows = torch.stack([dot2(dst_normal, a), cross2(a, dst_normal), *dst_normal.unbind(-1)], -1)
    direction_rows = torch.stack([dot2(dst_normal, src_dir), cross2(src_dir, dst_normal)], -1)
    H = H + torch.einsum("bki,bk,bkj->bij", offset_rows, v, offset_rows)
    direction_weight = cfg.line_direction_weight * v
    H[:, :2, :2] += torch.einsum("bki,bk,bkj->bij", direction_rows, direction_weight, direction_rows)
    g = g + torch.einsum("bki,bk->bi", offset_rows, v * dot2(dst_normal, b))

    # Eliminate t: for fixed u the optimum is t = Htt^-1 (g_t - Htr u).
    H_rr, H_rt, H_tt = H[:, :2, :2], H[:, :2, 2:], H[:, 2:, 2:]
    H_tt_inv = _inverse_2x2(H_tt)
    M = H_rr - H_rt @ H_tt_inv @ H_rt.transpose(1, 2)
    g_red = g[:, :2] - (H_rt @ H_tt_inv @ g[:, 2:, None])[..., 0]

    if rotation_prior is None:
        theta, ambiguity_gap = _minimise_angle(M, g_red, cfg)
    else:
        theta = wrap_angle(rotation_prior.to(dtype))
        ambiguity_gap = torch.full((B,), math.inf, dtype=dtype, device=device)
    u = torch.stack([torch.cos(theta), torch.sin(theta)], -1)
    t_centred = (H_tt_inv @ (g[:, 2:] - (H_rt.transpose(1, 2) @ u[..., None])[..., 0])[..., None])[..., 0]
    R = rotation_matrix(theta)
    t = t_centred + c_dst - (R @ c_src[..., None])[..., 0]

    # Gauss-Newton information of the solution. Rotation: marginal over t (the Schur complement,
    # independent of the origin). Translation: given θ, which equals the marginal one about the
    # point where rotation and translation decouple, so it does not depend on the centring either.
    if rotation_prior is None:
        rotation_info = _quad(M, torch.stack([-u[:, 1], u[:, 0]], -1))
    else:
        rotation_info = torch.full((B,), math.inf, dtype=dtype, device=device)
    translation_info = _min_eigenvalue_2x2(H_tt)
    condition = torch.minimum(rotation_info, translation_info)

    point_residual, line_residual = _residuals(
        R, t_centred, p, q, w, src_lines - c_src[:, None, None], b, dst_normal, v
    )
    finite = torch.isfinite(theta) & torch.isfinite(t).all(-1)
    valid = finite & (condition > cfg.information_eps) & (ambiguity_gap > cfg.ambiguity_eps)
    return RegistrationResult(
        theta=theta,
        R=R,
        t=t,
        valid=valid,
        condition=condition,
        ambiguity_gap=ambiguity_gap,
        point_residual=point_residual,
        line_residual=line_residual,
    )


def _check_shapes(
    src_points: torch.Tensor,
    dst_points: torch.Tensor,
    point_weights: torch.Tensor,
    src_lines: torch.Tensor,
    dst_lines: torch.Tensor,
    line_weights: torch.Tensor,
    rotation_prior: torch.Tensor | None,
) -> int:
    """Validate the argument shapes against (B, m, 2) points and (B, k, 2, 2) lines; returns B."""
    if src_points.ndim != 3 or src_points.shape[-1] != 2:
        raise ValueError(f"src_points: expected (B, m, 2), got {tuple(src_points.shape)}")
    B, m = src_points.shape[:2]
    if src_lines.ndim != 4 or src_lines.shape[0] != B or src_lines.shape[2:] != (2, 2):
        raise ValueError(f"src_lines: expected ({B}, k, 2, 2), got {tuple(src_lines.shape)}")
    k = src_lines.shape[1]
    expected = {
        "dst_points": (dst_points, (B, m, 2)),
        "point_weights": (point_weights, (B, m)),
        "dst_lines": (dst_lines, (B, k, 2, 2)),
        "line_weights": (line_weights, (B, k)),
    }
    if rotation_prior is not None:
        expected["rotation_prior"] = (rotation_prior, (B,))
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {tuple(tensor.shape)}")
    if not src_points.is_floating_point():
        raise ValueError("src_points must be a floating-point tensor")
    return B


def _quad(A: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """x^T A x for (B, 2, 2) A and (B, 2) x."""
    return (x[:, :, None] * A * x[:, None, :]).sum((1, 2))


def _unit_direction(lines: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit direction of (B, k, 2, 2) endpoint pairs and whether it is defined (non-zero length)."""
    delta = lines[..., 1, :] - lines[..., 0, :]
    length = torch.linalg.vector_norm(delta, dim=-1)
    ok = length > torch.finfo(lines.dtype).eps * (1.0 + torch.linalg.vector_norm(lines[..., 0, :], dim=-1))
    return delta / torch.where(ok, length, torch.ones_like(length))[..., None], ok


def _inverse_2x2(A: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse of (B, 2, 2) matrices; singular ones get a clamped determinant.

    A singular H_tt means the translation is unconstrained along some direction; the set is then
    flagged invalid by its translation information, and the clamp only keeps the output finite.
    """
    det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    scale = A.abs().amax((1, 2)) ** 2
    floor = torch.finfo(A.dtype).eps * scale + torch.finfo(A.dtype).tiny
    det = torch.where(det.abs() > floor, det, floor)
    adj = torch.stack(
        [torch.stack([A[:, 1, 1], -A[:, 0, 1]], -1), torch.stack([-A[:, 1, 0], A[:, 0, 0]], -1)], -2
    )
    return adj / det[:, None, None]


def _min_eigenvalue_2x2(A: torch.Tensor) -> torch.Tensor:
    """Smallest eigenvalue of symmetric (B, 2, 2) matrices, in closed form."""
    half_trace = 0.5 * (A[:, 0, 0] + A[:, 1, 1])
    half_diff = 0.5 * (A[:, 0, 0] - A[:, 1, 1])
    off = 0.5 * (A[:, 0, 1] + A[:, 1, 0])
    return half_trace - torch.sqrt(half_diff**2 + off**2)


def _angle_terms(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """cos θ, sin θ, cos 2θ, sin 2θ: computed once for f and its derivatives at the same θ."""
    return torch.cos(theta), torch.sin(theta), torch.cos(2 * theta), torch.sin(2 * theta)


def _angle_cost(
    coef: torch.Tensor, terms: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], order: int
) -> torch.Tensor:
    """Order-th derivative of f(θ) - a0 = a_c cos 2θ + a_s sin 2θ + b_c cos θ + b_s sin θ.

    coef is (B, 4) = (a_c, a_s, b_c, b_s); terms are `_angle_terms` of θ, (B, n) or (n,) (the
    same angles for every set). The constant a0 is left out because only differences and
    derivatives of f are needed.
    """
    a_c, a_s, b_c, b_s = (coef[:, i, None] for i in range(4))
    c1, s1, c2, s2 = terms
    if order == 0:
        return a_c * c2 + a_s * s2 + b_c * c1 + b_s * s1
    if order == 1:
        return 2 * (a_s * c2 - a_c * s2) + b_s * c1 - b_c * s1
    return -4 * (a_c * c2 + a_s * s2) - b_c * c1 - b_s * s1


def _minimise_angle(
    M: torch.Tensor, g_red: torch.Tensor, cfg: RegistrationConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Global minimiser of f(u) = u^T M u - 2 g_red^T u over unit u = (cos θ, sin θ).

    f is a degree-2 trigonometric polynomial in θ with at most two local minima. Grid points
    that are local minima of the sampled f bracket them to within one grid step; the two best
    brackets are refined by Newton steps clamped to their bracket. Returns θ (B,) and the cost
    gap to the other local minimum (inf if there is none).
    """
    dtype, device = M.dtype, M.device
    # u^T M u = (m00 + m11)/2 + (m00 - m11)/2 cos 2θ + m01 sin 2θ; the constant part is dropped.
    a_c, a_s = 0.5 * (M[:, 0, 0] - M[:, 1, 1]), 0.5 * (M[:, 0, 1] + M[:, 1, 0])
    coef = torch.stack([a_c, a_s, -2 * g_red[:, 0], -2 * g_red[:, 1]], -1)
    n = cfg.n_angle_samples
    step = 2 * math.pi / n
    grid = -math.pi + step * torch.arange(n, dtype=dtype, device=device)
    # The grid's sines and cosines once, not per set (cos and sin round each element alike).
    f_grid = _angle_cost(coef, _angle_terms(grid), 0)
    # Strict on one side so that two exactly equal neighbours count as one minimum.
    is_min = (f_grid < f_grid.roll(1, -1)) & (f_grid <= f_grid.roll(-1, -1))
    # The global grid minimum is a local one (unless f is flat); ranking by masked cost puts it first.
    masked = torch.where(is_min, f_grid, torch.full_like(f_grid, math.inf))
    ranked = masked.topk(2, dim=-1, largest=False)
    has_second = torch.isfinite(ranked.values[:, 1])
    start = grid[ranked.indices]
    lo, hi = start - step, start + step
    theta = start
    for _ in range(cfg.newton_iterations):
        terms = _angle_terms(theta)
        d1 = _angle_cost(coef, terms, 1)
        d2 = _angle_cost(coef, terms, 2)
        # Where f is not convex a Newton step would head for a maximum: walk downhill instead.
        newton = -d1 / d2.clamp_min(torch.finfo(dtype).tiny)
        theta = torch.clamp(theta + torch.where(d2 > 0, newton, -torch.sign(d1) * step), lo, hi)
    f_ref = _angle_cost(coef, _angle_terms(theta), 0)
    # Without a second grid minimum the second bracket is an arbitrary grid point: ignore it.
    first_best = (f_ref[:, 0] <= f_ref[:, 1]) | ~has_second
    best = torch.where(first_best, theta[:, 0], theta[:, 1])
    # Two brackets that converge to one minimum (a minimum between two grid points) are one candidate.
    distinct = has_second & (wrap_angle(theta[:, 0] - theta[:, 1]).abs() > 2 * step)
    gap = torch.where(distinct, (f_ref[:, 0] - f_ref[:, 1]).abs(), torch.full_like(best, math.inf))
    return wrap_angle(best), gap


def _residuals(
    R: torch.Tensor,
    t_centred: torch.Tensor,
    p: torch.Tensor,
    q: torch.Tensor,
    w: torch.Tensor,
    src_line_ends: torch.Tensor,
    b: torch.Tensor,
    dst_normal: torch.Tensor,
    v: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted RMS point residual and point-to-line residual, computed in centred coordinates."""
    mapped = p @ R.transpose(1, 2) + t_centred[:, None]
    point_sq = squared_norm2(mapped - q)
    ends = src_line_ends @ R.transpose(1, 2)[:, None] + t_centred[:, None, None]
    line_sq = (dot2(ends - b[:, :, None], dst_normal[:, :, None]) ** 2).mean(-1)
    return _weighted_rms(point_sq, w), _weighted_rms(line_sq, v)


def _weighted_rms(sq: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    total = weight.sum(-1)
    mean = (weight * sq).sum(-1) / total.clamp_min(torch.finfo(sq.dtype).tiny)
    return torch.where(total > 0, mean.sqrt(), torch.zeros_like(mean))

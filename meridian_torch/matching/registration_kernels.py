"""Compiled (numba) registration of every inlier set of a patch group, for CPU arrays.

`register_set_masks` is `hypotheses.register_sets` (members gathered from the set masks, then
`registration.register_se2` without a rotation prior) in one pass per set: the same
formulation, the same angle grid, bracketed Newton steps and validity rules. The torch path
runs ~150 small ops on (sets, members) tensors per patch group, whose dispatch held the GIL
while the groups ran side by side; this kernel releases it.

Arithmetic is float64 (the torch path runs in the inputs' dtype, float32 in matching), so the
results agree with torch's to the inputs' rounding, not bit for bit: poses by ~1e-6 of the
coordinates, and a validity or clustering decision can differ only where a value lies within
rounding of its threshold. The dtype-dependent guards (`_inverse_2x2`'s determinant floor, the
zero-length line test, the clamps by `tiny`) use the inputs' dtype's eps and tiny, as torch does.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["register_set_masks"]


@njit(cache=True, nogil=True, error_model="numpy")
def register_set_masks(
    masks: np.ndarray,
    assoc_valid: np.ndarray,
    pairs: np.ndarray,
    n_point_assoc: int,
    n_ground_points: int,
    n_aerial_points: int,
    ground_points: np.ndarray,
    ground_lines: np.ndarray,
    aerial_points: np.ndarray,
    aerial_lines: np.ndarray,
    line_direction_weight: float,
    information_eps: float,
    ambiguity_eps: float,
    n_angle_samples: int,
    newton_iterations: int,
    eps: float,
    tiny: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """theta (P, S), t (P, S, 2), valid, condition, ambiguity_gap, point_residual, line_residual
    (P, S) of the sets `masks` (P, S, m) bool over the associations `pairs` (P, m, 2): the first
    `n_point_assoc` columns are point associations (ground point, aerial point), the rest line
    associations (ground index counted after `n_ground_points` points, aerial after
    `n_aerial_points`). Members are associations in the set and `assoc_valid` (P, m)."""
    n_patches, n_sets, m = masks.shape
    theta_out = np.zeros((n_patches, n_sets))
    t_out = np.zeros((n_patches, n_sets, 2))
    valid_out = np.zeros((n_patches, n_sets), dtype=np.bool_)
    condition_out = np.zeros((n_patches, n_sets))
    gap_out = np.zeros((n_patches, n_sets))
    point_res_out = np.zeros((n_patches, n_sets))
    line_res_out = np.zeros((n_patches, n_sets))

    step = 2.0 * math.pi / n_angle_samples
    grid = np.empty(n_angle_samples)
    grid_terms = np.empty((n_angle_samples, 4))
    for j in range(n_angle_samples):
        grid[j] = -math.pi + step * j
        grid_terms[j, 0] = math.cos(grid[j])
        grid_terms[j, 1] = math.sin(grid[j])
        grid_terms[j, 2] = math.cos(2.0 * grid[j])
        grid_terms[j, 3] = math.sin(2.0 * grid[j])
    f_grid = np.empty(n_angle_samples)

    # The members of one set: point ends (src, dst) and line ends, midpoints, directions and weights.
    src_pt = np.empty((m, 2))
    dst_pt = np.empty((m, 2))
    src_ln = np.empty((m, 2, 2))
    dst_ln = np.empty((m, 2, 2))
    src_mid = np.empty((m, 2))
    dst_mid = np.empty((m, 2))
    src_dir = np.empty((m, 2))
    dst_normal = np.empty((m, 2))
    line_w = np.empty(m)
    H = np.empty((4, 4))
    gv = np.empty(4)

    for p in range(n_patches):
        for s in range(n_sets):
            n_pt = 0
            n_ln = 0
            for j in range(m):
                if not (masks[p, s, j] and assoc_valid[p, j]):
                    continue
                if j < n_point_assoc:
                    g, a = pairs[p, j, 0], pairs[p, j, 1]
                    for d in range(2):
                        src_pt[n_pt, d] = ground_points[g, d]
                        dst_pt[n_pt, d] = aerial_points[p, a, d]
                    n_pt += 1
                else:
                    g, a = pairs[p, j, 0] - n_ground_points, pairs[p, j, 1] - n_aerial_points
                    for d in range(2):
                        for e in range(2):
                            src_ln[n_ln, e, d] = ground_lines[g, e, d]
                            dst_ln[n_ln, e, d] = aerial_lines[p, a, e, d]
                        src_mid[n_ln, d] = 0.5 * (src_ln[n_ln, 0, d] + src_ln[n_ln, 1, d])
                        dst_mid[n_ln, d] = 0.5 * (dst_ln[n_ln, 0, d] + dst_ln[n_ln, 1, d])
                    sx, sy, src_ok = _unit_direction(src_ln[n_ln], eps)
                    dx, dy, dst_ok = _unit_direction(dst_ln[n_ln], eps)
                    # A zero-length line has no direction; it cannot constrain anything.
                    line_w[n_ln] = 1.0 if src_ok and dst_ok else 0.0
                    src_dir[n_ln, 0], src_dir[n_ln, 1] = sx, sy
                    dst_normal[n_ln, 0], dst_normal[n_ln, 1] = -dy, dx
                    n_ln += 1

            # Centre both sides on their weighted reference points (points and line midpoints).
            W = float(n_pt)
            V = 0.0
            cs0 = cs1 = cd0 = cd1 = 0.0
            for i in range(n_pt):
                cs0 += src_pt[i, 0]
                cs1 += src_pt[i, 1]
                cd0 += dst_pt[i, 0]
                cd1 += dst_pt[i, 1]
            for i in range(n_ln):
                v = line_w[i]
                V += v
                cs0 += v * src_mid[i, 0]
                cs1 += v * src_mid[i, 1]
                cd0 += v * dst_mid[i, 0]
                cd1 += v * dst_mid[i, 1]
            total = max(W + V, tiny)
            cs0, cs1, cd0, cd1 = cs0 / total, cs1 / total, cd0 / total, cd1 / total

            # Normal equations H x = g in x = (cos θ, sin θ, tx, ty), as `register_se2`.
            H[:] = 0.0
            gv[:] = 0.0
            p_sq = ps0 = ps1 = 0.0
            for i in range(n_pt):
                px, py = src_pt[i, 0] - cs0, src_pt[i, 1] - cs1
                qx, qy = dst_pt[i, 0] - cd0, dst_pt[i, 1] - cd1
                p_sq += px * px + py * py
                ps0 += px
                ps1 += py
                gv[0] += px * qx + py * qy
                gv[1] += px * qy - py * qx
                gv[2] += qx
                gv[3] += qy
            H[0, 0] = H[1, 1] = p_sq
            H[0, 2] = H[2, 0] = ps0
            H[0, 3] = H[3, 0] = ps1
            H[1, 2] = H[2, 1] = -ps1
            H[1, 3] = H[3, 1] = ps0
            H[2, 2] = H[3, 3] = W
            for i in range(n_ln):
                v = line_w[i]
                if v == 0.0:
                    continue
                nx, ny = dst_normal[i, 0], dst_normal[i, 1]
                ax, ay = src_mid[i, 0] - cs0, src_mid[i, 1] - cs1
                bx, by = dst_mid[i, 0] - cd0, dst_mid[i, 1] - cd1
                r0, r1, r2, r3 = nx * ax + ny * ay, ax * ny - ay * nx, nx, ny
                target = nx * bx + ny * by
                d0 = nx * src_dir[i, 0] + ny * src_dir[i, 1]
                d1 = src_dir[i, 0] * ny - src_dir[i, 1] * nx
                lam = line_direction_weight * v
                H[0, 0] += v * r0 * r0 + lam * d0 * d0
                H[0, 1] += v * r0 * r1 + lam * d0 * d1
                H[1, 1] += v * r1 * r1 + lam * d1 * d1
                H[0, 2] += v * r0 * r2
                H[0, 3] += v * r0 * r3
                H[1, 2] += v * r1 * r2
                H[1, 3] += v * r1 * r3
                H[2, 2] += v * r2 * r2
                H[2, 3] += v * r2 * r3
                H[3, 3] += v * r3 * r3
                gv[0] += v * r0 * target
                gv[1] += v * r1 * target
                gv[2] += v * r2 * target
                gv[3] += v * r3 * target
            H[1, 0], H[2, 0], H[3, 0], H[2, 1], H[3, 1], H[3, 2] = H[0, 1], H[0, 2], H[0, 3], H[1, 2], H[1, 3], H[2, 3]

            # Eliminate t: for fixed u the optimum is t = Htt^-1 (g_t - Htr u).
            i00, i01, i10, i11 = _inverse_2x2(H[2, 2], H[2, 3], H[3, 2], H[3, 3], eps, tiny)
            # K = H_rt Htt^-1 (2 x 2); M = H_rr - K H_rt^T; g_red = g_r - K g_t.
            k00 = H[0, 2] * i00 + H[0, 3] * i10
            k01 = H[0, 2] * i01 + H[0, 3] * i11
            k10 = H[1, 2] * i00 + H[1, 3] * i10
            k11 = H[1, 2] * i01 + H[1, 3] * i11
            m00 = H[0, 0] - (k00 * H[0, 2] + k01 * H[0, 3])
            m01 = H[0, 1] - (k00 * H[1, 2] + k01 * H[1, 3])
            m10 = H[1, 0] - (k10 * H[0, 2] + k11 * H[0, 3])
            m11 = H[1, 1] - (k10 * H[1, 2] + k11 * H[1, 3])
            gr0 = gv[0] - (k00 * gv[2] + k01 * gv[3])
            gr1 = gv[1] - (k10 * gv[2] + k11 * gv[3])

            theta, gap = _minimise_angle(
                0.5 * (m00 - m11), 0.5 * (m01 + m10), -2.0 * gr0, -2.0 * gr1, grid, grid_terms, f_grid, step,
                newton_iterations, tiny,
            )
            c, sn = math.cos(theta), math.sin(theta)
            # t_centred = Htt^-1 (g_t - H_rt^T u)
            e0 = gv[2] - (H[0, 2] * c + H[1, 2] * sn)
            e1 = gv[3] - (H[0, 3] * c + H[1, 3] * sn)
            tc0 = i00 * e0 + i01 * e1
            tc1 = i10 * e0 + i11 * e1
            t0 = tc0 + cd0 - (c * cs0 - sn * cs1)
            t1 = tc1 + cd1 - (sn * cs0 + c * cs1)

            # Information: rotation marginal over t (quadratic form of M in u'), translation's least eigenvalue.
            rotation_info = sn * sn * m00 - sn * c * (m01 + m10) + c * c * m11
            half_trace = 0.5 * (H[2, 2] + H[3, 3])
            half_diff = 0.5 * (H[2, 2] - H[3, 3])
            off = 0.5 * (H[2, 3] + H[3, 2])
            translation_info = half_trace - math.sqrt(half_diff * half_diff + off * off)
            condition = min(rotation_info, translation_info)

            # Weighted RMS residuals in centred coordinates.
            point_sq = 0.0
            for i in range(n_pt):
                px, py = src_pt[i, 0] - cs0, src_pt[i, 1] - cs1
                rx = c * px - sn * py + tc0 - (dst_pt[i, 0] - cd0)
                ry = sn * px + c * py + tc1 - (dst_pt[i, 1] - cd1)
                point_sq += rx * rx + ry * ry
            line_sq = 0.0
            for i in range(n_ln):
                v = line_w[i]
                if v == 0.0:
                    continue
                bx, by = dst_mid[i, 0] - cd0, dst_mid[i, 1] - cd1
                mean = 0.0
                for e in range(2):
                    ex, ey = src_ln[i, e, 0] - cs0, src_ln[i, e, 1] - cs1
                    off_line = (c * ex - sn * ey + tc0 - bx) * dst_normal[i, 0] + (sn * ex + c * ey + tc1 - by) * dst_normal[i, 1]
                    mean += off_line * off_line
                line_sq += v * 0.5 * mean

            theta_out[p, s] = theta
            t_out[p, s, 0], t_out[p, s, 1] = t0, t1
            condition_out[p, s] = condition
            gap_out[p, s] = gap
            point_res_out[p, s] = math.sqrt(point_sq / max(W, tiny)) if W > 0 else 0.0
            line_res_out[p, s] = math.sqrt(line_sq / max(V, tiny)) if V > 0 else 0.0
            finite = math.isfinite(theta) and math.isfinite(t0) and math.isfinite(t1)
            valid_out[p, s] = finite and condition > information_eps and gap > ambiguity_eps
    return theta_out, t_out, valid_out, condition_out, gap_out, point_res_out, line_res_out


@njit(cache=True, nogil=True, inline="always")
def _unit_direction(line: np.ndarray, eps: float) -> tuple[float, float, bool]:
    """Unit direction of a (2, 2) endpoint pair and whether it is defined (`registration._unit_direction`)."""
    dx, dy = line[1, 0] - line[0, 0], line[1, 1] - line[0, 1]
    length = math.sqrt(dx * dx + dy * dy)
    ok = length > eps * (1.0 + math.sqrt(line[0, 0] * line[0, 0] + line[0, 1] * line[0, 1]))
    if not ok:
        length = 1.0
    return dx / length, dy / length, ok


@njit(cache=True, nogil=True, inline="always")
def _inverse_2x2(a00: float, a01: float, a10: float, a11: float, eps: float, tiny: float) -> tuple[float, float, float, float]:
    """`registration._inverse_2x2`: the adjugate over a determinant clamped away from 0."""
    det = a00 * a11 - a01 * a10
    scale = max(max(abs(a00), abs(a01)), max(abs(a10), abs(a11))) ** 2
    floor = eps * scale + tiny
    if not abs(det) > floor:
        det = floor
    return a11 / det, -a01 / det, -a10 / det, a00 / det


@njit(cache=True, nogil=True, inline="always")
def _wrap(theta: float) -> float:
    return (theta + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, nogil=True, inline="always")
def _cost(a_c: float, a_s: float, b_c: float, b_s: float, c1: float, s1: float, c2: float, s2: float, order: int) -> float:
    """Order-th derivative of f(θ) - a0 at cos θ, sin θ, cos 2θ, sin 2θ (`registration._angle_cost`)."""
    if order == 0:
        return a_c * c2 + a_s * s2 + b_c * c1 + b_s * s1
    if order == 1:
        return 2.0 * (a_s * c2 - a_c * s2) + b_s * c1 - b_c * s1
    return -4.0 * (a_c * c2 + a_s * s2) - b_c * c1 - b_s * s1


@njit(cache=True, nogil=True, inline="always")
def _refine(
    a_c: float, a_s: float, b_c: float, b_s: float, start: float, step: float, newton_iterations: int, tiny: float
) -> tuple[float, float]:
    """Newton steps from the grid point `start`, clamped to its bracket of one step either side:
    the angle and f(θ) - a0 there. The angle terms are taken once per step for both derivatives."""
    lo, hi = start - step, start + step
    theta = start
    for _ in range(newton_iterations):
        c1, s1, c2, s2 = math.cos(theta), math.sin(theta), math.cos(2.0 * theta), math.sin(2.0 * theta)
        d1 = _cost(a_c, a_s, b_c, b_s, c1, s1, c2, s2, 1)
        d2 = _cost(a_c, a_s, b_c, b_s, c1, s1, c2, s2, 2)
        # Where f is not convex a Newton step would head for a maximum: walk downhill instead.
        if d2 > 0:
            theta = theta - d1 / max(d2, tiny)
        else:
            theta = theta - (1.0 if d1 > 0 else (-1.0 if d1 < 0 else 0.0)) * step
        theta = min(max(theta, lo), hi)
    f = _cost(a_c, a_s, b_c, b_s, math.cos(theta), math.sin(theta), math.cos(2.0 * theta), math.sin(2.0 * theta), 0)
    return theta, f


@njit(cache=True, nogil=True)
def _minimise_angle(
    a_c: float, a_s: float, b_c: float, b_s: float, grid: np.ndarray, grid_terms: np.ndarray, f_grid: np.ndarray,
    step: float, newton_iterations: int, tiny: float,
) -> tuple[float, float]:
    """`registration._minimise_angle` for one set: the global minimiser of f and the cost gap to
    its other local minimum (inf without one)."""
    n = grid.shape[0]
    for j in range(n):
        f_grid[j] = _cost(a_c, a_s, b_c, b_s, grid_terms[j, 0], grid_terms[j, 1], grid_terms[j, 2], grid_terms[j, 3], 0)
    # The two lowest grid points that are local minima (strict on one side, as torch's rolls).
    first = second = -1
    for j in range(n):
        f = f_grid[j]
        if not (f < f_grid[j - 1] and f <= f_grid[(j + 1) % n]):
            continue
        if first < 0 or f < f_grid[first]:
            second, first = first, j
        elif second < 0 or f < f_grid[second]:
            second = j
    has_second = second >= 0
    theta0, f0 = _refine(a_c, a_s, b_c, b_s, grid[max(first, 0)], step, newton_iterations, tiny)
    theta1, f1 = _refine(a_c, a_s, b_c, b_s, grid[max(second, 0)], step, newton_iterations, tiny)
    best = theta0 if (f0 <= f1 or not has_second) else theta1
    # Two brackets that converge to one minimum are one candidate.
    distinct = has_second and abs(_wrap(theta0 - theta1)) > 2.0 * step
    gap = abs(f0 - f1) if distinct else math.inf
    return _wrap(best), gap

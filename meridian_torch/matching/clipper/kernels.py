"""Compiled (numba) kernels of CLIPPER, for CPU arrays.

- `sparse_homotopy`: the continuous solve of one sparse problem (`ascent._homotopy` around
  `ascent._ascend` with `ascent._SparseProblem`'s products) in one call. The torch loop spends
  tens of microseconds per tiny op (a mat-vec, a sum, a norm, a where) and takes thousands of
  them per solve; here each objective evaluation is one pass over the CSR rows of u's nonzero
  entries. The same steps, other summation order, so it agrees with the torch loop to rounding,
  not bitwise.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["sparse_homotopy"]

_TINY = float(np.finfo(np.float64).tiny)  # the clamp of `ascent._normalize`


@njit(cache=True, nogil=True, error_model="numpy")
def _penalised_mv(crow: np.ndarray, col: np.ndarray, value: np.ndarray, d: float, u: np.ndarray,
                  out: np.ndarray, pattern_u: np.ndarray) -> float:
    """out = Md u = M_off u + u - d Cb u with Cb u = sum(u) - u - P u (P the pattern of M_off);
    returns F = u'Md u. `pattern_u` is scratch (P u on return).

    M_off is symmetric, so row j holds column j: the products are scattered from the rows of the
    nonzero entries of u only (the ascent soon zeroes most of u). Row i then receives its terms in
    ascending column order, the order of a pass over row i, and a zero term adds nothing: the
    sums are bitwise those of the row-by-row product."""
    n = u.shape[0]
    total = 0.0
    for i in range(n):
        total += u[i]
        out[i] = 0.0
        pattern_u[i] = 0.0
    for j in range(n):
        uj = u[j]
        if uj != 0.0:
            for k in range(crow[j], crow[j + 1]):
                out[col[k]] += value[k] * uj
                pattern_u[col[k]] += uj
    F = 0.0
    for i in range(n):
        out[i] = out[i] + u[i] - d * (total - u[i] - pattern_u[i])
        F += u[i] * out[i]
    return F


@njit(cache=True, nogil=True, error_model="numpy")
def _ascend(crow: np.ndarray, col: np.ndarray, value: np.ndarray, d: float, u: np.ndarray, g: np.ndarray,
            cand: np.ndarray, g_c: np.ndarray, pattern_u: np.ndarray, tol_u: float, noise: float, eps: float,
            tol_F: float, beta: float, max_inner: int, max_line_search: int) -> tuple[float, int]:
    """`ascent._ascend` for one problem: u and g (= Md u on return) are updated in place, cand, g_c
    and pattern_u are scratch. Returns (F, steps)."""
    n = u.shape[0]
    F = _penalised_mv(crow, col, value, d, u, g, pattern_u)
    steps = 0
    for _ in range(max_inner):
        slack = max(noise * (1.0 + abs(F)), eps)
        u_mass = 0.0
        for i in range(n):
            u_mass += abs(u[i])
        alpha = 1.0
        F_c = F
        for _ in range(max_line_search):
            norm = 0.0
            for i in range(n):
                cand[i] = max(u[i] + alpha * g[i], 0.0)
                norm += cand[i] * cand[i]
            norm = max(math.sqrt(norm), _TINY)
            mass = 0.0
            for i in range(n):
                cand[i] = cand[i] / norm
                mass += abs(cand[i])
            F_c = _penalised_mv(crow, col, value, d, cand, g_c, pattern_u)
            # A step clamping every entry to zero is no solution: shrink it (see `ascent._ascend`).
            collapsed = mass == 0.0 and u_mass > 0.0
            if not (F_c - F < -slack or collapsed):
                break
            alpha = alpha * beta
        # Every trial failing takes the last one, as the torch loop does.
        du = 0.0
        for i in range(n):
            du += (cand[i] - u[i]) ** 2
            u[i] = cand[i]
            g[i] = g_c[i]
        dF = abs(F_c - F)
        F = F_c
        steps += 1
        if not (math.sqrt(du) >= tol_u and dF >= max(slack, tol_F)):
            break
    return F, steps


@njit(cache=True, nogil=True, error_model="numpy")
def sparse_homotopy(crow: np.ndarray, col: np.ndarray, value: np.ndarray, u: np.ndarray, d: float, tol_u: float,
                    noise: float, eps: float, tol_F: float, beta: float, max_inner: int, max_line_search: int,
                    max_outer: int) -> tuple[float, int, int, bool]:
    """`ascent._homotopy` for one sparse problem (M_off in CSR, unit diagonal) from the start u
    (normalised, updated in place) and penalty d. Returns (objective, iterations, penalty
    updates, converged)."""
    n = u.shape[0]
    g, cand, g_c, pattern_u = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    objective, iterations, updates = 0.0, 0, 0
    for _ in range(max_outer):
        F, steps = _ascend(crow, col, value, d, u, g, cand, g_c, pattern_u, tol_u, noise, eps, tol_F, beta,
                           max_inner, max_line_search)
        objective = F
        iterations += steps
        # `ascent._penalty_ratio` at u: mean |(A u)_i / (Cb u)_i| where both are positive
        # (pattern_u holds P u: `_ascend`'s last product was at its final u)
        total = 0.0
        for i in range(n):
            total += u[i]
        ratio, count = 0.0, 0
        for i in range(n):
            cbu = total - u[i] - pattern_u[i]
            if cbu > eps and u[i] > eps:
                ratio += abs((g[i] + d * cbu) / cbu)
                count += 1
        if count == 0:  # a feasible support
            return objective, iterations, updates, True
        updates += 1
        d = d + ratio / count
    return objective, iterations, updates, False

"""Compiled (numba) Langevin loop of the particle sampler for CPU tensors: every step of one patch
(sparse drift, noise, RMSprop, projection, renormalisation, early-stop check) in a few passes
over its (m, N) particles, which stay in the core's cache for all its steps. The torch loop in
`matching.particles` makes ~12 passes over the whole (P, m, N) batch per step, which is memory
traffic, not arithmetic (a match spent 40 % of its time there).

Same dynamics, same noise: only the rounding differs (operation order and fused multiply-adds
of torch's kernels), so runs agree with the torch loop statistically, not bitwise. A patch's
result depends only on its own data and seed, never on the batch or its padding."""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["langevin_patches"]


@njit(cache=True, nogil=True, error_model="numpy")
def langevin_patches(
    patches: np.ndarray,
    crow: np.ndarray,
    col: np.ndarray,
    value: np.ndarray,
    d: np.ndarray,
    validf: np.ndarray,
    x: np.ndarray,
    iterations: np.ndarray,
    table: np.ndarray,
    offsets: np.ndarray,
    signed_sigma: np.ndarray,
    constants: np.ndarray,
    noise: bool,
    rmsprop: bool,
    early_stop: bool,
    check_interval: int,
    obj_tol: float,
    patience: int,
) -> None:
    """Run the dynamics of the patches `patches` in place on x (P, m, N).

    A: the penalised affinity as one CSR over rows p * m + i (crow (P m + 1,), col local j,
    value); d (P,), validf (P, m); iterations (P,) receives the steps run; noise of step t for
    patch p is table[offsets[t, p] + i N + n] * signed_sigma[t, p, n]; constants = (eta, alpha,
    1 - alpha, 1e-6, 0) in x's dtype, so that all arithmetic stays in it."""
    n_steps = offsets.shape[0]
    _, m, n = x.shape
    g = np.empty((m, n), x.dtype)
    h = np.empty((m, n), x.dtype)
    column = np.empty(n, x.dtype)  # 1' x per particle
    norm2 = np.empty(n, x.dtype)
    tiny, zero = constants[3], constants[4]
    # Loops over one row's particles (1-D, contiguous): they vectorise; numba's array
    # expressions would allocate a temporary each.
    for p in patches:
        xp = x[p]
        dp = d[p]
        ema = 0.0
        settled = 0
        iterations[p] = n_steps
        column[:] = zero
        for i in range(m):
            _add(column, xp[i])
        for t in range(n_steps):
            # g = A x - d valid (1' x): the penalty of the conflicting pairs without building it.
            for i in range(m):
                gi = g[i]
                gi[:] = zero
                k, stop = crow[p * m + i], crow[p * m + i + 1]
                # Four entries per pass over the row: g is loaded and stored once for four
                # products (the same additions in the same order as one at a time).
                while k + 4 <= stop:
                    _axpy4(gi, value[k], xp[col[k]], value[k + 1], xp[col[k + 1]], value[k + 2], xp[col[k + 2]],
                           value[k + 3], xp[col[k + 3]])
                    k += 4
                while k < stop:
                    _axpy(gi, value[k], xp[col[k]])
                    k += 1
                _axpy(gi, -(validf[p, i] * dp), column)
            if early_stop and t > 0 and t % check_interval == 0:
                objective = 0.0
                for i in range(m):
                    objective += _dot(g[i], xp[i])
                objective /= n
                if t == check_interval:
                    ema = objective
                else:
                    new = 0.5 * ema + 0.5 * objective
                    settled = settled + 1 if abs(new - ema) / (abs(ema) + 1e-12) < obj_tol else 0
                    ema = new
                if settled >= patience:
                    iterations[p] = t
                    break
            norm2[:] = zero
            base = offsets[t, p]
            for i in range(m):
                _row_step(xp[i], g[i], h[i], table[base + i * n : base + (i + 1) * n], signed_sigma[t, p],
                          noise, rmsprop, t == 0, constants, validf[p, i], norm2)
            for c in range(n):
                norm2[c] = max(np.sqrt(norm2[c]), tiny)
            column[:] = zero
            for i in range(m):
                _normalise(xp[i], norm2, column)

@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _add(y: np.ndarray, x: np.ndarray) -> None:
    for c in range(y.shape[0]):
        y[c] += x[c]


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _axpy(y: np.ndarray, a: float, x: np.ndarray) -> None:
    for c in range(y.shape[0]):
        y[c] += a * x[c]


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _axpy4(
    y: np.ndarray, a0: float, x0: np.ndarray, a1: float, x1: np.ndarray, a2: float, x2: np.ndarray, a3: float,
    x3: np.ndarray,
) -> None:
    for c in range(y.shape[0]):
        y[c] = (((y[c] + a0 * x0[c]) + a1 * x1[c]) + a2 * x2[c]) + a3 * x3[c]


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _dot(y: np.ndarray, x: np.ndarray) -> float:
    s = 0.0
    for c in range(y.shape[0]):
        s += y[c] * x[c]
    return s


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _row_step(
    x: np.ndarray, g: np.ndarray, h: np.ndarray, noise_row: np.ndarray, scale: np.ndarray, noise: bool,
    rmsprop: bool, first: bool, constants: np.ndarray, keep: float, norm2: np.ndarray,
) -> None:
    """One coordinate's step for every particle: v = g + noise; RMSprop; x = max(x + step, 0) *
    keep; norm2 += x^2. One pass, so the row is read and written once."""
    eta, alpha, one_minus_alpha, tiny, zero = constants[0], constants[1], constants[2], constants[3], constants[4]
    for c in range(x.shape[0]):
        v = g[c] + noise_row[c] * scale[c] if noise else g[c]
        if rmsprop:
            hc = v * v if first else h[c] * alpha + one_minus_alpha * v * v
            h[c] = hc
            xc = x[c] + eta * (v / (np.sqrt(hc) + tiny))
        else:
            xc = x[c] + eta * v
        xc = max(xc, zero) * keep
        x[c] = xc
        norm2[c] += xc * xc


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _normalise(x: np.ndarray, norm: np.ndarray, column: np.ndarray) -> None:
    """x /= norm; column += x (the next step's 1' x, in the same pass)."""
    for c in range(x.shape[0]):
        v = x[c] / norm[c]
        x[c] = v
        column[c] += v

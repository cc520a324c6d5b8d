"""Compiled (numba) evaluation of the gated affinity entries and of the line-pair tables, for
tensors on the CPU (the tables: `_compiled_line_pair_table`, below).

The torch path (`blocks`) builds (P, rows, cols) keys, gathers the gate tables, finds the
survivors with nonzero and scores them in ~20 small ops on flat index lists: ~90 % of the
affinity's CPU time on KITTI 09 submaps. Here one pass visits the association pairs of the same
spans in the same order, applies the same gate (row by row, vectorised on table rows gathered
per primitive) and then scores the pairs of a row that passed, appending (patch, i, j, M) to
growing buffers: no per-pair intermediates.

The arithmetic follows the torch code operation by operation in the tables' dtype (every Python
constant rounded to that dtype first, as torch does with scalars; numba fuses no multiply-adds),
so keys, gates, comparisons and +, -, *, /, abs, sqrt agree bit for bit. exp, pow and hypot come
from libm, torch's from SLEEF: in float32 exp and pow differ by one ulp on ~1 % of arguments,
hypot on 11 of 2e8 random pairs. Values then differ by at most a few ulps (KITTI 09: 9 % of the
entries, by <= 2 ulps, 1.2e-7 relative), and an entry could only appear or vanish if a product
(or a point distance) lay within an ulp of its threshold; on KITTI 09 the entries and their
order are identical. Float64 inputs run the same code in float64.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
from numba import njit, uint64

from meridian_torch.config.matching import AffinityConfig
from meridian_torch.geometry.se2 import line_angle_between
from meridian_torch.matching.affinity.lines import NEARBY_EPS_M, PARALLEL_EPS_RAD, _Lines
from meridian_torch.matching.affinity.scores import _GATE_SLACK
from meridian_torch.matching.kernels import grown

if TYPE_CHECKING:  # gather builds its tables with this module
    from meridian_torch.matching.affinity.gather import _Gathered

_KINDS = ("pp", "pl", "ll")  # span kinds; their index is the kernel's kind code
_PP, _PL, _LL = range(3)
_MIN_CAPACITY = 1 << 12  # first size of the output buffers, which double when full


class _Constants(NamedTuple):
    """Every scalar of the gate and the scores, rounded to the tables' dtype (numba would promote
    float32 arithmetic with a Python float to float64; torch rounds the scalar instead)."""

    zero: float
    half: float
    minus_half: float
    sqrt2: float
    third: float
    gate_t: float  # point-point and point-line gate: eps_t + slack
    gate_theta: float  # line-line gate: eps_theta + slack
    sigma_t: float
    eps_t: float
    sigma_split: float  # point-line along / across kernels: sigma_t / sqrt(2), eps_t / sqrt(2)
    eps_split: float
    min_separation: float
    sin_uncertainty: float
    sigma_theta: float
    eps_theta: float
    min_line_angle: float
    point_line_lever: float  # tan(sigma_theta) / 2
    line_lever: float  # tan(sigma_theta) / 4
    eps_cubed: float


def _constants(cfg: AffinityConfig, dtype: np.dtype) -> _Constants:
    """The scalars of cfg, each computed in Python floats like the torch code, then rounded."""
    tan_theta = math.tan(math.radians(cfg.sigma_theta_deg))
    values = _Constants(
        zero=0.0,
        half=0.5,
        minus_half=-0.5,
        sqrt2=math.sqrt(2.0),
        third=1.0 / 3.0,
        gate_t=cfg.epsilon_t_m + _GATE_SLACK,
        gate_theta=math.radians(cfg.epsilon_theta_deg) + _GATE_SLACK,
        sigma_t=cfg.sigma_t_m,
        eps_t=cfg.epsilon_t_m,
        sigma_split=cfg.sigma_t_m / math.sqrt(2.0),
        eps_split=cfg.epsilon_t_m / math.sqrt(2.0),
        min_separation=cfg.min_point_separation_m,
        sin_uncertainty=math.sin(math.radians(cfg.rotation_uncertainty_deg)),
        sigma_theta=math.radians(cfg.sigma_theta_deg),
        eps_theta=math.radians(cfg.epsilon_theta_deg),
        min_line_angle=math.radians(cfg.min_line_angle_deg),
        point_line_lever=tan_theta * 0.5,
        line_lever=tan_theta * 0.25,
        eps_cubed=cfg.affinity_eps**3,
    )
    return _Constants(*(dtype.type(v) for v in values))


class _Arrays(NamedTuple):
    """The `_Gathered` fields the kernel reads, as C-contiguous arrays; cos, sin (P,) per patch
    with a rotation prior, else empty."""

    q: np.ndarray
    cos: np.ndarray
    sin: np.ndarray
    a_px: np.ndarray
    a_py: np.ndarray
    g_px: np.ndarray
    g_py: np.ndarray
    a_pt: np.ndarray
    g_pt: np.ndarray
    a_ln: np.ndarray
    g_ln: np.ndarray
    a_pl: np.ndarray
    g_pl: np.ndarray
    a_ll: np.ndarray
    g_ll: np.ndarray
    a_pp_gate: np.ndarray
    g_pp_gate: np.ndarray
    a_pl_gate: np.ndarray
    g_pl_gate: np.ndarray
    a_ll_gate: np.ndarray
    g_ll_gate: np.ndarray
    n_aerial_points: int
    n_aerial_lines: int
    n_ground_points: int
    n_ground_lines: int
    n_point_assoc: int


def _compiled_entries(
    gat: _Gathered, spans: list[tuple[int, int, int, int, str]], cfg: AffinityConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """`blocks._entries` on CPU tensors: indices (n, 3) int64 (patch, i, j) and values (n,) of the
    spans (r0, r1, c0, c1, kind), in the torch path's order."""
    def array(x: torch.Tensor) -> np.ndarray:
        return x.contiguous().numpy()

    cos, sin = gat.cos_sin if gat.cos_sin is not None else (gat.q.new_zeros(0),) * 2
    shared = {name: getattr(gat, name) for name in _Arrays._fields if name not in ("cos", "sin")}
    arrays = _Arrays(cos=array(cos), sin=array(sin),
                     **{name: array(x) if isinstance(x, torch.Tensor) else x for name, x in shared.items()})
    span_array = np.array([(r0, r1, c0, c1, _KINDS.index(kind)) for r0, r1, c0, c1, kind in spans], np.int64)
    index, value = _span_entries(
        span_array.reshape(-1, 5), arrays, _constants(cfg, arrays.q.dtype), gat.cos_sin is not None,
        cfg.parallel_line_pairs == "separation", cfg.lever_arm_inflation,
    )
    return torch.from_numpy(index), torch.from_numpy(value)


@njit(cache=True, nogil=True, inline="always")
def _minimum(a, b):
    """torch.minimum of two scalars: NaN if either is NaN."""
    return a if a < b or a != a else b


@njit(cache=True, nogil=True, inline="always")
def _kernel(c, sigma, eps, k):
    """`scores.kernel` of one value: exp(-(c / sigma)^2 / 2) if c <= eps else 0 (NaN stays NaN)."""
    if c > eps:
        return k.zero
    ratio = c / sigma
    return math.exp(k.minus_half * (ratio * ratio))


@njit(cache=True, nogil=True, inline="always")
def _axis_kernel(a, g, delta, k):
    """The per-axis factor of `scores._point_pair_score` with a rotation prior."""
    widen = k.half * (abs(a) + abs(g)) * k.sin_uncertainty
    return _kernel(abs(a - g), (k.sigma_t + delta + widen) / k.sqrt2, (k.eps_t + delta + widen) / k.sqrt2, k)


# The scores below take scalars only (array arguments would be reference counted per call) and
# return 0 as soon as one factor of s (or one term of a minimum) is 0: torch's s is then 0 or
# NaN, and both fail `> affinity_eps^3`. Most gated pairs end there, before any exp.


@njit(cache=True, nogil=True, inline="always")
def _point_pair_score(ax, ay, gx, gy, delta, k, rotated, min_separation):
    """`scores._point_pair_score` of one pair of offsets (delta = 0 for a Python 0.0)."""
    len_a, len_g = math.hypot(ax, ay), math.hypot(gx, gy)
    c = abs(len_a - len_g)
    if c > k.eps_t or (min_separation and (len_a < k.min_separation or len_g < k.min_separation)):
        return k.zero
    score = _kernel(c, k.sigma_t + delta, k.eps_t, k)
    if rotated:
        axis_x = _axis_kernel(ax, gx, delta, k)
        if axis_x == 0:
            return k.zero
        score = _minimum(score, axis_x * _axis_kernel(ay, gy, delta, k))
    return score


@njit(cache=True, nogil=True, inline="always")
def _point_line_score(fields, k, rotated, lever_arm):
    """`scores._point_line_score` of the fields of one aerial and one ground point-line table
    entry (along, across, lever, vx, vy) each."""
    a_along, a_across, a_lever, a_vx, a_vy, g_along, g_across, g_lever, g_vx, g_vy = fields
    c_along = abs(abs(a_along) - abs(g_along))
    if c_along > k.eps_split:
        return k.zero
    delta = k.point_line_lever * (a_lever + g_lever) if lever_arm else k.zero
    c_across, eps_across = abs(abs(a_across) - abs(g_across)), k.eps_split + delta
    if c_across > eps_across:
        return k.zero
    if rotated:
        pair = _point_pair_score(a_vx, a_vy, g_vx, g_vy, delta, k, True, False)
    else:
        pair = _point_pair_score(a_along, a_across, g_along, g_across, delta, k, False, False)
    if pair == 0:
        return k.zero
    split = _kernel(c_along, k.sigma_split, k.eps_split, k) * _kernel(c_across, k.sigma_split + delta, eps_across, k)
    return _minimum(split, pair)


@njit(cache=True, nogil=True, inline="always")
def _line_line_score(fields, k, rotated, separation, lever_arm):
    """`scores._line_line_score` of the fields of one aerial and one ground line-pair table entry
    (angle, gap, lever, vx, vy) each."""
    a_theta, a_gap, a_lever, a_vx, a_vy, g_theta, g_gap, g_lever, g_vx, g_vy = fields
    c_theta = abs(a_theta - g_theta)
    par_a, par_g = a_theta < k.min_line_angle, g_theta < k.min_line_angle
    if c_theta > k.eps_theta or ((par_a != par_g) if separation else (par_a or par_g)):
        return k.zero
    if separation and par_a and (a_gap < k.min_separation or g_gap < k.min_separation):
        return k.zero
    delta = k.zero
    if lever_arm:
        # In 'separation' mode the lever of a parallel pair is already a distance.
        delta = k.half * (a_lever + g_lever) if separation and par_a else k.line_lever * (a_lever + g_lever)
    if rotated:
        s_t = _point_pair_score(a_vx, a_vy, g_vx, g_vy, delta, k, True, False)
    else:
        # `_point_pair_score` of the vectors (gap, 0): their lengths hypot(gap, 0) are |gap| bit
        # for bit (glibc returns |x| + 0 for y = 0; checked for every float32), without the calls.
        s_t = _kernel(abs(abs(a_gap) - abs(g_gap)), k.sigma_t + delta, k.eps_t, k)
    if s_t == 0:
        return k.zero
    return math.sqrt(_kernel(c_theta, k.sigma_theta, k.eps_theta, k) * s_t)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _gathered(out, table, base, cols, col_offset, lo, hi):
    """out[j] = table[base + cols[j - col_offset]] for j in [lo, hi): one row primitive's table
    row, laid out by column (association) so that the gate reads it contiguously."""
    # Indices are unsigned (all are >= 0) so that numba skips its wraparound of negative ones.
    for j in range(lo, hi):
        out[j] = table[uint64(base + cols[uint64(j - col_offset)])]


@njit(cache=True, nogil=True, error_model="numpy")
def _passing(mask, q, a_gate, g_gate, a_gap, g_gap, tol, gap_tol, with_gap):
    """mask[t] = whether column t of the rows (n,) passes the gate: q != 0 and the aerial and
    ground gate values within tol (and, with_gap, the gap lengths within gap_tol). Branch free
    over contiguous rows indexed from 0 (no wraparound of negative indices): it vectorises."""
    if with_gap:
        for t in range(q.shape[0]):
            mask[t] = (q[t] != 0) & (abs(a_gate[t] - g_gate[t]) <= tol) & (abs(a_gap[t] - g_gap[t]) <= gap_tol)
    else:
        for t in range(q.shape[0]):
            mask[t] = (q[t] != 0) & (abs(a_gate[t] - g_gate[t]) <= tol)


@njit(cache=True, nogil=True, error_model="numpy")
def _passed_columns(columns, mask, words, lo, n):
    """The columns lo + t of mask[t] != 0, t < n, in ascending order into `columns`; their
    count. words views mask as uint64: few pairs pass (3-7 %), so most words are skipped whole."""
    mask[n : (n + 7) & ~7] = 0
    n_passed = 0
    for w in range((n + 7) >> 3):
        if words[w] != 0:
            for t in range(8 * w, 8 * w + 8):
                columns[n_passed] = lo + t
                n_passed += mask[t]
    return n_passed


@njit(cache=True, nogil=True)
def _span_entries(spans, arr, k, rotated, separation, lever_arm):
    """Entries M = cbrt(s q_i q_j) > affinity_eps of the spans (S, 5) (r0, r1, c0, c1, kind code),
    each visited patch by patch, row by row (the torch path's nonzero order), j > i only:
    (n, 3) int64 (patch, i, j) and (n,) values."""
    # Arrays are unpacked outside the loops: taken from the tuple inside they are reference counted.
    q, cos, sin, a_pt, g_pt, a_ln, g_ln = arr.q, arr.cos, arr.sin, arr.a_pt, arr.g_pt, arr.a_ln, arr.g_ln
    a_px, a_py, g_px, g_py = arr.a_px, arr.a_py, arr.g_px, arr.g_py
    n_ap, n_al, n_gp, n_gl = arr.n_aerial_points, arr.n_aerial_lines, arr.n_ground_points, arr.n_ground_lines
    mp = arr.n_point_assoc
    index = np.empty(3 * _MIN_CAPACITY, np.int64)
    value = np.empty(_MIN_CAPACITY, q.dtype)
    n = 0
    m = q.shape[1]
    # The gate of (i, j) compares a_gate[key_a(row prim of i, col prim of j)] with the ground's:
    # gathered per pair that is 4 scattered reads. Instead each row primitive's table row is
    # gathered once per span and patch into column order (its gate value and, for lines, gap
    # length for every column j), which all rows of that primitive then read contiguously.
    a_rows_of = np.empty((2, max(n_ap, n_al), m), q.dtype)
    g_rows_of = np.empty((2, max(n_gp, n_gl), m), q.dtype)
    a_stamp = np.full(max(n_ap, n_al), -1, np.int64)  # the (span, patch) a row was gathered for
    g_stamp = np.full(max(n_gp, n_gl), -1, np.int64)
    mask = np.empty(8 * ((m + 15) // 8), np.uint8)  # one row's gate results, padded to words
    words = mask.view(np.uint64)
    columns = np.empty(m + 8, np.int64)  # the columns of one row that pass the gate (+ a word's slack)
    a_vx = a_vy = g_vx = g_vy = k.zero  # vector fields, read only with a rotation prior
    stamp = 0
    for s in range(spans.shape[0]):
        r0, r1, c0, c1, kind = spans[s]
        # As in `blocks._gate`, each side's key of (i, j) is row(i) * n_cols + col(j): (patch,
        # primitive of i, primitive of j) in that side's table of the kind.
        if kind == _PP:
            a_rows, g_rows, row_offset, n_a_rows = a_pt, g_pt, 0, n_ap
            a_cols, g_cols, col_offset, n_a_cols, n_g_cols = a_pt, g_pt, 0, n_ap, n_gp
            a_gate, g_gate, a_tab, g_tab, tol = arr.a_pp_gate, arr.g_pp_gate, arr.a_pl, arr.g_pl, k.gate_t
        elif kind == _PL:
            a_rows, g_rows, row_offset, n_a_rows = a_pt, g_pt, 0, n_ap
            a_cols, g_cols, col_offset, n_a_cols, n_g_cols = a_ln, g_ln, mp, n_al, n_gl
            a_gate, g_gate, a_tab, g_tab, tol = arr.a_pl_gate, arr.g_pl_gate, arr.a_pl, arr.g_pl, k.gate_t
        else:
            a_rows, g_rows, row_offset, n_a_rows = a_ln, g_ln, mp, n_al
            a_cols, g_cols, col_offset, n_a_cols, n_g_cols = a_ln, g_ln, mp, n_al, n_gl
            a_gate, g_gate, a_tab, g_tab, tol = arr.a_ll_gate, arr.g_ll_gate, arr.a_ll, arr.g_ll, k.gate_theta
        # s_t's window on the gap lengths of line pairs too (exact without a prior; the slack
        # covers the prior's rotation of the ground vectors): drops ~90 % of the line pairs
        # that pass the angle gate, before they are scored.
        with_gap = kind == _LL
        a_gap, g_gap = a_tab[1], g_tab[1]
        for b in range(q.shape[0]):
            stamp += 1
            a_cols_b, g_cols_b, q_b = a_cols[b], g_cols[b], q[b]
            for i in range(r0, r1):
                q_i = q[b, i]
                lo = max(c0, i + 1)
                if q_i == 0 or lo >= c1:  # q_i = 0: the product is 0 (padding, or a cosine below the window)
                    continue
                a_prim, g_prim = a_rows[b, i - row_offset], g_rows[b, i - row_offset]
                a_row, g_row = (b * n_a_rows + a_prim) * n_a_cols, g_prim * n_g_cols
                # A row's lo only grows with i: the first gather of a primitive covers its later rows.
                if a_stamp[a_prim] != stamp:
                    a_stamp[a_prim] = stamp
                    _gathered(a_rows_of[0, a_prim], a_gate, a_row, a_cols_b, col_offset, lo, c1)
                    if with_gap:
                        _gathered(a_rows_of[1, a_prim], a_gap, a_row, a_cols_b, col_offset, lo, c1)
                if g_stamp[g_prim] != stamp:
                    g_stamp[g_prim] = stamp
                    _gathered(g_rows_of[0, g_prim], g_gate, g_row, g_cols_b, col_offset, lo, c1)
                    if with_gap:
                        _gathered(g_rows_of[1, g_prim], g_gap, g_row, g_cols_b, col_offset, lo, c1)
                _passing(mask, q_b[lo:c1], a_rows_of[0, a_prim, lo:c1], g_rows_of[0, g_prim, lo:c1],
                         a_rows_of[1, a_prim, lo:c1], g_rows_of[1, g_prim, lo:c1], tol, k.gate_t, with_gap)
                for c in range(_passed_columns(columns, mask, words, lo, c1 - lo)):
                    j = columns[c]
                    a_key, g_key = a_row + a_cols[b, j - col_offset], g_row + g_cols[b, j - col_offset]
                    if kind == _PP:
                        score = _point_pair_score(
                            a_px[b, i] - a_px[b, j], a_py[b, i] - a_py[b, j],
                            g_px[b, i] - g_px[b, j], g_py[b, i] - g_py[b, j], k.zero, k, rotated, True,
                        )
                    else:
                        if rotated:  # ground vectors turned by the patch's prior, as `blocks._take`
                            a_vx, a_vy = a_tab[3, a_key], a_tab[4, a_key]
                            g_vx = cos[b] * g_tab[3, g_key] - sin[b] * g_tab[4, g_key]
                            g_vy = sin[b] * g_tab[3, g_key] + cos[b] * g_tab[4, g_key]
                        fields = (a_tab[0, a_key], a_tab[1, a_key], a_tab[2, a_key], a_vx, a_vy,
                                  g_tab[0, g_key], g_tab[1, g_key], g_tab[2, g_key], g_vx, g_vy)
                        if kind == _PL:
                            score = _point_line_score(fields, k, rotated, lever_arm)
                        else:
                            score = _line_line_score(fields, k, rotated, separation, lever_arm)
                    product = score * q_i * q[b, j]
                    if not product > k.eps_cubed:
                        continue
                    if n == len(value):
                        index, value = grown(index, 6 * n), grown(value, 2 * n)
                    index[3 * n], index[3 * n + 1], index[3 * n + 2] = b, i, j
                    value[n] = product**k.third
                    n += 1
    return index[: 3 * n].reshape(n, 3), value[:n]


# ------------------------------------------------------------------------------------------
# Line-pair tables (`scores._line_pair_table`)
# ------------------------------------------------------------------------------------------


class _LineConstants(NamedTuple):
    """The scalars of `lines._closest_params` and `scores._line_pair_table` in the lines' dtype."""

    zero: float
    one: float
    half: float
    inf: float
    nearby: float  # NEARBY_EPS_M
    cos_parallel: float  # cos(PARALLEL_EPS_RAD)
    parallel_below: float  # the separation mode's angle (unused without it)


def _compiled_line_pair_table(lines: _Lines, with_vectors: bool, parallel_below: float | None) -> torch.Tensor:
    """`scores._line_pair_table(lines.map_axis(-1), lines.map_axis(-2), ...)` of the lines (..., U)
    on the CPU: (F, ..., U, U), the same numbers (up to the sign of zeros in the gap vector).

    The angle, its sine and the gap length stay torch ops on tensors of the torch path's shapes
    (SLEEF's atan2, sin and hypot, which libm's do not match bit for bit, and whose last
    elements of a tensor take the scalar code); one compiled pass does the rest pair by pair,
    which in torch is ~100 ops on (..., U, U) tensors (the closest points' candidates)."""
    angle = line_angle_between(lines.map_axis(-1).angle(), lines.map_axis(-2).angle())
    n_rows, n = math.prod(angle.shape[:-2]), angle.shape[-1]
    table = angle.new_empty(5, *angle.shape)  # rows 3, 4 (the gap vector) also feed the gap length
    table[0] = angle
    separation = parallel_below is not None
    sin_angle = torch.sin(angle) if separation else angle
    dtype = angle.numpy().dtype
    constants = _LineConstants(*(dtype.type(v) for v in (
        0.0, 1.0, 0.5, math.inf, NEARBY_EPS_M, math.cos(PARALLEL_EPS_RAD), parallel_below if separation else 0.0)))

    def rows(x: torch.Tensor) -> np.ndarray:
        return x.reshape(n_rows, n).contiguous().numpy()

    _line_pair_fields(
        rows(lines.ox), rows(lines.oy), rows(lines.dx), rows(lines.dy), rows(lines.lo), rows(lines.hi), rows(lines.tref),
        sin_angle.reshape(n_rows, n, n).numpy(), angle.reshape(n_rows, n, n).numpy(), constants, separation,
        table.view(5, n_rows, n, n).numpy(),
    )
    torch.hypot(table[3], table[4], out=table[1])
    return table if with_vectors else table[:3]


@njit(cache=True, nogil=True, inline="always")
def _clamped(t, lo, hi):
    """`lines._clamp` of one value: torch.minimum(torch.maximum(t, lo), hi), NaN propagating."""
    t = t if t > lo or t != t else lo
    return t if t < hi or t != t else hi


@njit(cache=True, nogil=True, inline="always")
def _closest_params(line_1, line_2, k):
    """`lines._closest_params` of one pair of lines (ox, oy, dx, dy, lo, hi, tref): s1, s2, meet."""
    ox1, oy1, dx1, dy1, lo1, hi1, tref1 = line_1
    ox2, oy2, dx2, dy2, lo2, hi2, tref2 = line_2
    wx, wy = ox2 - ox1, oy2 - oy1
    c12 = dx1 * dx2 + dy1 * dy2
    x12 = dx1 * dy2 - dy1 * dx2
    w_d1 = wx * dx1 + wy * dy1
    w_d2 = wx * dx2 + wy * dy2
    w_x_d1 = wx * dy1 - wy * dx1
    w_x_d2 = wx * dy2 - wy * dx2
    parallel = abs(c12) >= k.cos_parallel
    safe = k.one if parallel else x12
    t1, t2 = w_x_d2 / safe, w_x_d1 / safe
    if not parallel and lo1 - k.nearby <= t1 <= hi1 + k.nearby and lo2 - k.nearby <= t2 <= hi2 + k.nearby:
        return t1, t2, True
    # The endpoint candidates in the torch order (a tie keeps the earlier one); non-finite ends
    # are skipped (their distance is inf there, which never wins nor changes the minimum).
    best_d, s1, s2 = k.inf, t1, t2
    for c in range(4):
        first = c < 2
        e = (lo1 if c == 0 else hi1) if first else (lo2 if c == 2 else hi2)
        if not math.isfinite(e):
            continue
        # An end at parameter e of line 1 relative to o2: along -w.d2 + e c12, across w x d2 - e x12;
        # an end of line 2 relative to o1: along w.d1 + e c12, across w x d1 - e x12.
        if first:
            along, across = -w_d2 + e * c12, w_x_d2 - e * x12
            near = _clamped(along, lo2, hi2)
        else:
            along, across = w_d1 + e * c12, w_x_d1 - e * x12
            near = _clamped(along, lo1, hi1)
        dist = across * across + (along - near) * (along - near)
        if dist < best_d:
            s1, s2 = (e, near) if first else (near, e)
        best_d = _minimum(best_d, dist)
    # Parallel with an infinite line: the gap is the same everywhere, anchor it at the reference.
    if parallel and math.isinf(lo1):
        s1, s2 = tref1, _clamped(-w_d2 + tref1 * c12, lo2, hi2)
    elif parallel and math.isinf(lo2):
        s1, s2 = _clamped(w_d1 + tref2 * c12, lo1, hi1), tref2
    return s1, s2, False


@njit(cache=True, nogil=True, error_model="numpy")
def _line_pair_fields(ox, oy, dx, dy, lo, hi, tref, sin_angle, angle, k, separation, out):
    """Lever (out[2]) and gap vector (out[3], out[4]) of every pair (i, j) of the lines (B, U) of
    each row b, as `scores._line_pair_table`; angle, sin_angle (B, U, U) from torch (sin_angle
    read only in 'separation' mode)."""
    n_rows, n = ox.shape
    for b in range(n_rows):
        for i in range(n):
            line_i = (ox[b, i], oy[b, i], dx[b, i], dy[b, i], lo[b, i], hi[b, i], tref[b, i])
            ox_i, oy_i, dx_i, dy_i, tref_i = ox[b, i], oy[b, i], dx[b, i], dy[b, i], tref[b, i]
            for j in range(n):
                ox_j, oy_j, dx_j, dy_j, tref_j = ox[b, j], oy[b, j], dx[b, j], dy[b, j], tref[b, j]
                s_i, s_j, meet = _closest_params(line_i, (ox_j, oy_j, dx_j, dy_j, lo[b, j], hi[b, j], tref_j), k)
                gx, gy = k.zero, k.zero
                if not meet:
                    gx = ox_i + s_i * dx_i - ox_j - s_j * dx_j
                    gy = oy_i + s_i * dy_i - oy_j - s_j * dy_j
                lever = abs(tref_i - s_i) + abs(tref_j - s_j)
                if separation and angle[b, i, j] < k.parallel_below:
                    # Near-parallel: the separation of the reference points across both lines.
                    wx = ox_j + tref_j * dx_j - ox_i - tref_i * dx_i
                    wy = oy_j + tref_j * dy_j - oy_i - tref_i * dy_i
                    w_di, w_dj = wx * dx_i + wy * dy_i, wx * dx_j + wy * dy_j
                    gx = k.half * (w_di * dx_i + w_dj * dx_j) - wx
                    gy = k.half * (w_di * dy_i + w_dj * dy_j) - wy
                    lever = sin_angle[b, i, j] * k.half * (abs(w_di) + abs(w_dj))
                out[2, b, i, j], out[3, b, i, j], out[4, b, i, j] = lever, gx, gy

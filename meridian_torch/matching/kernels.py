"""Compiled (numba) kernels of matching, for CPU arrays; each replaced a chain of torch ops whose
passes over large intermediates, not arithmetic, were the cost.

- `langevin_patches`: the particle sampler's Langevin loop (`matching.particles`), every step of
  one patch (sparse drift, noise, RMSprop, projection, renormalisation, early-stop check) in a
  few passes over its (m, N) particles, which stay in the core's cache for all its steps; the
  torch loop makes ~12 passes over the whole (P, m, N) batch per step (40 % of a match). Same
  dynamics and noise, other rounding (operation order and torch's fused multiply-adds), so it
  agrees with the torch loop to rounding, not bitwise. A patch's result depends only on its own
  data and seed, never on the batch or its padding.
- `mix_words`, `uniform_words`, `particle_words`, `signed_sigmas`, `initial_particles`: the
  splitmix64 finaliser of the sampler's random words, their uniform numbers, and the words,
  noise signs and start of every particle built in one pass each (`matching.particle_noise`),
  bitwise the torch expressions.
- `round_particles`, `greedy_clusters`: the sampler's rounding of particles to sets and the
  greedy clustering of sets (`matching.hypotheses`), the same sets and clusters as torch's sort
  and sweeps; `support_walks`, `renumbered_entries`: the support pruning of the sampler's
  problem (`matching.particle_problem`), bitwise torch's index_add_ passes; `block_rows`,
  `merge_sets`: the sampler's affinity sorted into CSR rows (a coalesced COO's order) and the
  merge of identical sets (`matching.particles`), the same order and integers as torch's sorts.
- `knn_picks`: the semantic K-NN picks of the putative associations (`matching.associations`)
  without the (P, G, A) ranked tensor: the pairs torch's topk picks, but for exact ties of the
  ranked values (which the tie-break jitter leaves now and then), given to the lower index.
- `near_pairs`: verification's point-segment grid (`matching.verification.segments_near_points`).
- `near_line_closeness`: verification's line score, walking `near_pairs`' grid; bitwise the torch
  expressions. `alignment_scores`: verification's whole alignment score (lines and points) of
  every pose in float64, one grid per patch; equal to the torch path to rounding.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = [
    "alignment_scores", "block_rows", "greedy_clusters", "grown", "initial_particles", "knn_picks", "langevin_patches",
    "merge_sets",
    "mix_words", "near_line_closeness", "near_pairs", "particle_words", "renumbered_entries", "round_particles",
    "signed_sigmas", "support_walks", "uniform_words",
]

# splitmix64's finaliser constants and shifts as unsigned words.
_MIX_1, _MIX_2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_SHIFT_11, _SHIFT_27, _SHIFT_30, _SHIFT_31 = np.uint64(11), np.uint64(27), np.uint64(30), np.uint64(31)
_TWO_TO_MINUS_53 = 2.0**-53


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
    keep; norm2 += x^2. One pass, so the row is read and written once. The default dynamics
    (noise and RMSprop) after the first step have a loop of their own, without the flags'
    branches inside it: the kernel ran 11-24 % faster (one thread), with the same numbers."""
    eta, alpha, one_minus_alpha, tiny, zero = constants[0], constants[1], constants[2], constants[3], constants[4]
    if noise and rmsprop and not first:
        for c in range(x.shape[0]):
            v = g[c] + noise_row[c] * scale[c]
            hc = h[c] * alpha + one_minus_alpha * v * v
            h[c] = hc
            xc = max(x[c] + eta * (v / (np.sqrt(hc) + tiny)), zero) * keep
            x[c] = xc
            norm2[c] += xc * xc
    else:
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


@njit(cache=True, nogil=True, inline="always")
def _ranks_above(x: float, y: float) -> bool:
    """x before y in a descending topk: larger, NaN above every number (torch's order)."""
    return x > y or (x != x and y == y)


@njit(cache=True, nogil=True, inline="always")
def _insert_top(values: np.ndarray, index: np.ndarray, n: int, k: int, v: float, i: int) -> int:
    """Insert (v, i) into the descending top list of n <= k entries; returns the new n."""
    if n == k and not _ranks_above(v, values[n - 1]):
        return n
    j = n if n < k else k - 1
    while j > 0 and _ranks_above(v, values[j - 1]):
        values[j], index[j] = values[j - 1], index[j - 1]
        j -= 1
    values[j], index[j] = v, i
    return n + 1 if n < k else n


@njit(cache=True, nogil=True, inline="always")
def _knn_rank(cosine: np.ndarray, jitter: np.ndarray, p: int, g: int, a: int) -> float:
    """float32(cosine) + jitter in float64, as `associations._chunk_pairs` ranks a pair."""
    return np.float64(np.float32(cosine[p, g, a])) + jitter[g, a]


@njit(cache=True, nogil=True)
def knn_picks(
    cosine: np.ndarray, jitter: np.ndarray, ground_ok: np.ndarray, aerial_ok: np.ndarray, k_aerial: int,
    k_ground: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Flat picks g * A + a (ascending, padded with -1) and their counts per patch: for every usable
    ground primitive g its k_aerial usable aerial primitives a of the highest rank, and (k_ground >
    0: 'union') for every usable a its k_ground usable g of the highest rank (`_knn_rank`), each
    pair once; cosine (P, G, A) float64, jitter (G, A), ground_ok (G,), aerial_ok (P, A)."""
    n_patches, n_ground, n_aerial = cosine.shape
    cap = min(n_ground * n_aerial, k_aerial * n_ground + k_ground * n_aerial)
    picks = np.full((n_patches, cap), -1, np.int64)
    counts = np.zeros(n_patches, np.int64)
    selected = np.zeros(n_ground * n_aerial, np.bool_)
    values = np.empty(max(k_aerial, k_ground, 1))
    index = np.empty(max(k_aerial, k_ground, 1), np.int64)
    for p in range(n_patches):
        for g in range(n_ground if k_aerial > 0 else 0):
            if not ground_ok[g]:
                continue
            n = 0
            for a in range(n_aerial):
                if aerial_ok[p, a]:
                    n = _insert_top(values, index, n, k_aerial, _knn_rank(cosine, jitter, p, g, a), a)
            for j in range(n):
                selected[g * n_aerial + index[j]] = True
        for a in range(n_aerial if k_ground > 0 else 0):
            if not aerial_ok[p, a]:
                continue
            n = 0
            for g in range(n_ground):
                if ground_ok[g]:
                    n = _insert_top(values, index, n, k_ground, _knn_rank(cosine, jitter, p, g, a), g)
            for j in range(n):
                selected[index[j] * n_aerial + a] = True
        c = 0
        for f in range(n_ground * n_aerial):
            if selected[f]:
                picks[p, c] = f
                c += 1
                selected[f] = False
        counts[p] = c
    return picks, counts


@njit(cache=True, nogil=True)
def mix_words(z: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser of uint64 words (numba's uint64 shifts are logical, products wrap)."""
    out = np.empty_like(z)
    flat_in, flat_out = z.reshape(-1), out.reshape(-1)
    for k in range(flat_in.size):
        flat_out[k] = _mix(flat_in[k])
    return out


@njit(cache=True, nogil=True, inline="always")
def _mix(v: np.uint64) -> np.uint64:
    v = (v ^ (v >> _SHIFT_30)) * _MIX_1
    v = (v ^ (v >> _SHIFT_27)) * _MIX_2
    return v ^ (v >> _SHIFT_31)


@njit(cache=True, nogil=True)
def near_pairs(points: np.ndarray, ends: np.ndarray, valid: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """`verification.segments_near_points` on float64 arrays, one patch at a time."""
    n_patches, n_points = points.shape[0], points.shape[1]
    n_segments = ends.shape[1]
    query = np.empty(1024, np.int64)
    segment = np.empty(1024, np.int64)
    n_out = 0
    for p in range(n_patches):
        grid, starts, cell_segments = _segment_grid(ends[p], valid[p], radius)
        if len(cell_segments) == 0:
            continue
        for q in range(n_points):
            c = _grid_cell(grid, points[p, q, 0], points[p, q, 1])
            if c < 0:
                continue
            need = n_out + starts[c + 1] - starts[c]
            if need > len(query):
                capacity = max(2 * len(query), need)
                query = grown(query, capacity)
                segment = grown(segment, capacity)
            for e in range(starts[c], starts[c + 1]):
                query[n_out] = p * n_points + q
                segment[n_out] = p * n_segments + cell_segments[e]
                n_out += 1
    return query[:n_out].copy(), segment[:n_out].copy()


@njit(cache=True, nogil=True)
def _segment_grid(ends: np.ndarray, valid: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`near_pairs`' grid of one patch's segments ends (M, 2, 2) float64: (x0, y0, cell, width,
    height) as floats, each cell's start in the segment list (n_cells + 1,) and the list (empty
    without valid segments)."""
    n_segments = ends.shape[0]
    cell, spacing = 1.5 * radius, 0.5 * radius
    counts = np.zeros(n_segments, np.int64)
    for m in range(n_segments):
        if valid[m]:
            length = np.hypot(ends[m, 1, 0] - ends[m, 0, 0], ends[m, 1, 1] - ends[m, 0, 1])
            counts[m] = int(np.ceil(length / spacing)) + 1
    n_samples = counts.sum()
    if n_samples == 0:
        return np.zeros(5), np.zeros(1, np.int64), np.empty(0, np.int64)
    xy = np.empty((n_samples, 2))
    owner = np.empty(n_samples, np.int64)
    k = 0
    for m in range(n_segments):
        for step in range(counts[m]):
            f = step / max(counts[m] - 1, 1)
            for axis in range(2):
                a = ends[m, 0, axis]
                xy[k, axis] = a + f * (ends[m, 1, axis] - a)
            owner[k] = m
            k += 1
    # The grid starts two cells below the lowest sample, so every neighbour cell is >= 0.
    x0, y0 = xy[:, 0].min() - 2 * cell, xy[:, 1].min() - 2 * cell
    cx = np.floor((xy[:, 0] - x0) / cell).astype(np.int64)
    cy = np.floor((xy[:, 1] - y0) / cell).astype(np.int64)
    width, height = cx.max() + 2, cy.max() + 2
    n_cells = width * height
    starts = np.zeros(n_cells + 1, np.int64)
    _cell_segments(cx, cy, owner, width, starts[1:], starts, False)
    starts = np.cumsum(starts)
    cell_segments = np.empty(starts[-1], np.int64)
    _cell_segments(cx, cy, owner, width, starts[:-1].copy(), cell_segments, True)
    return np.array([x0, y0, cell, width, height]), starts, cell_segments


@njit(cache=True, nogil=True, inline="always")
def _grid_cell(grid: np.ndarray, x: float, y: float) -> int:
    """The cell of `_segment_grid` (x0, y0, cell, width, height) holding (x, y); -1 outside or
    not finite."""
    x0, y0, cell, width, height = grid[0], grid[1], grid[2], grid[3], grid[4]
    if not (np.isfinite(x) and np.isfinite(y)):
        return -1
    i, j = np.floor((x - x0) / cell), np.floor((y - y0) / cell)
    if i < 0 or j < 0 or i >= width or j >= height:
        return -1
    return int(j) * int(width) + int(i)


@njit(cache=True, nogil=True)
def _cell_segments(
    cx: np.ndarray, cy: np.ndarray, owner: np.ndarray, width: int, slot: np.ndarray, out: np.ndarray, fill: bool
) -> None:
    """Each cell's segments, once and ascending, from the samples' 3 x 3 cells: samples come
    segment by segment, so a cell sees its segments in order and a repeat is always its last.
    Counts them into slot[cell], and with `fill` first writes each at out[slot[cell]]."""
    last = np.full(len(slot), -1, np.int64)
    for k in range(len(owner)):
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                c = (cy[k] + dy) * width + cx[k] + dx
                if last[c] != owner[k]:
                    last[c] = owner[k]
                    if fill:
                        out[slot[c]] = owner[k]
                    slot[c] += 1


@njit(cache=True, nogil=True, error_model="numpy")
def near_line_closeness(
    points: np.ndarray,
    directions: np.ndarray,
    ends: np.ndarray,
    segment_directions: np.ndarray,
    valid: np.ndarray,
    radius: float,
    constants: np.ndarray,
) -> np.ndarray:
    """Verification's line score (`matching.verification.piece_closeness`) of points (P, Q, 2)
    with unit directions (P, Q, 2) against their patch's valid segments ends (P, M, 2, 2) with
    unit directions (P, M, 2): (P, Q) max of max(1 - d^2 / radius^2, 0), d the distance to a
    segment with |direction · segment direction| >= cos_tol, over the segments `near_pairs`
    pairs the point with (its grid, built from the same float64 values); 0 without one.
    constants = (cos_tol, 1e-12, 0, 1, radius^2) in the points' dtype: each value is rounded as
    torch's elementwise ops round it (the same operations in the same order, in that dtype), so
    the result is bitwise theirs. Scoring while walking the grid saves writing and reading the
    ~100k pairs of a chunk."""
    cos_tol, floor, zero, one, radius2 = constants[0], constants[1], constants[2], constants[3], constants[4]
    out = np.zeros(points.shape[:2], points.dtype)
    for p in range(points.shape[0]):
        grid, starts, cell_segments = _segment_grid(ends[p].astype(np.float64), valid[p], radius)
        if len(cell_segments) == 0:
            continue
        for q in range(points.shape[1]):
            px, py = points[p, q, 0], points[p, q, 1]
            c = _grid_cell(grid, np.float64(px), np.float64(py))
            if c < 0:
                continue
            out[p, q] = _closeness(
                px, py, directions[p, q, 0], directions[p, q, 1], ends[p], segment_directions[p],
                cell_segments[starts[c] : starts[c + 1]], cos_tol, floor, zero, one, radius2,
            )
    return out


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _closeness(
    px: float, py: float, ux: float, uy: float, ends: np.ndarray, segment_directions: np.ndarray,
    segments: np.ndarray, cos_tol: float, floor: float, zero: float, one: float, radius2: float,
) -> float:
    """max(1 - d^2 / radius^2, 0) of the point (px, py) with unit direction (ux, uy) over the
    `segments` (indices into ends (M, 2, 2), unit directions (M, 2)) within the angle; `zero`
    without one. Every operation in the arguments' dtype."""
    best = zero
    for m in segments:
        if abs(ux * segment_directions[m, 0] + uy * segment_directions[m, 1]) < cos_tol:
            continue
        ax, ay = ends[m, 0, 0], ends[m, 0, 1]
        abx, aby = ends[m, 1, 0] - ax, ends[m, 1, 1] - ay
        t = ((px - ax) * abx + (py - ay) * aby) / max(abx * abx + aby * aby, floor)
        t = min(max(t, zero), one)
        ex, ey = (ax + t * abx) - px, (ay + t * aby) - py
        best = max(best, max(one - (ex * ex + ey * ey) / radius2, zero))
    return best


@njit(cache=True, nogil=True, error_model="numpy")
def alignment_scores(
    T: np.ndarray,
    piece_mid: np.ndarray,
    piece_u: np.ndarray,
    piece_length: np.ndarray,
    ground_points: np.ndarray,
    ends: np.ndarray,
    line_u: np.ndarray,
    line_valid: np.ndarray,
    aerial_points: np.ndarray,
    point_valid: np.ndarray,
    cos_tol: float,
    line_distance: float,
    point_distance: float,
    point_weight: float,
) -> np.ndarray:
    """`matching.verification.alignment_score` of poses T (P, H, 3, 3), float64 throughout: the
    ground line pieces (midpoints, unit directions, lengths) and points moved by each pose, each
    piece scored against its patch's valid segments (unit directions line_u) through `near_pairs`'
    grid (built once per patch, not per chunk of poses), each point against every valid aerial
    point."""
    n_patches, n_poses = T.shape[0], T.shape[1]
    out = np.zeros((n_patches, n_poses))
    line2, point2 = line_distance * line_distance, point_distance * point_distance
    for p in range(n_patches):
        grid, starts, cell_segments = _segment_grid(ends[p], line_valid[p], line_distance)
        for h in range(n_poses):
            r00, r01, tx = T[p, h, 0, 0], T[p, h, 0, 1], T[p, h, 0, 2]
            r10, r11, ty = T[p, h, 1, 0], T[p, h, 1, 1], T[p, h, 1, 2]
            score = 0.0
            if len(cell_segments):
                for n in range(piece_mid.shape[0]):
                    px = r00 * piece_mid[n, 0] + r01 * piece_mid[n, 1] + tx
                    py = r10 * piece_mid[n, 0] + r11 * piece_mid[n, 1] + ty
                    c = _grid_cell(grid, px, py)
                    if c < 0:
                        continue
                    ux = r00 * piece_u[n, 0] + r01 * piece_u[n, 1]
                    uy = r10 * piece_u[n, 0] + r11 * piece_u[n, 1]
                    best = _closeness(
                        px, py, ux, uy, ends[p], line_u[p], cell_segments[starts[c] : starts[c + 1]], cos_tol, 1e-12,
                        0.0, 1.0, line2,
                    )
                    score += best * piece_length[n]
            points_score = 0.0
            for g in range(ground_points.shape[0]):
                qx = r00 * ground_points[g, 0] + r01 * ground_points[g, 1] + tx
                qy = r10 * ground_points[g, 0] + r11 * ground_points[g, 1] + ty
                best = 0.0
                for a in range(aerial_points.shape[1]):
                    if point_valid[p, a]:
                        dx, dy = qx - aerial_points[p, a, 0], qy - aerial_points[p, a, 1]
                        best = max(best, 1.0 - (dx * dx + dy * dy) / point2)
                points_score += best
            out[p, h] = score + point_weight * points_score
    return out


@njit(cache=True, nogil=True)
def grown(array: np.ndarray, capacity: int) -> np.ndarray:
    """`array` copied into a new array of `capacity` (the output buffers' doubling)."""
    out = np.empty(capacity, array.dtype)
    out[: len(array)] = array
    return out


@njit(cache=True, nogil=True)
def round_particles(
    x: np.ndarray, k: np.ndarray, valid: np.ndarray, pairs: np.ndarray, support: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sampler's rounding (`matching.particles`) of particles x (P, m, N): each particle's set
    is its k[p, n] largest valid entries, ties in index order (or, with `support`, its valid
    entries > 0). Returns masks (P, N, m) bool, sizes (P, N) and whether no ground and no aerial
    primitive (pairs (P, m, 2)) is used twice (P, N).

    Most entries of a settled particle are exactly 0, so its nonzeros are ranked alone (by
    insertion) and the zeros, if the set needs any, follow in index order."""
    n_patches, m, n_particles = x.shape
    masks = np.zeros((n_patches, n_particles, m), np.bool_)
    size = np.zeros((n_patches, n_particles), np.int64)
    one_to_one = np.ones((n_patches, n_particles), np.bool_)
    ranked = np.empty(m, np.int64)
    chosen = np.empty(m, np.int64)
    for p in range(n_patches):
        for n in range(n_particles):
            count = 0
            if support:
                for i in range(m):
                    if valid[p, i] and x[p, i, n] > 0:
                        chosen[count] = i
                        count += 1
            else:
                n_ranked = 0
                for i in range(m):
                    value = x[p, i, n]
                    if valid[p, i] and value != 0:
                        slot = n_ranked  # insert after every larger or equal value (stable)
                        while slot > 0 and x[p, ranked[slot - 1], n] < value:
                            ranked[slot] = ranked[slot - 1]
                            slot -= 1
                        ranked[slot] = i
                        n_ranked += 1
                want = k[p, n]
                for r in range(min(want, n_ranked)):
                    chosen[count] = ranked[r]
                    count += 1
                for i in range(m):
                    if count >= want:
                        break
                    if valid[p, i] and x[p, i, n] == 0:
                        chosen[count] = i
                        count += 1
            size[p, n] = count
            for a in range(count):
                masks[p, n, chosen[a]] = True
                for b in range(a):
                    for side in range(2):
                        if pairs[p, chosen[a], side] == pairs[p, chosen[b], side]:
                            one_to_one[p, n] = False
    return masks, size, one_to_one


@njit(cache=True, nogil=True)
def uniform_words(z: np.ndarray, out: np.ndarray) -> None:
    """out = U[0, 1) from the top 53 bits of the uint64 words z (computed in float64, then
    rounded to out's dtype)."""
    flat_in, flat_out = z.reshape(-1), out.reshape(-1)
    for k in range(flat_in.size):
        flat_out[k] = _uniform(flat_in[k])


@njit(cache=True, nogil=True, inline="always")
def _uniform(v: np.uint64) -> float:
    return np.float64(v >> _SHIFT_11) * _TWO_TO_MINUS_53


@njit(cache=True, nogil=True, error_model="numpy")
def support_walks(index: np.ndarray, value: np.ndarray, validf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The degree (M' valid) * valid and the two-step walk count M' degree (P, m) of
    `particle_problem.support_pruning`, M' given by its strict upper-triangle entries index (n, 3)
    (patch, i, j) and value (n,); validf (P, m) in value's dtype. Each product M' x is summed
    entry by entry, first into the rows i, then into the rows j: torch's two index_add_ passes."""
    degree = _upper_times(index, value, validf) * validf
    return degree, _upper_times(index, value, degree)


@njit(cache=True, nogil=True, error_model="numpy")
def _upper_times(index: np.ndarray, value: np.ndarray, x: np.ndarray) -> np.ndarray:
    out = np.zeros_like(x)
    for e in range(len(value)):
        out[index[e, 0], index[e, 1]] += value[e] * x[index[e, 0], index[e, 2]]
    for e in range(len(value)):
        out[index[e, 0], index[e, 2]] += value[e] * x[index[e, 0], index[e, 1]]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def renumbered_entries(index: np.ndarray, value: np.ndarray, new_of_old: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The entries (patch, i, j), value whose i and j both have a new number (new_of_old (P, m)
    >= 0), in their order, with i and j renumbered."""
    keep = np.empty(len(value), np.bool_)
    for e in range(len(value)):
        keep[e] = new_of_old[index[e, 0], index[e, 1]] >= 0 and new_of_old[index[e, 0], index[e, 2]] >= 0
    n_kept = keep.sum()
    kept_index = np.empty((n_kept, 3), np.int64)
    kept_value = np.empty(n_kept, value.dtype)
    k = 0
    for e in range(len(value)):
        if keep[e]:
            b = index[e, 0]
            kept_index[k, 0], kept_index[k, 1], kept_index[k, 2] = b, new_of_old[b, index[e, 1]], new_of_old[b, index[e, 2]]
            kept_value[k] = value[e]
            k += 1
    return kept_index, kept_value


@njit(cache=True, nogil=True, error_model="numpy")
def greedy_clusters(
    t: np.ndarray, theta: np.ndarray, valid: np.ndarray, counts: np.ndarray, limits: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The greedy clustering of `matching.hypotheses` for poses t (P, S, 2), theta (P, S): in
    index order a valid set joins the first earlier representative close to it, else founds a
    cluster. Returns the representatives (P, S) bool and their weights (P, S), the summed counts
    of the valid sets that join them (a set joins the first representative close to it; none:
    set 0's cluster); 0 elsewhere. Only the pairs the walk needs are compared, in the dtype of
    t with limits = (translation, rotation in radians, pi, 2 pi) in it: torch's expressions."""
    n_patches, n_sets = valid.shape
    rep = np.zeros((n_patches, n_sets), np.bool_)
    weight = np.zeros((n_patches, n_sets), np.int64)
    joined = np.empty(n_sets, np.int64)
    reps = np.empty(n_sets, np.int64)
    for p in range(n_patches):
        n_reps = 0
        for s in range(n_sets):
            joined[s] = 0
            if not valid[p, s]:
                continue
            joined[s] = -1
            for q in range(n_reps):
                if _close(t, theta, limits, p, s, reps[q]):
                    joined[s] = reps[q]
                    break
            if joined[s] < 0:
                rep[p, s] = True
                reps[n_reps] = s
                n_reps += 1
        # A representative joins itself unless its pose is not close to itself (NaN): then the
        # first later representative close to it, or set 0's cluster.
        for q in range(n_reps):
            s = reps[q]
            joined[s] = 0
            for later in range(q, n_reps):
                if _close(t, theta, limits, p, s, reps[later]):
                    joined[s] = reps[later]
                    break
        for s in range(n_sets):
            if valid[p, s]:
                weight[p, joined[s]] += counts[p, s]
        for s in range(n_sets):
            if not rep[p, s]:
                weight[p, s] = 0
    return rep, weight


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _close(t: np.ndarray, theta: np.ndarray, limits: np.ndarray, p: int, s: int, r: int) -> bool:
    """|t_s - t_r| <= limits[0] and |wrap(theta_s - theta_r)| <= limits[1], wrap(a) = remainder(a +
    pi, 2 pi) - pi with torch's remainder (fmod, then + 2 pi if the signs differ)."""
    dx, dy = t[p, s, 0] - t[p, r, 0], t[p, s, 1] - t[p, r, 1]
    if not np.sqrt(dx * dx + dy * dy) <= limits[0]:
        return False
    shifted = (theta[p, s] - theta[p, r]) + limits[2]
    wrapped = np.fmod(shifted, limits[3])
    if wrapped != 0 and (limits[3] < 0) != (wrapped < 0):
        wrapped = wrapped + limits[3]
    return abs(wrapped - limits[2]) <= limits[1]


@njit(cache=True, nogil=True, error_model="numpy")
def merge_sets(
    masks: np.ndarray, keep: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The merge of identical sets of `matching.particles._merge`: masks (P, N, m) bool, keep
    (P, N) bool, weights (m,) int64 of the linear hash. Per patch the particles in the order of
    their (hash key, particle), signed and stable, kept ones first; returns that order (P, N),
    the masks in it (P, N, m), first (P, N) bool marking the first particle of each run of equal
    kept sets, and counts (P, N), the run's length at its first particle (0 elsewhere)."""
    n_patches, n_particles, m = masks.shape
    order = np.empty((n_patches, n_particles), np.int64)
    masks_sorted = np.empty_like(masks)
    first = np.zeros((n_patches, n_particles), np.bool_)
    counts = np.zeros((n_patches, n_particles), np.int64)
    words = weights.view(np.uint64)
    key = np.empty(n_particles, np.uint64)
    for p in range(n_patches):
        for n in range(n_particles):
            k = np.uint64(0)  # sums wrap mod 2^64
            for i in range(m):
                if masks[p, n, i]:
                    k += words[i]
            key[n] = k
        by_key = np.argsort(key.view(np.int64), kind="mergesort")
        j = 0
        for kept in (True, False):
            for n in by_key:
                if keep[p, n] == kept:
                    order[p, j] = n
                    j += 1
        last = -1  # position of the current run's first particle
        for j in range(n_particles):
            n = order[p, j]
            masks_sorted[p, j] = masks[p, n]
            if not keep[p, n]:
                continue
            if last >= 0 and key[n] == key[order[p, j - 1]] and _equal_rows(masks[p, n], masks[p, order[p, j - 1]]):
                counts[p, last] += 1
            else:
                first[p, j] = True
                counts[p, j] = 1
                last = j
    return order, masks_sorted, first, counts


@njit(cache=True, nogil=True, inline="always")
def _equal_rows(a: np.ndarray, b: np.ndarray) -> bool:
    for i in range(a.shape[0]):
        if a[i] != b[i]:
            return False
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def block_rows(
    index: np.ndarray, value: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """P symmetric affinities (m, m) from their strict upper-triangle entries index (n, 3)
    (patch, i, j), value (n,) (each pair once) and unit diagonal on valid (P, m), as the rows p m
    + i of one CSR matrix in `AffinityEntries.to_sparse`'s coalesced order (rows, then columns
    ascending): crow (P m + 1,), and per entry its patch, row i, column j and value."""
    n_patches, m = valid.shape
    crow = np.zeros(n_patches * m + 1, np.int64)
    for e in range(len(value)):
        crow[index[e, 0] * m + index[e, 1] + 1] += 1
        crow[index[e, 0] * m + index[e, 2] + 1] += 1
    for r in range(n_patches * m):
        crow[r + 1] += crow[r] + valid[r // m, r % m]
    nnz = crow[-1]
    col = np.empty(nnz, np.int64)
    out = np.empty(nnz, value.dtype)
    slot = crow[:-1].copy()
    for r in range(n_patches * m):
        if valid[r // m, r % m]:
            col[slot[r]], out[slot[r]] = r % m, 1.0
            slot[r] += 1
    for e in range(len(value)):
        for a, b in ((1, 2), (2, 1)):
            r = index[e, 0] * m + index[e, a]
            col[slot[r]], out[slot[r]] = index[e, b], value[e]
            slot[r] += 1
    batch = np.empty(nnz, np.int64)
    row = np.empty(nnz, np.int64)
    for r in range(n_patches * m):
        batch[crow[r] : crow[r + 1]] = r // m
        row[crow[r] : crow[r + 1]] = r % m
        for k in range(crow[r] + 1, crow[r + 1]):  # insertion sort of the row by column
            c, v = col[k], out[k]
            q = k
            while q > crow[r] and col[q - 1] > c:
                col[q], out[q] = col[q - 1], out[q - 1]
                q -= 1
            col[q], out[q] = c, v
    return crow, batch, row, col, out


@njit(cache=True, nogil=True)
def particle_words(base: np.ndarray, n: int, row: np.uint64) -> np.ndarray:
    """The words mix(base + k row) (S, n) of the sampler's particles k < n for the uint64 words
    base (S,) (sums and products wrap mod 2^64), in one pass."""
    out = np.empty((len(base), n), np.uint64)
    for a in range(len(base)):
        for k in range(n):
            out[a, k] = _mix(base[a] + np.uint64(k) * row)
    return out


@njit(cache=True, nogil=True)
def signed_sigmas(words: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """sigmas[t] x (1 - 2 (words[t, k] & 1)) (T, K) in sigmas' dtype: the noise scale of every
    step and particle with its sign from the word's low bit (negation is the exact product)."""
    out = np.empty(words.shape, sigmas.dtype)
    for t in range(words.shape[0]):
        for k in range(words.shape[1]):
            out[t, k] = -sigmas[t] if words[t, k] & np.uint64(1) else sigmas[t]
    return out


@njit(cache=True, nogil=True)
def initial_particles(words: np.ndarray, coord_keys: np.ndarray, validf: np.ndarray) -> np.ndarray:
    """The sampler's start x[p, i, n] = U(mix(words[p, n] ^ coord_keys[i])) x validf[p, i] (P, m, N)
    in validf's dtype (U as `uniform_words`, rounded to the dtype before the product)."""
    n_patches, m = validf.shape
    out = np.empty((n_patches, m, words.shape[1]), validf.dtype)
    for p in range(n_patches):
        for i in range(m):
            for n in range(words.shape[1]):
                out[p, i, n] = _uniform(_mix(words[p, n] ^ coord_keys[i]))
                out[p, i, n] *= validf[p, i]
    return out

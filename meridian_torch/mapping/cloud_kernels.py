"""Compiled (numba) kernels for grouped point clouds: exact k-nearest-neighbour distances, DBSCAN
labels and whether a query has a point of its group within a radius, each group searched on its
own uniform grid.

Clouds are (N, 2) or (N, 3) float64, sorted by group, with `starts` (G + 1,) the first row of
every group. A grid sorts a group's points by cell (x, y, z) and finds the columns of cells
(x, y) through a hash table, so its memory follows the points, not the bounding box
(group_any_within, for speed, through a dense table of at most max(16 n, 2^16) columns). Distances
are sqrt(((0 + dx*dx) + dy*dy) + dz*dz) in float64, the same operations as scipy's cKDTree, so
the k-NN distances equal cKDTree's bitwise and `group_any_within` decides as
cKDTree.query(distance_upper_bound=radius) (squared distance < radius * radius).
`group_voxel_order` is the stable (group, voxel) sort behind voxel downsampling and the DBSCAN
cells, `run_means` the means of its runs; `voxels_reached` and `merge_sorted_rows` the tracker's
test of occluded voxels against a cloud on the same lattice and its growth. The kernels release
the GIL (frames run in threads).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from meridian_torch.core.union_find import find_root

__all__ = [
    "group_any_within", "group_dbscan_labels", "group_knn_distances", "group_voxel_order", "merge_sorted_rows",
    "run_means", "voxels_reached",
]

_BRUTE_FORCE_MAX = 48  # groups up to this size are searched pair by pair (faster than a grid)
_SAMPLE = 16  # points whose k-NN distance sets a group's cell size
_CELL_PER_KNN = 1.5  # cell size / median k-NN distance (KITTI 09 frames: 1.3-1.6 fastest, 1.0 is 1.4x slower)
_CELL_PER_RADIUS = 3.0  # group_any_within's cell / radius (KITTI 09 frames: 3-4 fastest, 1 is 1.2x slower)
# relative slack of the ring bound and of group_any_within's reach (rounding of coordinates up to
# ~1e7 is < 1e-15)
_TOL = 1e-12
_RADIX_BITS = 11  # digit of the radix sort: 3 passes sort a frame's (group, voxel) keys
_KEY_LIMIT = 1 << 62  # (group, voxel) ranges beyond this many keys are left to the caller


@njit(cache=True, nogil=True, inline="always")
def _dist2(points: np.ndarray, i: int, others: np.ndarray, j: int) -> float:
    """Squared distance of points[i] and others[j] (often the same array)."""
    s = 0.0  # cKDTree's order: 0 + dx*dx, then + dy*dy, then + dz*dz (the sign of d is exact)
    for a in range(points.shape[1]):
        d = points[i, a] - others[j, a]
        s += d * d
    return s


@njit(cache=True, nogil=True, inline="always")
def _push(best: np.ndarray, d2: float) -> None:
    """Insert d2 into the ascending `best` (inf = empty), dropping the largest. Branch-free: 3x
    faster than a shifting insertion, whose exits the CPU cannot predict."""
    for j in range(len(best) - 1, 0, -1):
        best[j] = min(best[j], max(best[j - 1], d2))
    best[0] = min(best[0], d2)


@njit(cache=True, nogil=True, inline="always")
def _hash(key: int, mask: int) -> int:
    x = key * 2654435761  # wraps in int64; the mask keeps the low bits
    return (x ^ (x >> 16)) & mask


@njit(cache=True, nogil=True)
def _grid_cells(points: np.ndarray, a: int, b: int, cell: float):
    """Rows a..b-1 sorted by cell of `cell` metres (x, then y, then z), from the group's minimum
    corner: (minimum corner (3,), order: grid position -> row - a, cell index (n, 3) by grid
    position, shape (3,), cell key (x * shape[1] + y) * shape[2] + z (n,) by grid position)."""
    n, dims = b - a, points.shape[1]
    lo = np.zeros(3)
    for ax in range(dims):
        lo[ax] = points[a, ax]
        for i in range(a, b):
            lo[ax] = min(lo[ax], points[i, ax])
    raw = np.zeros((n, 3), np.int64)
    shape = np.ones(3, np.int64)
    for i in range(n):
        for ax in range(dims):
            c = int(np.floor((points[a + i, ax] - lo[ax]) / cell))
            raw[i, ax] = c
            shape[ax] = max(shape[ax], c + 1)
    key = (raw[:, 0] * shape[1] + raw[:, 1]) * shape[2] + raw[:, 2]
    order = np.argsort(key)
    return lo, order, raw[order], shape, key[order]


@njit(cache=True, nogil=True)
def _grid(points: np.ndarray, a: int, b: int, cell: float):
    """`_grid_cells` and a hash table of its cell columns (x, y): (minimum corner, order, cells,
    shape, column start (m + 1,) in grid positions, hash table keys (H,) and columns (H,))."""
    lo, order, cells, shape, _ = _grid_cells(points, a, b, cell)
    col_start = _run_starts(cells, 2)
    m = len(col_start) - 1
    size = 1
    while size < 2 * m:
        size *= 2
    table_key = np.full(size, -1, np.int64)
    table_col = np.empty(size, np.int64)
    for col in range(m):
        p = col_start[col]
        k = cells[p, 0] * shape[1] + cells[p, 1]
        h = _hash(k, size - 1)
        while table_key[h] >= 0:
            h = (h + 1) & (size - 1)
        table_key[h] = k
        table_col[h] = col
    return lo, order, cells, shape, col_start, table_key, table_col


@njit(cache=True, nogil=True, inline="always")
def _column(table_key: np.ndarray, table_col: np.ndarray, shape: np.ndarray, x: int, y: int) -> int:
    """Column index of cell column (x, y), -1 if empty or outside the grid."""
    if x < 0 or y < 0 or x >= shape[0] or y >= shape[1]:
        return -1
    k = x * shape[1] + y
    mask = len(table_key) - 1
    h = _hash(k, mask)
    while table_key[h] >= 0:
        if table_key[h] == k:
            return table_col[h]
        h = (h + 1) & mask
    return -1


@njit(cache=True, nogil=True, inline="always")
def _z_from(z_of: np.ndarray, s: int, e: int, z: int) -> int:
    """First grid position in s..e-1 (one column, sorted by z) with cell z >= z."""
    while s < e:
        mid = (s + e) // 2
        if z_of[mid] < z:
            s = mid + 1
        else:
            e = mid
    return s


@njit(cache=True, nogil=True)
def _knn_brute(points: np.ndarray, a: int, b: int, i: int, best: np.ndarray) -> None:
    """best = the len(best) smallest squared distances from point i to rows a..b-1."""
    best[:] = np.inf
    for j in range(a, b):
        d2 = _dist2(points, i, points, j)
        if d2 < best[-1]:  # rarely true after the first few, unlike in a cell's box
            _push(best, d2)


@njit(cache=True, nogil=True, inline="always")
def _write(out: np.ndarray, i: int, best: np.ndarray) -> None:
    for j in range(1, len(best)):  # the first is the point itself (or a duplicate)
        out[i, j - 1] = np.sqrt(best[j])


@njit(cache=True, nogil=True)
def _cell_size(points: np.ndarray, a: int, b: int, k1: int) -> float:
    """Cell size of a group: _CELL_PER_KNN times the median k-NN distance of evenly spaced points,
    at least extent / 2^20 (bounded cell indices); 1 if all points coincide."""
    n, dims = b - a, points.shape[1]
    best = np.empty(k1)
    sample = np.empty(_SAMPLE)
    for s in range(_SAMPLE):
        _knn_brute(points, a, b, a + s * n // _SAMPLE, best)
        sample[s] = best[-1]
    cell = _CELL_PER_KNN * np.sqrt(np.median(sample))
    extent = 0.0
    for ax in range(dims):
        extent = max(extent, points[a:b, ax].max() - points[a:b, ax].min())
    if extent == 0.0:
        return 1.0
    if cell == 0.0:  # mostly duplicates: the spacing of n points spread evenly
        cell = extent / n ** (1.0 / dims)
    return max(cell, extent / 2.0**20)


@njit(cache=True, nogil=True)
def _run_starts(cells: np.ndarray, n_axes: int) -> np.ndarray:
    """(runs + 1,) first grid position of every run of equal cells[:, :n_axes] (the grid is sorted
    by cell): n_axes 2 gives the columns (x, y), 3 the cells."""
    n = len(cells)
    start = np.empty(n + 1, np.int64)
    count = 0
    for p in range(n):
        new = p == 0
        for ax in range(n_axes):
            new = new or cells[p, ax] != cells[p - 1, ax]
        if new:
            start[count] = p
            count += 1
    start[count] = n
    return start[: count + 1]


@njit(cache=True, nogil=True)
def group_knn_distances(points: np.ndarray, starts: np.ndarray, k: int) -> np.ndarray:
    """(N, k) ascending distances from every point to its k nearest other points of its group, inf
    where the group has fewer; exact (the k + 1 nearest including the point itself, the first
    dropped, as cKDTree.query(k=k + 1)[:, 1:]).

    The points of one cell share the search: shells of cells around it, outwards, until a point's
    k + 1-th distance is within the searched box (or the box holds the whole group)."""
    n, dims = points.shape
    out = np.full((n, k), np.inf)
    if k == 0:
        return out
    k1 = k + 1
    for g in range(len(starts) - 1):
        a, b = starts[g], starts[g + 1]
        if b - a <= max(_BRUTE_FORCE_MAX, k1):
            best = np.empty(k1)
            for i in range(a, b):
                _knn_brute(points, a, b, i, best)
                _write(out, i, best)
            continue
        cell = _cell_size(points, a, b, k1)
        lo, order, cells, shape, col_start, table_key, table_col = _grid(points, a, b, cell)
        n_cols = len(col_start) - 1
        grid_points = points[a + order]  # grid order: a column's points are contiguous in memory
        z_of = cells[:, 2].copy()
        cell_start = _run_starts(cells, 3)
        tol = _TOL * (np.abs(grid_points).max() + cell)
        best = np.empty(k1)
        done = np.empty(np.diff(cell_start).max(), np.bool_)
        # the candidates of a cell's box (x, y, z; z = 0 in 2D) and their squared distances
        box = np.zeros((3, b - a))
        d2 = np.empty(b - a)
        near = np.empty(b - a, np.int64)
        last_kth2 = np.inf
        for c in range(len(cell_start) - 1):
            p0, p1 = cell_start[c], cell_start[c + 1]
            cx, cy, cz = cells[p0, 0], cells[p0, 1], cells[p0, 2]
            done[: p1 - p0] = False
            left = p1 - p0
            n_box = 0
            r = 0
            while left > 0:
                if (2 * r + 1) ** 2 > 4 * n_cols:  # a far search: every point costs less
                    for p in range(p0, p1):
                        if not done[p - p0]:
                            _knn_brute(grid_points, 0, b - a, p, best)
                            _write(out, a + order[p], best)
                    break
                for x in range(cx - r, cx + r + 1):
                    for y in range(cy - r, cy + r + 1):
                        col = _column(table_key, table_col, shape, x, y)
                        if col < 0:
                            continue
                        s, e = col_start[col], col_start[col + 1]
                        rim = abs(x - cx) == r or abs(y - cy) == r
                        # rim columns: all z of the shell; inner columns: its bottom and top only
                        z = cz - r
                        while z <= cz + r:
                            q0 = _z_from(z_of, s, e, z)
                            q1 = _z_from(z_of, q0, e, (cz + r if rim else z) + 1)
                            for q in range(q0, q1):
                                for ax in range(dims):
                                    box[ax, n_box] = grid_points[q, ax]
                                n_box += 1
                            z = cz + r + 1 if rim or r == 0 else z + 2 * r
                for p in range(p0, p1):
                    if done[p - p0]:
                        continue
                    # every point outside the box is at least `bound` away: done when k + 1
                    # candidates are within it, and only those can be the nearest
                    bound = np.inf
                    for ax in range(dims):
                        local = grid_points[p, ax] - lo[ax]
                        if cells[p, ax] - r > 0:
                            bound = min(bound, local - (cells[p, ax] - r) * cell)
                        if cells[p, ax] + r < shape[ax] - 1:
                            bound = min(bound, (cells[p, ax] + r + 1) * cell - local)
                    within2 = np.inf if bound == np.inf else (bound - tol) ** 2 if bound > tol else -1.0
                    guess2 = min(within2, 2.0 * last_kth2)  # a neighbour's k-NN radius, widened
                    px, py = grid_points[p, 0], grid_points[p, 1]
                    pz = grid_points[p, 2] if dims == 3 else 0.0
                    n_within = 0
                    n_guess = 0
                    for q in range(n_box):
                        dx, dy, dz = px - box[0, q], py - box[1, q], pz - box[2, q]
                        d2[q] = dx * dx + dy * dy + dz * dz  # cKDTree's sum (0 + dx*dx first)
                        n_within += d2[q] <= within2
                        n_guess += d2[q] <= guess2
                    if bound != np.inf and n_within < k1:
                        continue
                    # the k + 1 smallest are among the candidates under a limit if k + 1 are
                    limit2 = guess2 if n_guess >= k1 else within2
                    n_near = 0
                    for q in range(n_box):  # branch-free compaction
                        near[n_near] = q
                        n_near += d2[q] <= limit2
                    best[:] = np.inf
                    for t in range(n_near):
                        _push(best, d2[near[t]])
                    _write(out, a + order[p], best)
                    if best[-1] < np.inf:
                        last_kth2 = best[-1]
                    done[p - p0] = True
                    left -= 1
                r += 1
    return out


@njit(cache=True, nogil=True)
def group_dbscan_labels(points: np.ndarray, weight: np.ndarray, starts: np.ndarray, eps: float,
                        min_points: float) -> np.ndarray:
    """DBSCAN of weighted points per group: (N,) cluster label, -1 for noise.

    A point is core when the weight within eps (distance <= eps, itself included) reaches
    `min_points`; core points within eps are connected; a border point (not core, a core point
    within eps) takes the label of its nearest core point, ties to the lowest row. Labels count
    up from 0 in the order of each cluster's first core row.
    """
    n, dims = points.shape
    label = np.full(n, -1, np.int64)
    eps2 = eps * eps
    cell = eps / np.sqrt(dims) * (1.0 - 1e-6)  # any two points of one cell are within eps
    reach = 2  # cells further than 2 apart along an axis are more than eps apart
    next_label = 0
    for g in range(len(starts) - 1):
        a, b = starts[g], starts[g + 1]
        if b == a:
            continue
        _, order, cells, shape, point_key = _grid_cells(points, a, b, cell)
        grid_points, grid_weight = points[a + order], weight[a + order]
        m = b - a
        cell_start = _run_starts(cells, 3)
        n_cells = len(cell_start) - 1
        cell_of = np.empty(m, np.int64)
        for c in range(n_cells):
            cell_of[cell_start[c]: cell_start[c + 1]] = c
        # neighbour cells (itself included), CSR; grown as needed (up to 125 a cell, ~25 on ground).
        # Cells are sorted by key (x, y, z): the neighbours in column (x + dx, y + dy) are one run
        # of keys, and its start only moves forward as the cells go up, so each of the 25 columns
        # keeps a cursor (no hashing, memory read in order); with one z layer (2D) the 5 columns
        # of one dx are one run
        s1, s2 = shape[1], shape[2]
        key = point_key[cell_start[:-1]]
        width = 2 * reach + 1
        flat = s2 == 1
        n_runs = 1 if flat else width
        cursor = np.zeros(width * width, np.int64)
        nb_start = np.empty(n_cells + 1, np.int64)
        nb = np.empty(27 * n_cells, np.int64)
        n_nb = 0
        for c in range(n_cells):
            nb_start[c] = n_nb
            p0 = cell_start[c]
            cx, cy, cz = cells[p0, 0], cells[p0, 1], cells[p0, 2]
            z_lo, z_hi = max(cz - reach, 0), min(cz + reach, s2 - 1)
            for i in range(width):
                x = cx + i - reach
                if x < 0 or x >= shape[0]:
                    continue
                for j in range(n_runs):
                    if flat:  # one z layer: the 5 columns x, y - 2 .. y + 2 are one run of keys
                        y_lo, y_hi = max(cy - reach, 0), min(cy + reach, s1 - 1)
                    else:
                        y_lo = y_hi = cy + j - reach
                        if y_lo < 0 or y_lo >= s1:
                            continue
                    t = cursor[i * width + j]
                    while t < n_cells and key[t] < (x * s1 + y_lo) * s2 + z_lo:
                        t += 1
                    cursor[i * width + j] = t
                    last = (x * s1 + y_hi) * s2 + z_hi
                    while t < n_cells and key[t] <= last:
                        if n_nb == len(nb):
                            grown = np.empty(2 * len(nb), np.int64)
                            grown[:n_nb] = nb
                            nb = grown
                        nb[n_nb] = t
                        n_nb += 1
                        t += 1
        nb_start[n_cells] = n_nb
        # core points: weight of the own cell, then neighbours until min_points
        core = np.zeros(m, np.bool_)
        for c in range(n_cells):
            own = 0.0
            for p in range(cell_start[c], cell_start[c + 1]):
                own += grid_weight[p]
            for p in range(cell_start[c], cell_start[c + 1]):
                total = own
                t = nb_start[c]
                while total < min_points and t < nb_start[c + 1]:
                    d = nb[t]
                    if d != c:
                        for q in range(cell_start[d], cell_start[d + 1]):
                            if _dist2(grid_points, p, grid_points, q) <= eps2:
                                total += grid_weight[q]
                    t += 1
                core[p] = total >= min_points
        # clusters: union of cells holding core points (one cell's cores are all connected)
        has_core = np.zeros(n_cells, np.bool_)
        for p in range(m):
            if core[p]:
                has_core[cell_of[p]] = True
        parent = np.arange(n_cells)
        for c in range(n_cells):
            if not has_core[c]:
                continue
            for t in range(nb_start[c], nb_start[c + 1]):
                d = nb[t]
                if d <= c or not has_core[d] or find_root(parent, c) == find_root(parent, d):
                    continue
                linked = False
                for p in range(cell_start[c], cell_start[c + 1]):
                    if not core[p]:
                        continue
                    for q in range(cell_start[d], cell_start[d + 1]):
                        if core[q] and _dist2(grid_points, p, grid_points, q) <= eps2:
                            linked = True
                            break
                    if linked:
                        break
                if linked:
                    parent[find_root(parent, d)] = find_root(parent, c)
        # labels by each cluster's first core row
        first_row = np.full(n_cells, m, np.int64)
        for p in range(m):
            if core[p]:
                root = find_root(parent, cell_of[p])
                first_row[root] = min(first_row[root], order[p])
        roots = np.flatnonzero(first_row < m)
        root_label = np.full(n_cells, -1, np.int64)
        for rank, root in enumerate(roots[np.argsort(first_row[roots])]):
            root_label[root] = next_label + rank
        next_label += len(roots)
        for p in range(m):
            if core[p]:
                label[a + order[p]] = root_label[find_root(parent, cell_of[p])]
        # border points: the nearest core point within eps, ties to the lowest row
        for p in range(m):
            if core[p]:
                continue
            c = cell_of[p]
            best_d2, best = np.inf, m
            for t in range(nb_start[c], nb_start[c + 1]):
                d = nb[t]
                if not has_core[d]:
                    continue
                for q in range(cell_start[d], cell_start[d + 1]):
                    if not core[q]:
                        continue
                    d2 = _dist2(grid_points, p, grid_points, q)
                    if d2 <= eps2 and (d2 < best_d2 or (d2 == best_d2 and order[q] < best)):
                        best_d2, best = d2, order[q]
            if best < m:
                label[a + order[p]] = label[a + best]
    return label


@njit(cache=True, nogil=True)
def group_voxel_order(points: np.ndarray, groups: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Stable order of the rows by (group, voxel index floor(p / voxel_m) in x, y, z order): (order
    (N,), first (N,) bool, True where a sorted row starts a run of equal (group, voxel), largest
    |voxel index|). The order of np.lexsort((voxel keys, groups)) for any keys monotone in the
    index (as `voxel_hash`): the voxel indices relative to their minimum and the group form one
    integer key, sorted by a stable LSD radix sort. (N, 2) points use z index 0. When the ranges
    do not fit one int64 key, order and first are empty (the caller sorts)."""
    n, dims = points.shape
    idx = np.zeros((n, 3), np.int64)
    lo = np.zeros(4, np.int64)
    hi = np.zeros(4, np.int64)
    largest = 0
    for i in range(n):
        for ax in range(dims):
            v = int(np.floor(points[i, ax] / voxel_m))
            idx[i, ax] = v
            largest = max(largest, abs(v))
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.bool_), 0
    for ax in range(3):
        lo[ax], hi[ax] = idx[:, ax].min(), idx[:, ax].max()
    lo[3], hi[3] = groups.min(), groups.max()
    # key = ((group * span_x + x) * span_y + y) * span_z + z, all relative to the minimum
    span = hi - lo + 1
    total = 1
    for ax in (3, 0, 1, 2):
        if span[ax] >= _KEY_LIMIT // total:
            return np.zeros(0, np.int64), np.zeros(0, np.bool_), largest
        total *= span[ax]
    key = np.empty(n, np.int64)
    for i in range(n):
        key[i] = (((groups[i] - lo[3]) * span[0] + idx[i, 0] - lo[0]) * span[1] + idx[i, 1] - lo[1]) * span[2] \
            + idx[i, 2] - lo[2]
    order = np.arange(n)
    other = np.empty(n, np.int64)
    count = np.empty((1 << _RADIX_BITS) + 1, np.int64)
    digit_mask = (1 << _RADIX_BITS) - 1
    shift = 0
    while shift == 0 or (total - 1) >> shift > 0:
        count[:] = 0
        for i in range(n):
            count[((key[order[i]] >> shift) & digit_mask) + 1] += 1
        for d in range(1, len(count)):
            count[d] += count[d - 1]
        for i in range(n):  # in the current order: equal digits keep it (stable)
            d = (key[order[i]] >> shift) & digit_mask
            other[count[d]] = order[i]
            count[d] += 1
        order, other = other, order
        shift += _RADIX_BITS
    first = np.empty(n, np.bool_)
    first[0] = True
    for i in range(1, n):
        first[i] = key[order[i]] != key[order[i - 1]]
    return order, first, largest


@njit(cache=True, nogil=True)
def _pairwise_sum(values: np.ndarray, order: np.ndarray, lo: int, n: int, col: int) -> float:
    """NumPy's pairwise sum (`pairwise_sum_DOUBLE`: 8 partial sums up to 128 terms, halves at
    multiples of 8 above) of values[order[lo:lo + n], col], starting from -0.0 as NumPy does."""
    if n < 8:
        res = -0.0
        for i in range(n):
            res += values[order[lo + i], col]
        return res
    if n <= 128:
        r = np.empty(8)
        for j in range(8):
            r[j] = values[order[lo + j], col]
        i = 8
        while i < n - n % 8:
            for j in range(8):
                r[j] += values[order[lo + i + j], col]
            i += 8
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
        while i < n:
            res += values[order[lo + i], col]
            i += 1
        return res
    half = n // 2
    half -= half % 8
    return _pairwise_sum(values, order, lo, half, col) + _pairwise_sum(values, order, lo + half, n - half, col)


@njit(cache=True, nogil=True)
def run_means(values: np.ndarray, order: np.ndarray, first: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean of `values` (N, C) float64 over every run of the rows taken in `order` (N,), a run
    starting where `first` (N,) is True (first[0] must be): (means (M, C), index of each run's
    first row (M,), rows per run (M,)). Bitwise `np.add.reduceat(values[order], starts, axis=0) / counts` (a run's
    first row plus NumPy's pairwise sum of the others), without gathering the (N, C) rows."""
    n, c = values.shape
    starts = np.flatnonzero(first)
    m = len(starts)
    means = np.empty((m, c))
    heads = np.empty(m, np.int64)
    counts = np.empty(m, np.int64)
    rest = np.empty(c)
    for run in range(m):
        lo = starts[run]
        count = (starts[run + 1] if run + 1 < m else n) - lo
        heads[run] = order[lo]
        counts[run] = count
        if count <= 8:  # the common case, row by row: the rest summed in order from -0.0
            rest[:] = -0.0
            for i in range(lo + 1, lo + count):
                row = order[i]
                for j in range(c):
                    rest[j] += values[row, j]
        else:
            for j in range(c):
                rest[j] = _pairwise_sum(values, order, lo + 1, count - 1, j)
        for j in range(c):
            means[run, j] = (values[order[lo], j] + rest[j]) / count
    return means, heads, counts


@njit(cache=True, nogil=True)
def voxels_reached(
    voxel_keys: np.ndarray, centres: np.ndarray, cloud_keys: np.ndarray, points: np.ndarray,
    column_offsets: np.ndarray, radius: float,
) -> np.ndarray:
    """(Q,) whether a point of a cloud (sorted unique voxel `cloud_keys` (P,), one point each
    (P, 3)) lies within `radius` of the centre (Q, 3) of each voxel of the sorted unique
    `voxel_keys` (Q,). Only the 27 voxels around can hold one: `column_offsets` are the key
    offsets of the lowest voxel of each of the 9 columns, whose 3 voxels are consecutive keys.
    Searched from the smaller side. Distance sqrt((dx^2 + dy^2) + dz^2) of point - centre, NumPy's
    `linalg.norm(axis=1)` for 3-vectors, so the decisions are the NumPy expression's."""
    n_voxels, n_points = len(voxel_keys), len(cloud_keys)
    reached = np.zeros(n_voxels, np.bool_)
    if n_voxels == 0 or n_points == 0:
        return reached
    from_voxels = n_voxels <= n_points
    small, large = (voxel_keys, cloud_keys) if from_voxels else (cloud_keys, voxel_keys)
    for i in range(len(small)):
        for o in column_offsets:
            base = small[i] + o
            pos = np.searchsorted(large, base)
            for j in range(pos, min(pos + 3, len(large))):
                if large[j] > base + 2:
                    break
                v, p = (i, j) if from_voxels else (j, i)
                if reached[v]:
                    continue
                dx = points[p, 0] - centres[v, 0]
                dy = points[p, 1] - centres[v, 1]
                dz = points[p, 2] - centres[v, 2]
                if np.sqrt((dx * dx + dy * dy) + dz * dz) <= radius:
                    reached[v] = True
            if from_voxels and reached[i]:
                break
    return reached


@njit(cache=True, nogil=True)
def merge_sorted_rows(
    keys: np.ndarray, rows: np.ndarray, new_keys: np.ndarray, new_rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Sorted `keys` (N,) with their `rows` (N, C) and sorted `new_keys` (M,) with `new_rows`
    merged into one sorted array in one pass: np.insert at np.searchsorted(keys, new_keys) (a new
    key goes before equal old ones), without its index sort and copies."""
    n, m = len(keys), len(new_keys)
    out_keys = np.empty(n + m, keys.dtype)
    out_rows = np.empty((n + m, rows.shape[1]), rows.dtype)
    i = j = 0
    for k in range(n + m):
        if j < m and (i == n or new_keys[j] <= keys[i]):
            out_keys[k] = new_keys[j]
            out_rows[k] = new_rows[j]
            j += 1
        else:
            out_keys[k] = keys[i]
            out_rows[k] = rows[i]
            i += 1
    return out_keys, out_rows


@njit(cache=True, nogil=True)
def group_any_within(queries: np.ndarray, query_starts: np.ndarray, points: np.ndarray, point_starts: np.ndarray,
                     radius: float) -> np.ndarray:
    """(N,) whether some point of each query's group has squared distance < radius * radius from
    it, as cKDTree(points).query(queries, distance_upper_bound=radius)[0] < inf on groups moved
    too far apart to pair. Groups without points give False; a group with non-finite points is
    searched pair by pair (no grid); a non-finite query is within no finite radius.

    A query searches the cells that [q - reach, q + reach] overlaps along each axis, reach a hair
    above the radius; the columns (x, y) are found in a dense table (faster than the hash)."""
    n, dims = queries.shape
    out = np.zeros(n, np.bool_)
    r2 = radius * radius  # as cKDTree: the bound squared (a negative radius counts as positive)
    if not r2 > 0.0:  # 0 or NaN: nothing is strictly closer
        return out
    for g in range(len(query_starts) - 1):
        qa, qb = query_starts[g], query_starts[g + 1]
        a, b = point_starts[g], point_starts[g + 1]
        if qa == qb or a == b:
            continue
        size = 0.0
        extent = np.zeros(3)
        for ax in range(dims):
            size = max(size, np.abs(points[a:b, ax]).max())
            extent[ax] = points[a:b, ax].max() - points[a:b, ax].min()
        if r2 == np.inf or b - a <= _BRUTE_FORCE_MAX or not np.isfinite(extent.sum() + size):
            for i in range(qa, qb):
                for j in range(a, b):
                    if _dist2(queries, i, points, j) < r2:
                        out[i] = True
                        break
            continue
        # a point within the radius of q lies in [q - reach, q + reach] along each axis even after
        # rounding q +- reach (slack far above the rounding of coordinates up to size + radius),
        # and cell indices are monotone in the coordinate: the searched cells hold all such points
        reach = abs(radius) + _TOL * (size + abs(radius))
        cell = max(_CELL_PER_RADIUS * reach, extent.max() / 2.0**20)  # bounded cell indices
        while (np.floor(extent[0] / cell) + 1) * (np.floor(extent[1] / cell) + 1) > max(16 * (b - a), 1 << 16):
            cell *= 2.0  # a bounded dense column table
        lo, order, cells, shape, col_start, _, _ = _grid(points, a, b, cell)
        grid_points = points[a + order]
        z_of = cells[:, 2].copy()
        col_of = np.full((shape[0], shape[1]), -1, np.int64)
        for col in range(len(col_start) - 1):
            col_of[cells[col_start[col], 0], cells[col_start[col], 1]] = col
        first = np.zeros(3, np.int64)  # 2D: z cells 0 to 0
        last = np.zeros(3, np.int64)
        for i in range(qa, qb):
            outside = False
            for ax in range(dims):
                f0 = np.floor((queries[i, ax] - reach - lo[ax]) / cell)  # as _grid
                f1 = np.floor((queries[i, ax] + reach - lo[ax]) / cell)
                if not (f1 >= 0.0 and f0 < shape[ax]):  # no occupied cell in reach (or NaN)
                    outside = True
                    break
                first[ax] = int(max(f0, 0.0))
                last[ax] = int(min(f1, shape[ax] - 1.0))
            if outside:
                continue
            found = False
            for x in range(first[0], last[0] + 1):
                for y in range(first[1], last[1] + 1):
                    col = col_of[x, y]
                    if col < 0:
                        continue
                    e = col_start[col + 1]
                    q = _z_from(z_of, col_start[col], e, first[2])
                    while q < e and z_of[q] <= last[2]:
                        if _dist2(queries, i, grid_points, q) < r2:
                            found = True
                            break
                        q += 1
                    if found:
                        break
                if found:
                    break
            out[i] = found
    return out

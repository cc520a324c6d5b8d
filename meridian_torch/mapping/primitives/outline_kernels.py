"""Compiled (numba) kernels of the alpha-shape outlines of segments (`outline.alpha_shape_outline`):
the grid's cell means (`grid_means`), the band of cells near the border (`boundary_band`), the 2D
Delaunay triangulation (`delaunay`), the alpha complex (`alpha_kept_triangles`), its boundary
(`alpha_boundary_edges`), its walk into loops (`simple_loops`) and the pieces of the complex with
its holes filled (`filled_pieces`, which refuses outlines before GEOS would). As qhull, NumPy, OpenCV and Python code they took about
half of building an aerial patch, much of it in per-segment call overheads (a 60 m patch has ~75
segments); every kernel but `delaunay` computes bit for bit what that code computed (tests against
the plain definitions), and the maps named below are byte for byte the same. Also here: the convex
hull of a segment's points (`convex_hull`, for its diameter and a ground segment's area): qhull's
vertices, turns within the coordinates' rounding merged as qhull merges them; and a bound on the
smallest principal variance of a segment's points (`minor_variance_lower_bound`), which spares
most segments LAPACK's eigen-decomposition in the thin-line rule.

qhull (scipy.spatial.Delaunay) triangulates in any dimension through a lifted convex hull and
costs 4-9 us per point plus ~0.2 ms per call; an aerial 60 m patch triangulates ~75 outlines
(median 65 points, up to several thousand), which was about a third of building a patch. This
is the sweep-hull algorithm (as in Mapbox's delaunator): points are added in order of distance
from a seed triangle's circumcentre, each joined to the hull edges it sees, and every new edge
is made locally Delaunay by flips (Lawson), in plain float64 predicates: about 12x less time than
qhull on the outlines of a 300 m world.

Points in general position have one Delaunay triangulation, and on random points this gives
qhull's triangles and neighbours (another order; tested). The outline's input is a lattice
jittered by 1e-6 of a cell: here the flips resolve every near-cocircular quad by the jitter,
while qhull merges such quads within its precision and splits them either way (4742 of 5931
triangulations of a 300 m world differed in such quads). The two triangles of a cocircular quad
share its circumcircle, so the alpha test keeps or drops both whichever diagonal is taken, and
the outlines are the same unless that circumradius equals 1/alpha to rounding: the maps of the
KITTI 09 and 00 worlds (609 and 594 patches) and of SpaceNet's sample GeoTIFF (196) are byte for
byte those of qhull's triangulation, and a test compares outlines of random segment shapes. When the input is
degenerate (fewer than 3 distinct points, all collinear, not finite) or a point cannot be placed
(a duplicate), `delaunay` reports failure and the caller asks qhull, which decides those cases as
before.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from meridian_torch.core.dense_ranks import dense_ranks

__all__ = [
    "alpha_boundary_edges", "alpha_kept_triangles", "boundary_band", "convex_hull", "delaunay", "filled_pieces",
    "grid_means", "minor_variance_lower_bound", "simple_loops",
]


@njit(cache=True, nogil=True, inline="always")
def _cross(xy: np.ndarray, a: int, b: int, c: int) -> float:
    """Twice the signed area of (a, b, c): > 0 when counter-clockwise."""
    return (xy[b, 0] - xy[a, 0]) * (xy[c, 1] - xy[a, 1]) - (xy[b, 1] - xy[a, 1]) * (xy[c, 0] - xy[a, 0])


@njit(cache=True, nogil=True, inline="always")
def _in_circle(xy: np.ndarray, a: int, b: int, c: int, d: int) -> bool:
    """Whether d lies strictly inside the circumcircle of the counter-clockwise (a, b, c)."""
    adx, ady = xy[a, 0] - xy[d, 0], xy[a, 1] - xy[d, 1]
    bdx, bdy = xy[b, 0] - xy[d, 0], xy[b, 1] - xy[d, 1]
    cdx, cdy = xy[c, 0] - xy[d, 0], xy[c, 1] - xy[d, 1]
    a2, b2, c2 = adx * adx + ady * ady, bdx * bdx + bdy * bdy, cdx * cdx + cdy * cdy
    return a2 * (bdx * cdy - cdx * bdy) - b2 * (adx * cdy - cdx * ady) + c2 * (adx * bdy - bdx * ady) > 0.0


@njit(cache=True, nogil=True, inline="always")
def _circumcentre_offset(xy: np.ndarray, a: int, b: int, c: int) -> tuple[float, float]:
    """Circumcentre of (a, b, c) relative to a; (inf, inf) when they are collinear."""
    dx, dy = xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1]
    ex, ey = xy[c, 0] - xy[a, 0], xy[c, 1] - xy[a, 1]
    bl, cl, d = dx * dx + dy * dy, ex * ex + ey * ey, dx * ey - dy * ex
    if d == 0.0:
        return math.inf, math.inf
    return (ey * bl - dy * cl) * 0.5 / d, (dx * cl - ex * bl) * 0.5 / d


@njit(cache=True, nogil=True, inline="always")
def _circumradius2(xy: np.ndarray, a: int, b: int, c: int) -> float:
    """Squared circumradius of (a, b, c); inf when they are collinear."""
    x, y = _circumcentre_offset(xy, a, b, c)
    r2 = x * x + y * y
    return r2 if math.isfinite(r2) else math.inf


@njit(cache=True, nogil=True, inline="always")
def _link(opposite: np.ndarray, a: int, b: int) -> None:
    opposite[a] = b
    if b >= 0:
        opposite[b] = a


@njit(cache=True, nogil=True, inline="always")
def _hash_key(xy: np.ndarray, v: int, cx: float, cy: float, size: int) -> int:
    """Bucket of v's direction from (cx, cy): a pseudo-angle, monotone in the angle, in [0, 1)."""
    dx, dy = xy[v, 0] - cx, xy[v, 1] - cy
    if dx == 0.0 and dy == 0.0:
        return 0
    p = dx / (abs(dx) + abs(dy))
    angle = (3.0 - p if dy > 0.0 else 1.0 + p) / 4.0
    return int(math.floor(angle * size)) % size


@njit(cache=True, nogil=True)
def _legalize(xy, corner, opposite, hull_edge, stack, start):
    """Flip edges until all that `start` leads to are locally Delaunay. Halfedge h = 3 t + k runs
    from corner[h] to the next corner of triangle t; the apex opposite a pushed edge is always the
    point being inserted. Returns False if the stack overflowed."""
    top = 0
    stack[top] = start
    top += 1
    while top > 0:
        top -= 1
        a = stack[top]
        b = opposite[a]
        if b < 0:
            continue
        t1, t2, ka, kb = a - a % 3, b - b % 3, a % 3, b % 3
        a_next, a_prev = t1 + (ka + 1) % 3, t1 + (ka + 2) % 3
        b_next, b_prev = t2 + (kb + 1) % 3, t2 + (kb + 2) % 3
        a0, a1, p, q = corner[a], corner[a_next], corner[a_prev], corner[b_prev]
        if not _in_circle(xy, a0, a1, p, q):
            continue
        # The quad a0, q, a1, p (counter-clockwise) takes the diagonal p-q:
        # t1 = (p, a0, q), t2 = (q, a1, p), the outer edges keeping their twins.
        out_a1p, out_pa0, out_a0q, out_qa1 = opposite[a_next], opposite[a_prev], opposite[b_next], opposite[b_prev]
        corner[t1], corner[t1 + 1], corner[t1 + 2] = p, a0, q
        corner[t2], corner[t2 + 1], corner[t2 + 2] = q, a1, p
        _link(opposite, t1, out_pa0)
        _link(opposite, t1 + 1, out_a0q)
        _link(opposite, t1 + 2, t2 + 2)
        _link(opposite, t2, out_qa1)
        _link(opposite, t2 + 1, out_a1p)
        # An outer edge on the hull moved: its hull vertex must point at its new place.
        for h in (t1, t1 + 1, t2, t2 + 1):
            if opposite[h] < 0:
                hull_edge[corner[h]] = h
        if top + 2 > len(stack):
            return False
        stack[top] = t1 + 1  # a0 -> q, opposite p
        stack[top + 1] = t2  # q -> a1, opposite p
        top += 2
    return True


@njit(cache=True, nogil=True)
def delaunay(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Delaunay triangulation of the points xy (n, 2) float64.

    Returns (triangles (T, 3) int64 counter-clockwise, neighbours (T, 3) int64: the triangle
    across the edge opposite each corner, -1 on the hull (scipy's `neighbors`), ok). ok is False,
    with empty arrays, when the points are degenerate or not finite, or one could not be placed (see
    the module).
    """
    n = xy.shape[0]
    empty = np.zeros((0, 3), np.int64)
    if n < 3 or not np.isfinite(xy).all():
        return empty, empty, False
    # Seed: the point nearest the bounding box's centre, its nearest point, and the point making
    # the smallest circumcircle with them.
    cx = 0.5 * (xy[:, 0].min() + xy[:, 0].max())
    cy = 0.5 * (xy[:, 1].min() + xy[:, 1].max())
    i0, best = 0, math.inf
    for i in range(n):
        d = (xy[i, 0] - cx) ** 2 + (xy[i, 1] - cy) ** 2
        if d < best:
            i0, best = i, d
    i1, best = -1, math.inf
    for i in range(n):
        d = (xy[i, 0] - xy[i0, 0]) ** 2 + (xy[i, 1] - xy[i0, 1]) ** 2
        if i != i0 and 0.0 < d < best:
            i1, best = i, d
    if i1 < 0:
        return empty, empty, False
    i2, best = -1, math.inf
    for i in range(n):
        if i != i0 and i != i1:
            r2 = _circumradius2(xy, i0, i1, i)
            if r2 < best:
                i2, best = i, r2
    if i2 < 0:  # every point on one line
        return empty, empty, False
    if _cross(xy, i0, i1, i2) < 0.0:
        i1, i2 = i2, i1
    # Circumcentre of the seed; the points are added by distance from it.
    ox, oy = _circumcentre_offset(xy, i0, i1, i2)
    cx, cy = xy[i0, 0] + ox, xy[i0, 1] + oy
    dist = np.empty(n)
    for i in range(n):
        dist[i] = (xy[i, 0] - cx) ** 2 + (xy[i, 1] - cy) ** 2
    order = np.argsort(dist)

    max_triangles = 2 * n - 5
    corner = np.empty(3 * max_triangles, np.int64)
    opposite = np.full(3 * max_triangles, -1, np.int64)
    stack = np.empty(3 * max_triangles + 8, np.int64)
    # The hull, counter-clockwise: hull_next / hull_prev, and hull_edge[v] = the halfedge v ->
    # hull_next[v] of the triangle inside it; on_hull marks its vertices.
    hull_next = np.full(n, -1, np.int64)
    hull_prev = np.full(n, -1, np.int64)
    hull_edge = np.full(n, -1, np.int64)
    on_hull = np.zeros(n, np.bool_)
    hash_size = max(1, int(math.ceil(math.sqrt(n))))
    hull_hash = np.full(hash_size, -1, np.int64)

    corner[0], corner[1], corner[2] = i0, i1, i2
    n_triangles = 1
    hull_next[i0], hull_next[i1], hull_next[i2] = i1, i2, i0
    hull_prev[i0], hull_prev[i1], hull_prev[i2] = i2, i0, i1
    hull_edge[i0], hull_edge[i1], hull_edge[i2] = 0, 1, 2
    for v in (i0, i1, i2):
        on_hull[v] = True
        hull_hash[_hash_key(xy, v, cx, cy, hash_size)] = v

    for k in range(n):
        p = order[k]
        if p == i0 or p == i1 or p == i2:
            continue
        # A hull vertex near p's direction, then forward to the first hull edge p sees.
        key = _hash_key(xy, p, cx, cy, hash_size)
        start = -1
        for j in range(hash_size):
            v = hull_hash[(key + j) % hash_size]
            if v >= 0 and on_hull[v]:
                start = v
                break
        if start < 0:
            return empty, empty, False
        start = hull_prev[start]
        e = start
        while _cross(xy, e, hull_next[e], p) >= 0.0:
            e = hull_next[e]
            if e == start:  # sees no edge: a duplicate, or rounding
                return empty, empty, False
        # Triangle (e, p, q) on the edge e -> q.
        q = hull_next[e]
        t = 3 * n_triangles
        n_triangles += 1
        corner[t], corner[t + 1], corner[t + 2] = e, p, q
        _link(opposite, t + 2, hull_edge[e])
        hull_edge[e], hull_edge[p] = t, t + 1
        on_hull[p] = True
        if not _legalize(xy, corner, opposite, hull_edge, stack, t + 2):
            return empty, empty, False
        # Forward: the next hull edges n -> w that p sees.
        nv = q
        while _cross(xy, nv, hull_next[nv], p) < 0.0:
            w = hull_next[nv]
            t = 3 * n_triangles
            n_triangles += 1
            corner[t], corner[t + 1], corner[t + 2] = nv, p, w
            _link(opposite, t, hull_edge[p])
            _link(opposite, t + 2, hull_edge[nv])
            hull_edge[p] = t + 1
            on_hull[nv] = False
            if not _legalize(xy, corner, opposite, hull_edge, stack, t + 2):
                return empty, empty, False
            nv = w
            if nv == e:  # p saw the whole hull: only rounding can do that
                return empty, empty, False
        # Backward: the previous hull edges v -> e that p sees.
        while _cross(xy, hull_prev[e], e, p) < 0.0:
            v = hull_prev[e]
            if v == nv:
                return empty, empty, False
            t = 3 * n_triangles
            n_triangles += 1
            corner[t], corner[t + 1], corner[t + 2] = v, p, e
            _link(opposite, t + 1, hull_edge[e])
            _link(opposite, t + 2, hull_edge[v])
            hull_edge[v] = t
            on_hull[e] = False
            if not _legalize(xy, corner, opposite, hull_edge, stack, t + 2):
                return empty, empty, False
            e = v
        hull_next[e], hull_prev[p] = p, e
        hull_next[p], hull_prev[nv] = nv, p
        hull_hash[_hash_key(xy, p, cx, cy, hash_size)] = p
        hull_hash[_hash_key(xy, e, cx, cy, hash_size)] = e

    triangles = corner[: 3 * n_triangles].reshape(n_triangles, 3).copy()
    neighbours = np.empty((n_triangles, 3), np.int64)
    for t in range(n_triangles):
        for c in range(3):
            h = opposite[3 * t + (c + 1) % 3]  # the edge opposite corner c
            neighbours[t, c] = h // 3 if h >= 0 else -1
    return triangles, neighbours, True


@njit(cache=True, nogil=True)
def simple_loops(edges: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """Closed vertex loops of an edge set (E, 2) int64 of vertex ids below `n_points` in which every
    vertex has exactly two edges: (the loops' vertex ids one after another, (L + 1,) loop starts,
    True), else (empty, empty, False).

    Loops come in the order of their smallest vertex; each starts there and first steps to the
    other end of the first edge (in `edges` order) holding it.
    """
    empty = np.zeros(0, np.int64)
    label = np.full(n_points, -1, np.int64)  # vertices relabelled 0..V-1 in increasing id order
    for e in range(edges.shape[0]):
        label[edges[e, 0]] = 0
        label[edges[e, 1]] = 0
    n_vertices = 0
    for v in range(n_points):
        if label[v] == 0:
            label[v] = n_vertices
            n_vertices += 1
    if edges.shape[0] != n_vertices:
        return empty, empty, False
    vertex = np.empty(n_vertices, np.int64)
    for v in range(n_points):
        if label[v] >= 0:
            vertex[label[v]] = v
    # Each vertex's two neighbours in edge order.
    neighbour = np.empty((n_vertices, 2), np.int64)
    degree = np.zeros(n_vertices, np.int64)
    for e in range(edges.shape[0]):
        for side in range(2):
            x, other = label[edges[e, side]], label[edges[e, 1 - side]]
            if degree[x] == 2:
                return empty, empty, False
            neighbour[x, degree[x]] = other
            degree[x] += 1
    if (degree != 2).any():
        return empty, empty, False
    visited = np.zeros(n_vertices, np.bool_)
    loops = np.empty(n_vertices, np.int64)
    starts = np.empty(n_vertices + 1, np.int64)
    n_loops, n = 0, 0
    for start in range(n_vertices):
        if visited[start]:
            continue
        starts[n_loops] = n
        n_loops += 1
        loops[n] = vertex[start]
        n += 1
        visited[start] = True
        prev, cur = start, neighbour[start, 0]
        while cur != start:
            loops[n] = vertex[cur]
            n += 1
            visited[cur] = True
            a, b = neighbour[cur, 0], neighbour[cur, 1]
            prev, cur = cur, (a if a != prev else b)
    starts[n_loops] = n
    return loops, starts[: n_loops + 1].copy(), True


@njit(cache=True, nogil=True)
def grid_means(points: np.ndarray, grid_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean point and integer cell of every occupied cell of the global lattice floor(p / grid_m),
    cells in (x, y) lexicographic order; each mean sums its points in input order from 0.0 and
    divides by their count (NumPy's bincount means, bit for bit)."""
    n = points.shape[0]
    cells = np.empty((n, 2), np.int64)
    for i in range(n):
        cells[i, 0] = np.int64(math.floor(points[i, 0] / grid_m))
        cells[i, 1] = np.int64(math.floor(points[i, 1] / grid_m))
    lo_x, lo_y = cells[:, 0].min(), cells[:, 1].min()
    width = cells[:, 1].max() - lo_y + 1
    slot, n_cells = dense_ranks((cells[:, 0] - lo_x) * width + (cells[:, 1] - lo_y))
    sums = np.zeros((n_cells, 2))
    counts = np.zeros(n_cells, np.int64)
    out_cells = np.empty((n_cells, 2), np.int64)
    for i in range(n):
        s = slot[i]
        sums[s, 0] += points[i, 0]
        sums[s, 1] += points[i, 1]
        counts[s] += 1
        out_cells[s, 0], out_cells[s, 1] = cells[i, 0], cells[i, 1]
    for s in range(n_cells):
        sums[s, 0] /= counts[s]
        sums[s, 1] /= counts[s]
    return sums, out_cells


@njit(cache=True, nogil=True)
def _row_runs(image: np.ndarray, rightward: bool) -> np.ndarray:
    """Length of the run of 1s of a 0/1 image along its row ending at each pixel, counted from the
    left (`rightward`) or from the right; 0 on 0 pixels."""
    rows, cols = image.shape
    run = np.zeros((rows, cols), np.int64)
    for y in range(rows):
        count = 0
        for k in range(cols):
            x = k if rightward else cols - 1 - k
            count = count + 1 if image[y, x] != 0 else 0
            run[y, x] = count
    return run


@njit(cache=True, nogil=True)
def _square_morphology(image: np.ndarray, dilate: bool) -> np.ndarray:
    """Binary dilation (max) or erosion (min) of a 0/1 image by the 3 x 3 square, one axis at a time
    (the square is the product of two 3-pixel lines); pixels outside the image count as 0 (OpenCV's
    constant border of value 0)."""
    rows, cols = image.shape
    out = image
    for axis in range(2):
        src, out = out, np.empty_like(image)
        for y in range(rows):
            for x in range(cols):
                hit = not dilate
                for d in range(-1, 2):
                    yy, xx = (y + d, x) if axis == 0 else (y, x + d)
                    value = src[yy, xx] if 0 <= yy < rows and 0 <= xx < cols else 0
                    if dilate and value != 0:
                        hit = True
                    if not dilate and value == 0:
                        hit = False
                out[y, x] = 1 if hit else 0
    return out


@njit(cache=True, nogil=True)
def _disc_erosion(image: np.ndarray, radius: float) -> np.ndarray:
    """Binary erosion of a 0/1 image by the disc of offsets dy^2 + dx^2 <= radius^2, outside the
    image counting as 0: a pixel stays iff for each row offset dy the row y + dy exists and its run
    of 1s through x reaches the disc's half-width at dy on both sides."""
    rows, cols = image.shape
    r = int(math.floor(radius))
    half = np.zeros(2 * r + 1, np.int64)
    for dy in range(-r, r + 1):
        w = 0
        while (w + 1) * (w + 1) + dy * dy <= radius * radius:
            w += 1
        half[dy + r] = w
    left, right = _row_runs(image, True), _row_runs(image, False)
    out = np.zeros((rows, cols), np.uint8)
    for y in range(rows):
        for x in range(cols):
            deep = True
            for dy in range(-r, r + 1):
                yy = y + dy
                if yy < 0 or yy >= rows or left[yy, x] <= half[dy + r] or right[yy, x] <= half[dy + r]:
                    deep = False
                    break
            out[y, x] = 1 if deep else 0
    return out


@njit(cache=True, nogil=True)
def boundary_band(cells: np.ndarray, band_cells: float) -> np.ndarray:
    """Mask of the cells (n, 2) at most `band_cells` from an empty cell (Euclidean, in cells).

    Holes narrower than 3 cells are closed first: pixel lattices coarser than the grid leave
    empty cell rows inside a segment (0.3 m pixels on 0.25 m cells), which would otherwise put
    every point near an empty cell. A cell is farther than `band_cells` from every empty cell iff
    the disc of that radius around it is all occupied, so the band is what an erosion by that
    disc removes. Outside the grid counts as empty, as in scipy's closing; the 2-cell empty margin
    keeps that from reaching an occupied cell that the margin's own empty cells would not.
    """
    lo_x, lo_y = cells[:, 0].min() - 2, cells[:, 1].min() - 2
    occupied = np.zeros((cells[:, 0].max() - lo_x + 3, cells[:, 1].max() - lo_y + 3), np.uint8)
    for i in range(cells.shape[0]):
        occupied[cells[i, 0] - lo_x, cells[i, 1] - lo_y] = 1
    closed = _square_morphology(_square_morphology(occupied, True), False)
    deep = _disc_erosion(closed, band_cells)
    band = np.empty(cells.shape[0], np.bool_)
    for i in range(cells.shape[0]):
        band[i] = deep[cells[i, 0] - lo_x, cells[i, 1] - lo_y] == 0
    return band


@njit(cache=True, nogil=True)
def alpha_kept_triangles(pts: np.ndarray, simplices: np.ndarray, radius: float) -> np.ndarray:
    """Mask of the triangles of the alpha complex: circumradius < radius (abc < 2 r |twice the
    area|, without a division, so slivers stay out)."""
    n_tri = simplices.shape[0]
    keep = np.zeros(n_tri, np.bool_)
    two_r = radius * 2.0
    for t in range(n_tri):
        product = 1.0  # (a b) c, as NumPy's prod; 1.0 * a is a
        for k in range(3):
            a, b = simplices[t, k], simplices[t, (k + 1) % 3]
            dx, dy = pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1]
            product *= np.sqrt(dx * dx + dy * dy)
        a, b, c = simplices[t, 0], simplices[t, 1], simplices[t, 2]
        ux, uy = pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1]
        vx, vy = pts[c, 0] - pts[a, 0], pts[c, 1] - pts[a, 1]
        keep[t] = product < two_r * abs(ux * vy - uy * vx)
    return keep


@njit(cache=True, nogil=True)
def alpha_boundary_edges(simplices: np.ndarray, neighbors: np.ndarray, keep: np.ndarray, n_points: int) -> np.ndarray:
    """The boundary of the kept triangles (`alpha_kept_triangles`): edges (E, 2) that lie in exactly
    one kept triangle, each as (smaller, larger) vertex id, sorted; (0, 2) if no triangle is kept."""
    n_tri = simplices.shape[0]
    n_edges = 0
    ends = np.empty((3 * n_tri, 2), np.int64)
    for t in range(n_tri):
        if not keep[t]:
            continue
        for k in range(3):
            other = neighbors[t, k]
            if other < 0 or not keep[other]:
                a, b = simplices[t, (k + 1) % 3], simplices[t, (k + 2) % 3]
                ends[n_edges, 0], ends[n_edges, 1] = min(a, b), max(a, b)
                n_edges += 1
    key = np.empty(n_edges, np.int64)
    for e in range(n_edges):
        key[e] = ends[e, 0] * n_points + ends[e, 1]
    return ends[np.argsort(key)]


@njit(cache=True, nogil=True)
def filled_pieces(neighbors: np.ndarray, keep: np.ndarray) -> int:
    """How many pieces the kept triangles make once their holes are filled: the triangles that are
    kept or cut off from the triangulation's outside by kept ones, in groups joined across edges.
    Pieces meet at most at a vertex, so with 2 or more their union is not one polygon."""
    n_tri = keep.shape[0]
    outside = np.zeros(n_tri, np.bool_)  # dropped triangles reachable from the hull's exterior
    stack = np.empty(n_tri, np.int64)
    top = 0
    for t in range(n_tri):
        if not keep[t] and (neighbors[t, 0] < 0 or neighbors[t, 1] < 0 or neighbors[t, 2] < 0):
            outside[t] = True
            stack[top] = t
            top += 1
    while top > 0:
        top -= 1
        t = stack[top]
        for k in range(3):
            other = neighbors[t, k]
            if other >= 0 and not keep[other] and not outside[other]:
                outside[other] = True
                stack[top] = other
                top += 1
    seen = outside.copy()
    pieces = 0
    for start in range(n_tri):
        if seen[start]:
            continue
        pieces += 1
        seen[start] = True
        stack[0] = start
        top = 1
        while top > 0:
            top -= 1
            t = stack[top]
            for k in range(3):
                other = neighbors[t, k]
                if other >= 0 and not seen[other]:
                    seen[other] = True
                    stack[top] = other
                    top += 1
    return pieces


@njit(cache=True, nogil=True, inline="always")
def _turns_left(xy: np.ndarray, a: int, b: int, c: int, tolerance: float) -> bool:
    """Whether a -> b -> c turns counter-clockwise by more than the rounding of the coordinates'
    differences can (`tolerance`: their rounding error per metre of the sides' lengths)."""
    dx1, dy1 = xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1]
    dx2, dy2 = xy[c, 0] - xy[b, 0], xy[c, 1] - xy[b, 1]
    return dx1 * dy2 - dy1 * dx2 > tolerance * (abs(dx1) + abs(dy1) + abs(dx2) + abs(dy2))


@njit(cache=True, nogil=True)
def convex_hull(xy: np.ndarray) -> np.ndarray:
    """Indices of the convex hull's corners of points (n, 2), counter-clockwise (Andrew's monotone
    chain). Points on a hull side are not corners, nor are turns within the rounding of the
    coordinates (pixel centres of a straight side far from the origin), which qhull merges too;
    fewer than 3 corners when the points are collinear so, or fewer than 3 distinct. qhull
    (scipy's ConvexHull) took 40-650 us per segment, mostly per call."""
    n = xy.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    tolerance = 16.0 * 2.220446049250313e-16 * np.abs(xy).max()
    order = np.argsort(xy[:, 1], kind="mergesort")
    order = order[np.argsort(xy[order, 0], kind="mergesort")]  # by x, then y
    hull = np.empty(2 * n + 1, np.int64)
    k = 0
    for i in range(n):  # lower chain
        while k >= 2 and not _turns_left(xy, hull[k - 2], hull[k - 1], order[i], tolerance):
            k -= 1
        hull[k] = order[i]
        k += 1
    lower = k + 1
    for i in range(n - 2, -1, -1):  # upper chain
        while k >= lower and not _turns_left(xy, hull[k - 2], hull[k - 1], order[i], tolerance):
            k -= 1
        hull[k] = order[i]
        k += 1
    return hull[: max(k - 1, 0)].copy()


@njit(cache=True, nogil=True)
def minor_variance_lower_bound(points: np.ndarray) -> float:
    """A lower bound on the smallest eigenvalue of the points' (n, 2) population covariance, n >= 1:
    the closed-form 2 x 2 eigenvalue less a margin far above its rounding (1e-9 of the trace; the
    sums' and the square root's rounding is ~n eps of it), so a bound above a threshold proves the
    exact eigenvalue is too."""
    n = points.shape[0]
    mx, my = 0.0, 0.0
    for i in range(n):
        mx += points[i, 0]
        my += points[i, 1]
    mx /= n
    my /= n
    sxx, sxy, syy = 0.0, 0.0, 0.0
    for i in range(n):
        dx, dy = points[i, 0] - mx, points[i, 1] - my
        sxx += dx * dx
        sxy += dx * dy
        syy += dy * dy
    sxx /= n
    sxy /= n
    syy /= n
    half_gap = 0.5 * (sxx - syy)
    trace = sxx + syy
    return 0.5 * trace - math.sqrt(half_gap * half_gap + sxy * sxy) - 1e-9 * trace

"""Segment → primitive conversion: outlines, point/line classification and line fusion.

A segment is a 2D point set in metres (aerial: world centres of its mask pixels; ground:
flattened 3D points) with one semantic descriptor. Following the paper (section III-A) and the
reference implementation, each segment is classified in this order:

1. outline: alpha shape of the points on a 0.25 m grid (Delaunay triangles with circumradius
   < 1/alpha, boundary edges polygonized and unioned); a result other than one polygon means
   no outline;
2. area below `min_area_m2`: dropped;
3. compact (small area and diameter): one point at the centre (mean of the points);
4. thin (minor PCA variance below a threshold): one line between the extreme projections;
5. roughly circular and small: one point at the fitted circle centre;
6. otherwise every outline edge becomes a line (after Douglas-Peucker simplification of the
   outline by `outline_simplify_m`, if set).
Primitives outside the border box (shrunk by `border_margin_m`) are not emitted; a point whose
centre is outside drops its whole segment. All lines are then fused into coarse lines.

Departures from the reference, all deliberate:
- grid downsampling keeps the mean of each cell of one global lattice (reference: the first
  point found), so the result does not depend on point order;
- only the grid points within 3 cells of an empty cell enter the Delaunay triangulation (see
  BAND_CELLS): the union of the polygonized faces fills every hole, so deeper points do not
  change the outline; they only cost time (a 2000 m^2 segment has ~32 000 grid points, ~2 000
  in the band);
- the thin-line rule needs only the raw points, so it also applies when the alpha shape fails
  (collinear grid points, several polygons), where the reference drops the segment: an
  axis-aligned bar one grid cell wide would otherwise vanish or not depending on grid alignment;
- the short-line angle relaxation is angle * short / length (reference: angle / length, equal at
  the 1 m default), and angles are compared as angles (reference: |sin| against radians);
- line fusion is a deterministic sequence of sweeps; see `fuse_lines`;
- `outline_simplify_m` (default 0.05 m; 0 = reference) simplifies the outline by Douglas-Peucker
  before its edges become lines, each run of edges inside the border box separately (see
  `_simplified_outline_edges`). At 0.05 m, 10x below the 0.5 m merge offset, it drops the lattice
  vertices of straight sides: ~1.9x fewer edges to fuse on aerial patches, equal line recall and
  slightly higher precision (scripts/eval_primitives.py, sim-tiny and kitti0); 0.1 m and more
  lose recall.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import shapely
import torch
from scipy import ndimage
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree

from meridian_torch.config.mapping import PrimitiveConfig
from meridian_torch.types import LineKind, PrimitiveSet

__all__ = [
    "segments_to_primitives",
    "alpha_shape_outline",
    "fit_circle",
    "fuse_lines",
    "mergeable_line_pairs",
]

PARALLEL_SIN = 1e-3  # |sin| below this: the parallel-lines branch of the merge test (reference)
SHORT_LINE_MAX_ANGLE = np.pi / 4  # cap of the relaxed angle tolerance of short lines (reference)
COST_BIN = 0.02  # merge priority is |sin angle| in bins of this width; ties broken pseudo-randomly
# Only grid points at most this many cells from an empty cell are triangulated. A triangle with
# an empty circumcircle wider than a cell has its vertices next to empty cells, so the triangles
# along the exterior are unchanged; deeper points only add interior faces that the union fills.
# 2 cells already matched the full triangulation on 240 random shapes (with holes and notches).
BAND_CELLS = 3.0
# Below this many grid points the band is not worth its cost (closing, distance transform):
# all points are triangulated, which gives the same outline (see BAND_CELLS).
BAND_MIN_POINTS = 400
SEMANTIC_CHUNK = 16384  # pairs per descriptor dot-product chunk (bounds memory for D = 1024)

BorderBox = tuple[float, float, float, float]


# ----------------------------------------------------------------------------------- outline


def _grid_downsample(points: np.ndarray, grid_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean point and integer cell of every occupied cell of the global lattice floor(p / grid)."""
    cells = np.floor(points / grid_m).astype(np.int64)
    lo = cells.min(axis=0)
    width = int(cells[:, 1].max() - lo[1]) + 1
    key = (cells[:, 0] - lo[0]) * width + (cells[:, 1] - lo[1])  # 1D keys: far faster to sort
    size = int(cells[:, 0].max() - lo[0] + 1) * width
    if size <= 8 * len(points) + 65536:  # a dense table of the bounding box: no sort needed
        counts = np.bincount(key, minlength=size)
        uniq = np.flatnonzero(counts)
        sums = [np.bincount(key, points[:, k], minlength=size)[uniq] for k in range(2)]
        means = np.stack(sums, axis=1) / counts[uniq, None]
    else:
        uniq, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        means = np.stack([np.bincount(inverse, points[:, k]) for k in range(2)], axis=1) / counts[:, None]
    return means, np.stack([uniq // width + lo[0], uniq % width + lo[1]], axis=1)


_JITTER = np.zeros((0, 2))


def _jitter(n: int) -> np.ndarray:
    """Rows 0..n-1 of default_rng(0).uniform(-1e-6, 1e-6, (N, 2)), a prefix of any longer draw; cached."""
    global _JITTER
    if len(_JITTER) < n:
        _JITTER = np.random.default_rng(0).uniform(-1e-6, 1e-6, (max(n, 2 * len(_JITTER), 4096), 2))
        _JITTER.setflags(write=False)
    return _JITTER[:n]


def _boundary_band(cells: np.ndarray, band_cells: float) -> np.ndarray:
    """Mask of the cells at most `band_cells` from an empty cell (Euclidean, in cells).

    Holes narrower than 3 cells are closed first: pixel lattices coarser than the grid leave
    empty cell rows inside a segment (0.3 m pixels on 0.25 m cells), which would otherwise put
    every point near an empty cell.
    """
    lo = cells.min(axis=0) - 2
    shape = tuple(cells.max(axis=0) - lo + 3)
    occupied = np.zeros(shape, dtype=bool)
    idx = cells - lo
    occupied[idx[:, 0], idx[:, 1]] = True
    occupied = ndimage.binary_closing(occupied, structure=np.ones((3, 3), dtype=bool))
    depth = ndimage.distance_transform_edt(occupied)
    return depth[idx[:, 0], idx[:, 1]] <= band_cells


def alpha_shape_outline(
    points: np.ndarray, alpha: float = 1.0, grid_m: float = 0.25, max_points: int | None = None
) -> np.ndarray | None:
    """Outline of a 2D point set by an alpha shape on a grid, or None.

    Points are downsampled to one mean point per `grid_m` cell (the cell doubles while more than
    `max_points` remain), Delaunay-triangulated, triangles with circumradius < 1/alpha kept, and
    the boundary edges of the kept triangles polygonized and unioned. Returns the exterior ring's
    K distinct vertices (K, 2), counter-clockwise, implicitly closed (vertex K-1 connects to
    vertex 0); None if the points are degenerate or the union is not a single polygon.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(points) < 3:
        return None
    pts, cells = _grid_downsample(points, grid_m)
    while max_points is not None and len(pts) > max_points:
        grid_m *= 2.0
        pts, cells = _grid_downsample(points, grid_m)
    if len(pts) < 3:
        return None
    radius = 1.0 / alpha
    if len(pts) > BAND_MIN_POINTS:
        pts = pts[_boundary_band(cells, BAND_CELLS)]
    # A deterministic jitter far below the grid breaks the co-circular quads of lattice input,
    # which make qhull several times slower; the coordinates used below stay unjittered.
    try:
        tri_obj = Delaunay(pts + _jitter(len(pts)) * grid_m)
    except (QhullError, ValueError):
        return None
    simplices, neighbors = tri_obj.simplices, tri_obj.neighbors
    tri = pts[simplices]  # (T, 3, 2)
    side = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=-1)  # (T, 3)
    u, v = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    twice_area = np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
    # circumradius R = abc / (4 area); written without division to keep slivers (area 0) out
    keep = side.prod(axis=1) < radius * 2.0 * twice_area
    if not keep.any():
        return None
    # Boundary edges: the edges of kept triangles whose neighbour across (opposite vertex k) is
    # missing or not kept, i.e. the edges in exactly one kept triangle; sorted by vertex pair.
    kept = np.flatnonzero(keep)
    nb = neighbors[kept]
    open_side = (nb < 0) | ~keep[np.maximum(nb, 0)]
    t_idx, k_idx = np.nonzero(open_side)
    s_kept = simplices[kept]
    ends = np.stack([s_kept[t_idx, (k_idx + 1) % 3], s_kept[t_idx, (k_idx + 2) % 3]], axis=1)
    if len(ends) < 3:
        return None
    ends.sort(axis=1)
    edges = ends[np.argsort(ends[:, 0] * len(pts) + ends[:, 1])]
    loops = _simple_loops(edges)
    if loops is None:  # a vertex shared by several boundary loops: let GEOS sort it out
        shape = shapely.union_all(shapely.get_parts(shapely.polygonize(shapely.linestrings(pts[edges]))))
        if not isinstance(shape, shapely.Polygon) or shape.is_empty:
            return None
        ring = shapely.get_coordinates(shape.exterior)[:-1]
    else:
        # Vertex-disjoint loops: union of the faces (holes filled) is one polygon iff the
        # largest loop encloses all others.
        rings = [pts[loop] for loop in loops]
        ring = rings[int(np.argmax([abs(_signed_area(r)) for r in rings]))]
        others = np.array([r[0] for r in rings if r is not ring]).reshape(-1, 2)
        if len(others) and not shapely.contains_xy(shapely.Polygon(ring), others[:, 0], others[:, 1]).all():
            return None
    if _signed_area(ring) < 0:
        ring = ring[::-1]
    return np.ascontiguousarray(ring)


def _simple_loops(edges: np.ndarray) -> list[np.ndarray] | None:
    """Closed vertex loops of an edge set (E, 2) in which every vertex has two edges, else None.

    Each loop starts at its smallest vertex and first steps to the other end of the first edge
    (in `edges` order) holding it.
    """
    verts, inverse = np.unique(edges, return_inverse=True)  # vertices relabelled 0..V-1
    v = inverse.ravel()
    if len(v) != 2 * len(verts) or (np.bincount(v) != 2).any():
        return None
    other = inverse[:, ::-1].ravel()
    order = np.argsort(v, kind="stable")
    nbr = other[order].reshape(-1, 2).tolist()  # row x: the two neighbours of vertex x, in edge order
    visited = [False] * len(nbr)
    loops = []
    for start in range(len(nbr)):
        if visited[start]:
            continue
        loop, prev, cur = [start], start, nbr[start][0]
        visited[start] = True
        while cur != start:
            loop.append(cur)
            visited[cur] = True
            a, b = nbr[cur]
            prev, cur = cur, (a if a != prev else b)
        loops.append(verts[loop])
    return loops


def _signed_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    x_next, y_next = np.concatenate((x[1:], x[:1])), np.concatenate((y[1:], y[:1]))  # np.roll(., -1)
    return 0.5 * float(np.dot(x, y_next) - np.dot(x_next, y))


# ------------------------------------------------------------------------- per-segment rules


def fit_circle(points: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """Least-squares (algebraic, Kasa) circle through 2D points: (centre (2,), radius, RMS radial residual).

    None for fewer than 3 points or collinear points.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(points) < 3:
        return None
    offset = points.mean(axis=0)  # centred for conditioning
    p = points - offset
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    b = (p**2).sum(axis=1)
    sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    if rank < 3:
        return None
    centre = sol[:2]
    r2 = sol[2] + centre @ centre
    if not r2 > 0:
        return None
    radius = float(np.sqrt(r2))
    residual = float(np.sqrt(np.mean((np.linalg.norm(p - centre, axis=1) - radius) ** 2)))
    return centre + offset, radius, residual


def _diameter(points: np.ndarray) -> float:
    """Largest distance between two points (over the convex hull's vertices)."""
    if len(points) < 2:
        return 0.0
    try:
        hull = points[ConvexHull(points).vertices]
    except (QhullError, ValueError):  # collinear: the extent along the principal axis
        centred = points - points.mean(axis=0)
        t = centred @ np.linalg.svd(centred, full_matrices=False)[2][0]
        return float(t.max() - t.min())
    return float(np.sqrt(((hull[:, None, :] - hull[None, :, :]) ** 2).sum(-1).max()))


def _inside(xy: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Which points (..., 2) lie in box (x_min, x_max, y_min, y_max), margin already applied."""
    return (xy[..., 0] >= box[0]) & (xy[..., 0] <= box[1]) & (xy[..., 1] >= box[2]) & (xy[..., 1] <= box[3])


def _convert_segment(
    points: np.ndarray, area: float | None, box: np.ndarray, cfg: PrimitiveConfig
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Classify one segment: (point (2,) or None, lines (n, 2, 2) or None)."""
    if area is not None and area < cfg.min_area_m2:  # the outline cannot rescue it: skip that cost
        return None, None
    alpha = cfg.alpha
    if cfg.alpha_ref_size_m is not None:
        alpha *= min(1.0, cfg.alpha_ref_size_m / max(_diameter(points), 1e-9))
    outline = alpha_shape_outline(points, alpha, cfg.alpha_grid_m, cfg.alpha_max_points)
    if area is None:
        if outline is not None:
            area = abs(_signed_area(outline))
        else:  # rasterized footprint, used only by the thin-line rule below
            area = len(np.unique(np.floor(points / cfg.alpha_grid_m), axis=0)) * cfg.alpha_grid_m**2
    if area < cfg.min_area_m2:
        return None, None

    if outline is not None and area < cfg.point_max_area_m2 and _diameter(points) < cfg.point_max_len_m:
        centre = points.mean(axis=0)
        return (centre, None) if _inside(centre, box) else (None, None)

    if cfg.thin_line_max_minor_var_m2 > 0 and len(points) > 1:
        mean = points.mean(axis=0)
        evals, evecs = np.linalg.eigh(np.cov(points - mean, rowvar=False, bias=True))
        if evals[0] < cfg.thin_line_max_minor_var_m2:
            t = (points - mean) @ evecs[:, 1]
            line = mean + np.outer([t.min(), t.max()], evecs[:, 1])
            ok = _inside(line, box).all() and t.max() - t.min() > cfg.line_min_length_m
            return None, (line[None] if ok else None)
    if outline is None:
        return None, None

    if area < cfg.circle_max_area_m2:
        circle = fit_circle(outline)
        if circle is not None:
            centre, radius, residual = circle
            max_radius = np.sqrt(cfg.circle_max_area_m2 / np.pi)
            if 0 < radius < max_radius and residual < cfg.circle_max_fit_error_frac * radius:
                return (centre, None) if _inside(centre, box) else (None, None)

    if cfg.outline_simplify_m > 0:
        edges = _simplified_outline_edges(outline, box, cfg.outline_simplify_m)
    else:
        edges = np.stack([outline, np.roll(outline, -1, axis=0)], axis=1)  # closing edge included
        edges = edges[_inside(edges, box).all(axis=1)]
    ok = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1) > cfg.line_min_length_m
    return None, (edges[ok] if ok.any() else None)


def _simplified_outline_edges(ring: np.ndarray, box: np.ndarray, tolerance: float) -> np.ndarray:
    """Edges (n, 2, 2) of the outline ring simplified by Douglas-Peucker, only where inside the box.

    The unsimplified rule keeps the edges with both ends in the box; these form runs of
    consecutive inside vertices (or the whole ring). Each run is simplified on its own with its
    ends fixed, so the simplified edges cover exactly the kept part of the outline: a long
    straight side running out of the box is not lost with its last vertex.
    """
    inside = _inside(ring, box)
    if inside.all():
        closed = np.concatenate([ring, ring[:1]])
        simple = shapely.get_coordinates(
            shapely.simplify(shapely.linestrings(closed), tolerance, preserve_topology=False)
        )
        if len(simple) < 4:  # collapsed below a triangle: keep the outline as it is
            simple = closed
        return np.stack([simple[:-1], simple[1:]], axis=1)
    start = int(np.flatnonzero(~inside)[0])  # runs never wrap around when starting outside
    ring, inside = np.roll(ring, -start, axis=0), np.roll(inside, -start)
    step = np.diff(np.concatenate([[0], inside.astype(np.int8), [0]]))
    first, stop = np.flatnonzero(step == 1), np.flatnonzero(step == -1)
    long_run = stop - first >= 2
    first, stop = first[long_run], stop[long_run]
    if len(first) == 0:
        return np.zeros((0, 2, 2))
    sizes = stop - first
    run = np.repeat(np.arange(len(first)), sizes)
    vertex = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes) + np.repeat(first, sizes)
    lines = shapely.linestrings(ring[vertex], indices=run)
    lines = shapely.simplify(lines, tolerance, preserve_topology=False)
    coords, owner = shapely.get_coordinates(lines, return_index=True)
    same = owner[1:] == owner[:-1]
    return np.stack([coords[:-1][same], coords[1:][same]], axis=1)


# ------------------------------------------------------------------------------ line fusion


def _line_samples(endpoints: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Midpoints of the pieces (no longer than h) each line is cut into, and the owning line."""
    lengths = np.linalg.norm(endpoints[:, 1] - endpoints[:, 0], axis=1)
    pieces = np.maximum(np.ceil(lengths / h), 1).astype(np.int64)
    owner = np.repeat(np.arange(len(endpoints)), pieces)
    first = np.cumsum(pieces) - pieces
    frac = (np.arange(len(owner)) - first[owner] + 0.5) / pieces[owner]
    samples = endpoints[owner, 0] + frac[:, None] * (endpoints[owner, 1] - endpoints[owner, 0])
    return samples, owner


def _candidate_pairs(endpoints: np.ndarray, max_dist: float, query: np.ndarray | None = None) -> np.ndarray:
    """Pairs (i < j) whose segments may be closer than `max_dist` (a superset), (E, 2), sorted.

    Each line is cut into pieces no longer than h = max_dist / 2 and represented by the piece
    midpoints; every point of a line is within h / 2 of one, so two lines closer than max_dist
    have midpoints closer than max_dist + h (searched with a 1e-9 relative margin against
    rounding). With `query` (sorted line indices), only the pairs with at least one line in it.
    """
    n = len(endpoints)
    h = 0.5 * max_dist
    radius = (max_dist + h) * (1.0 + 1e-9)
    samples, owner = _line_samples(endpoints, h)
    tree = cKDTree(samples)
    sub = None
    if query is not None:
        is_query = np.zeros(n, dtype=bool)
        is_query[query] = True
        sub = np.flatnonzero(is_query[owner])
    if sub is not None and 4 * len(sub) < len(samples):  # few query samples: search from them only
        found = cKDTree(samples[sub]).sparse_distance_matrix(tree, radius, output_type="ndarray")
        a, b = owner[sub[found["i"]]], owner[found["j"]]
    else:
        sample_pairs = tree.query_pairs(radius, output_type="ndarray")
        a, b = owner[sample_pairs[:, 0]], owner[sample_pairs[:, 1]]
        if sub is not None:
            touch = is_query[a] | is_query[b]
            a, b = a[touch], b[touch]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = np.unique(lo[lo != hi] * n + hi[lo != hi])
    return np.stack([key // n, key % n], axis=1)


def _closest_on_segment(p: np.ndarray, a0: np.ndarray, a1: np.ndarray) -> np.ndarray:
    """Closest point to p (E, 2) on segments a0-a1 (E, 2)."""
    d = a1 - a0
    t = np.clip(((p - a0) * d).sum(-1) / (d * d).sum(-1), 0.0, 1.0)
    return a0 + t[:, None] * d


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _merge_test(
    endpoints: np.ndarray, pairs: np.ndarray, cfg: PrimitiveConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Geometric merge test of line pairs (A = pairs[:, 0], B = pairs[:, 1]): (ok, |sin angle|).

    The angle test runs first; the distance tests only on the pairs passing it.
    """
    vec = endpoints[:, 1] - endpoints[:, 0]
    length = np.linalg.norm(vec, axis=1)
    direction = vec / length[:, None]
    len_a, len_b = length[pairs[:, 0]], length[pairs[:, 1]]
    # antiparallel lines count as parallel
    sin = np.abs(_cross(direction[pairs[:, 0]], direction[pairs[:, 1]]))

    theta = np.deg2rad(cfg.line_merge_angle_deg)
    shortest = np.minimum(len_a, len_b)
    relaxed = np.minimum(theta * cfg.line_merge_short_m / shortest, SHORT_LINE_MAX_ANGLE)
    tol = np.where(shortest < cfg.line_merge_short_m, np.maximum(relaxed, theta), theta)
    ok = sin < np.sin(tol)
    sub = np.flatnonzero(ok)
    ok[sub] = _distance_test(endpoints, direction, pairs[sub], sin[sub], cfg)
    return ok, sin


def _distance_test(
    endpoints: np.ndarray, direction: np.ndarray, pairs: np.ndarray, sin: np.ndarray, cfg: PrimitiveConfig
) -> np.ndarray:
    """Gap and offset tests of the merge test (see `mergeable_line_pairs`)."""
    a0, a1 = endpoints[pairs[:, 0], 0], endpoints[pairs[:, 0], 1]
    b0, b1 = endpoints[pairs[:, 1], 0], endpoints[pairs[:, 1], 1]
    dir_a, dir_b = direction[pairs[:, 0]], direction[pairs[:, 1]]
    # Closest points between the segments: candidates are each endpoint against the other segment.
    q = np.stack(
        [
            _closest_on_segment(a0, b0, b1),
            _closest_on_segment(a1, b0, b1),
            _closest_on_segment(b0, a0, a1),
            _closest_on_segment(b1, a0, a1),
        ]
    )  # (4, E, 2)
    p = np.stack([a0, a1, b0, b1])
    d = np.linalg.norm(p - q, axis=-1)
    k = d.argmin(axis=0)
    rows = np.arange(len(pairs))
    gap = d[k, rows]
    on_a = np.where((k < 2)[:, None], p[k, rows], q[k, rows])  # closest point on A
    on_b = np.where((k < 2)[:, None], q[k, rows], p[k, rows])  # closest point on B

    # Proper intersection of non-parallel segments: closest points coincide, gap and offsets 0.
    denom = _cross(a1 - a0, b1 - b0)
    safe = np.where(denom == 0, 1.0, denom)
    s = _cross(b0 - a0, b1 - b0) / safe
    t = _cross(b0 - a0, a1 - a0) / safe
    crossing = (sin >= PARALLEL_SIN) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
    gap = np.where(crossing, 0.0, gap)
    off_a = np.where(crossing, 0.0, np.abs(_cross(dir_b, on_a - b0)))  # A's point from line B
    off_b = np.where(crossing, 0.0, np.abs(_cross(dir_a, on_b - a0)))  # B's point from line A

    perp = cfg.line_merge_perp_dist_m
    parallel_ok = np.abs(_cross(dir_a, b0 - a0)) <= perp
    general_ok = (off_a <= perp) & (off_b <= perp)
    return np.where(sin < PARALLEL_SIN, parallel_ok, general_ok) & (gap < cfg.line_merge_dist_m)


def _semantic_ok(table: torch.Tensor, rows: np.ndarray, pairs: np.ndarray, min_sim: float) -> np.ndarray:
    """Descriptor test of line pairs whose descriptors are table[rows] (rows L2-normalized).

    Lines sharing a table row pass without a dot product; each distinct row pair is computed once.
    """
    ra, rb = rows[pairs[:, 0]], rows[pairs[:, 1]]
    ok = ra == rb
    differ = np.flatnonzero(~ok)
    if differ.size:
        n = len(table)
        lo_hi = np.minimum(ra, rb)[differ] * n + np.maximum(ra, rb)[differ]
        key, inverse = np.unique(lo_hi, return_inverse=True)
        lo, hi = torch.from_numpy(key // n), torch.from_numpy(key % n)
        chunks = torch.split(torch.arange(len(key)), SEMANTIC_CHUNK)
        sim = torch.cat([(table[lo[c]] * table[hi[c]]).sum(-1) for c in chunks])
        ok[differ] = (sim >= min_sim).cpu().numpy()[inverse.ravel()]
    return ok


def _mergeable(
    endpoints: np.ndarray,
    table: torch.Tensor,
    rows: np.ndarray,
    cfg: PrimitiveConfig,
    query: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mergeable pairs (i < j, sorted) and their |sin angle|; with `query`, only pairs touching it."""
    pairs = _candidate_pairs(endpoints, cfg.line_merge_dist_m, query)
    ok, sin = _merge_test(endpoints, pairs, cfg)
    pairs, sin = pairs[ok], sin[ok]
    keep = _semantic_ok(table, rows, pairs, cfg.line_merge_semantic_sim)
    return pairs[keep], sin[keep]


def mergeable_line_pairs(
    endpoints: np.ndarray, descriptors: torch.Tensor, cfg: PrimitiveConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i < j) of lines (N, 2, 2) passing the merge test, (E, 2), and its |sin angle| (E,).

    The test (reference `clean_up_line_map`, with A = line i, B = line j): angle below the
    tolerance (relaxed for lines shorter than `line_merge_short_m`); descriptor cosine
    similarity >= `line_merge_semantic_sim`; gap between the segments < `line_merge_dist_m`;
    nearly parallel lines (|sin| < 1e-3): B's first endpoint within `line_merge_perp_dist_m` of
    line A; otherwise the segments' closest points each within that distance of the other line.
    Vectorized over the candidate pairs of a KD-tree (a superset of the pairs closer than the gap
    limit), never over all N^2 pairs.
    """
    endpoints = np.asarray(endpoints, dtype=np.float64).reshape(-1, 2, 2)
    if len(endpoints) < 2:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0)
    table = torch.nn.functional.normalize(descriptors, dim=-1)
    return _mergeable(endpoints, table, np.arange(len(endpoints)), cfg)


def _pseudo_random(keys: np.ndarray) -> np.ndarray:
    """splitmix64 of int keys: a deterministic, order-free tie-break."""
    z = keys.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _greedy_matching(pairs: np.ndarray, cost: np.ndarray, n: int) -> np.ndarray:
    """Disjoint pairs picked greedily by (binned cost, pseudo-random tie-break), (K, 2).

    Computed in rounds: a pair that ranks first for both of its lines is taken, all its lines'
    other pairs are dropped, repeat. This equals the sequential greedy matching, and the random
    tie-break keeps the number of rounds logarithmic on chains of equal-cost pairs.
    """
    order = np.lexsort((_pseudo_random(pairs[:, 0] * n + pairs[:, 1]), np.floor(cost / COST_BIN)))
    rank = np.empty(len(pairs), dtype=np.int64)
    rank[order] = np.arange(len(pairs))
    active = np.arange(len(pairs))
    matched = np.zeros(n, dtype=bool)
    chosen = []
    while active.size:
        best = np.full(n, len(pairs), dtype=np.int64)
        a, b, r = pairs[active, 0], pairs[active, 1], rank[active]
        np.minimum.at(best, a, r)
        np.minimum.at(best, b, r)
        dominant = active[(best[a] == r) & (best[b] == r)]
        chosen.append(dominant)
        matched[pairs[dominant].ravel()] = True
        active = active[~matched[a] & ~matched[b]]
    return pairs[np.concatenate(chosen)]


def _refit(original: np.ndarray, label: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """PCA line through all original endpoints of each group, clipped to their extreme projections."""
    members = np.flatnonzero(np.isin(label, groups))
    pts = original[members].reshape(-1, 2)
    gi = np.searchsorted(groups, np.repeat(label[members], 2))  # groups is sorted
    n = np.bincount(gi, minlength=len(groups)).astype(np.float64)
    mean = np.stack([np.bincount(gi, pts[:, k], minlength=len(groups)) for k in range(2)], 1) / n[:, None]
    c = pts - mean[gi]
    sxx, syy, sxy = (
        np.bincount(gi, w, minlength=len(groups)) for w in (c[:, 0] ** 2, c[:, 1] ** 2, c[:, 0] * c[:, 1])
    )
    phi = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # major axis of the 2x2 scatter matrix
    direction = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    t = (c * direction[gi]).sum(1)
    t_min = np.full(len(groups), np.inf)
    t_max = np.full(len(groups), -np.inf)
    np.minimum.at(t_min, gi, t)
    np.maximum.at(t_max, gi, t)
    return np.stack([mean + t_min[:, None] * direction, mean + t_max[:, None] * direction], axis=1)


def _fuse(
    original: np.ndarray, table: torch.Tensor, rows: np.ndarray, cfg: PrimitiveConfig
) -> tuple[np.ndarray, torch.Tensor, np.ndarray, np.ndarray]:
    """Fusion sweeps over lines whose descriptors are rows of a table (L2-normalized).

    Descriptors stay deduplicated: a merge of two lines on one row keeps that row, only a
    merge of different rows appends one. Returns (endpoints, table, rows, label: input line ->
    fused line).
    """
    current = original.copy()
    label = np.arange(len(original))
    pairs, sin = None, None
    for sweep in range(cfg.line_merge_max_sweeps):
        if len(current) < 2:
            break
        if pairs is None:
            pairs, sin = _mergeable(current, table, rows, cfg)
        if len(pairs) == 0:
            break
        merged = _greedy_matching(pairs, sin, len(current))
        a, b = merged[:, 0], merged[:, 1]
        mixed = rows[a] != rows[b]
        if mixed.any():
            lengths = torch.from_numpy(np.linalg.norm(current[:, 1] - current[:, 0], axis=1)).to(table)
            am, bm = torch.from_numpy(a[mixed]), torch.from_numpy(b[mixed])
            ra, rb = torch.from_numpy(rows[a[mixed]]), torch.from_numpy(rows[b[mixed]])
            new = lengths[am, None] * table[ra] + lengths[bm, None] * table[rb]
            rows = rows.copy()
            rows[a[mixed]] = len(table) + np.arange(int(mixed.sum()))
            table = torch.cat([table, torch.nn.functional.normalize(new, dim=-1)])
        keep = np.ones(len(current), dtype=bool)
        keep[b] = False
        target = np.arange(len(current))
        target[b] = a
        remap = (np.cumsum(keep) - 1)[target]
        label = remap[label]
        # Pairs of two untouched lines keep their geometry and descriptors, hence their test
        # result: keep them (renumbered; the order and i < j survive) and test only the pairs
        # of the refitted lines. The pair set equals a full recomputation.
        touched = ~keep
        touched[a] = True
        untouched = ~(touched[pairs[:, 0]] | touched[pairs[:, 1]])
        pairs, sin = remap[pairs[untouched]], sin[untouched]
        current, rows = current[keep], rows[keep]
        groups = np.sort(remap[a])
        current[groups] = _refit(original, label, groups)
        if sweep + 1 < cfg.line_merge_max_sweeps and len(current) >= 2:
            new_pairs, new_sin = _mergeable(current, table, rows, cfg, groups)
            pairs = np.concatenate([pairs, new_pairs])
            sin = np.concatenate([sin, new_sin])
            order = np.argsort(pairs[:, 0] * len(current) + pairs[:, 1])  # keys are distinct
            pairs, sin = pairs[order], sin[order]
    return current, table, rows, label


def fuse_lines(
    endpoints: np.ndarray, descriptors: torch.Tensor, cfg: PrimitiveConfig
) -> tuple[np.ndarray, torch.Tensor, list[np.ndarray]]:
    """Fuse fine lines (N, 2, 2) with descriptors (N, D) into coarse lines.

    Returns (endpoints (M, 2, 2) float64, L2-normalized descriptors (M, D), member indices: for
    each fused line the sorted input lines it holds). Lines must have positive length.

    Each sweep finds every mergeable pair at once (`mergeable_line_pairs`), picks disjoint
    pairs greedily, best aligned first, and merges them all: the merged line is the PCA fit to
    all pooled original endpoints, clipped to their extreme projections, and its descriptor the
    length-weighted sum of both, normalized. Sweeps repeat until nothing merges. Every merge
    passes the same test as in the reference; the reference instead merges each line with the
    first later mergeable line, one at a time, so its result depends on input order. Ours does
    not (up to index tie-breaks), takes ~log2(N) sweeps instead of up to N, and merges the
    best-aligned pairs first, so short corner edges are not absorbed before collinear ones.
    The mergeable pairs are carried over between sweeps: only the pairs of refitted lines are
    tested again (pairs of untouched lines keep their result), which gives the same pair sets.
    """
    original = np.asarray(endpoints, dtype=np.float64).reshape(-1, 2, 2)
    if len(original) != len(descriptors):
        raise ValueError("fuse_lines: one descriptor per line expected")
    if (np.linalg.norm(original[:, 1] - original[:, 0], axis=1) <= 0).any():
        raise ValueError("fuse_lines: lines must have positive length")
    table, rows = torch.unique(torch.nn.functional.normalize(descriptors, dim=-1), dim=0, return_inverse=True)
    lines, table, rows, label = _fuse(original, table, rows.cpu().numpy(), cfg)
    return lines, table[torch.from_numpy(rows)], _members(label, len(lines))


def _members(label: np.ndarray, n: int) -> list[np.ndarray]:
    order = np.argsort(label, kind="stable")
    return np.split(order, np.cumsum(np.bincount(label, minlength=n))[:-1])


# ------------------------------------------------------------------------------ entry point


def _border_boxes(border_box: BorderBox | np.ndarray | None, n: int, margin: float) -> np.ndarray:
    if border_box is None:
        return np.tile(np.array([-np.inf, np.inf, -np.inf, np.inf]), (n, 1))
    boxes = np.broadcast_to(np.asarray(border_box, dtype=np.float64), (n, 4)).copy()
    return boxes + np.array([margin, -margin, margin, -margin])


def segments_to_primitives(
    segment_points: Sequence[np.ndarray],
    descriptors: torch.Tensor,
    cfg: PrimitiveConfig,
    *,
    areas_m2: np.ndarray | None = None,
    border_box: BorderBox | np.ndarray | None = None,
    segment_ids: Sequence[int] | np.ndarray | None = None,
) -> PrimitiveSet:
    """Convert S segments (point sets (K, 2) in metres) with descriptors (S, D) to points and lines.

    `areas_m2` (S,) overrides the outline area (aerial: pixel-count area). `border_box` is
    (x_min, x_max, y_min, y_max) in the points' frame, or (S, 4) per segment (segments of several
    sub-crops converted and fused in one call); primitives must lie `border_margin_m` inside it.
    None means unbounded (ground). `segment_ids` default to 0..S-1. Points and lines inherit
    their segment's normalized descriptor; fused lines the length-weighted mean, normalized,
    and the id of the segment contributing most of their length. Everything stays in the
    caller's frame; floating outputs take the descriptor dtype (float32 if it is not floating).
    """
    n_seg = len(segment_points)
    if descriptors.ndim != 2 or descriptors.shape[0] != n_seg:
        raise ValueError(f"descriptors: expected shape ({n_seg}, D), got {tuple(descriptors.shape)}")
    dtype = descriptors.dtype if descriptors.is_floating_point() else torch.float32
    device = descriptors.device
    desc = torch.nn.functional.normalize(descriptors.detach().to("cpu", torch.float64), dim=-1)
    ids = np.arange(n_seg) if segment_ids is None else np.asarray(segment_ids, dtype=np.int64)
    if ids.shape != (n_seg,):
        raise ValueError(f"segment_ids: expected {n_seg} ids")
    if areas_m2 is not None and np.shape(areas_m2) != (n_seg,):
        raise ValueError(f"areas_m2: expected shape ({n_seg},)")
    boxes = _border_boxes(border_box, n_seg, cfg.border_margin_m)

    point_xy, point_seg, line_ep, line_seg = [], [], [], []
    for s, pts in enumerate(segment_points):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            continue
        area = None if areas_m2 is None else float(areas_m2[s])
        point, lines = _convert_segment(pts, area, boxes[s], cfg)
        if point is not None:
            point_xy.append(point)
            point_seg.append(s)
        if lines is not None:
            line_ep.append(lines)
            line_seg.append(np.full(len(lines), s))

    if line_ep:
        fine = np.concatenate(line_ep)
        fine_seg = np.concatenate(line_seg)
        lines, table, rows, label = _fuse(fine, desc, fine_seg, cfg)
        line_desc = table[torch.from_numpy(rows)]
        # the segment contributing most of each fused line's length
        fine_len = np.linalg.norm(fine[:, 1] - fine[:, 0], axis=1)
        order = np.lexsort((-fine_len, label))
        first = np.searchsorted(label[order], np.arange(len(lines)))
        line_src = fine_seg[order[first]]
    else:
        lines, line_desc, line_src = np.zeros((0, 2, 2)), desc[:0], np.zeros(0, dtype=np.int64)
    kinds = np.full(len(lines), int(LineKind.SEGMENT), dtype=np.int64)
    if cfg.line_len_to_infinite is not None:
        too_long = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1) > cfg.line_len_to_infinite
        kinds[too_long] = int(LineKind.INFINITE)

    point_seg_arr = np.asarray(point_seg, dtype=np.int64)
    f = dict(dtype=dtype, device=device)
    return PrimitiveSet(
        points_xy=torch.as_tensor(np.asarray(point_xy).reshape(-1, 2)).to(**f),
        point_descriptors=desc[torch.from_numpy(point_seg_arr)].to(**f),
        point_segment_ids=torch.from_numpy(ids[point_seg_arr]).to(device),
        line_endpoints=torch.as_tensor(lines).to(**f),
        line_kinds=torch.from_numpy(kinds).to(device),
        line_descriptors=line_desc.to(**f),
        line_segment_ids=torch.from_numpy(ids[line_src]).to(device),
    )

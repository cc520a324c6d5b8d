"""Outline of a segment's points: the alpha shape on a grid, and its edges inside the border box,
optionally simplified by Douglas-Peucker."""

from __future__ import annotations

import numpy as np
import shapely
from scipy.spatial import Delaunay, QhullError

from meridian_torch.mapping.primitives.outline_kernels import (
    alpha_boundary_edges,
    alpha_kept_triangles,
    boundary_band,
    delaunay,
    filled_pieces,
    grid_means,
    simple_loops,
)

__all__ = ["alpha_shape_outline", "inside_box", "signed_area", "simplified_outline_edges"]

# Only grid points at most this many cells from an empty cell are triangulated. A triangle with
# an empty circumcircle wider than a cell has its vertices next to empty cells, so the triangles
# along the exterior are unchanged; deeper points only add interior faces that the union fills.
# 2 cells already matched the full triangulation on 240 random shapes (with holes and notches).
BAND_CELLS = 3.0
# Below this many grid points the band is not worth its cost (closing, distance transform):
# all points are triangulated, which gives the same outline (see BAND_CELLS).
BAND_MIN_POINTS = 400


_JITTER = np.zeros((0, 2))


def _jitter(n: int) -> np.ndarray:
    """Rows 0..n-1 of default_rng(0).uniform(-1e-6, 1e-6, (N, 2)), a prefix of any longer draw; cached."""
    global _JITTER
    if len(_JITTER) < n:
        _JITTER = np.random.default_rng(0).uniform(-1e-6, 1e-6, (max(n, 2 * len(_JITTER), 4096), 2))
        _JITTER.setflags(write=False)
    return _JITTER[:n]


def _triangulation(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
    """Delaunay triangles and their neighbours (scipy's conventions) of xy, or (None, None) for
    degenerate input: compiled (`delaunay`), with qhull deciding the inputs it reports as
    degenerate (collinear, duplicates)."""
    simplices, neighbors, ok = delaunay(xy)
    if ok:
        return simplices, neighbors
    try:
        tri_obj = Delaunay(xy)
    except (QhullError, ValueError):
        return None, None
    return tri_obj.simplices, tri_obj.neighbors


def alpha_shape_outline(
    points: np.ndarray, alpha: float, grid_m: float, max_points: int | None = None
) -> np.ndarray | None:
    """Outline of a 2D point set by an alpha shape on a grid, or None.

    Points are downsampled to one mean point per `grid_m` cell (the cell doubles while more than
    `max_points` remain; None: no cap), Delaunay-triangulated, triangles with circumradius < 1/alpha kept, and
    the boundary edges of the kept triangles polygonized and unioned. Returns the exterior ring's
    K distinct vertices (K, 2), counter-clockwise, implicitly closed (vertex K-1 connects to
    vertex 0); None if the points are degenerate or not finite, or the union is not a single polygon.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(points) < 3 or not np.isfinite(points).all():  # the compiled grid needs finite cells
        return None
    pts, cells = grid_means(points, grid_m)
    while max_points is not None and len(pts) > max_points:
        grid_m *= 2.0
        pts, cells = grid_means(points, grid_m)
    if len(pts) < 3:
        return None
    radius = 1.0 / alpha
    if len(pts) > BAND_MIN_POINTS:
        pts = pts[boundary_band(cells, BAND_CELLS)]
    # A deterministic jitter far below the grid breaks the co-circular quads of lattice input
    # (which make the triangulation ambiguous); the coordinates used below stay unjittered.
    simplices, neighbors = _triangulation(pts + _jitter(len(pts)) * grid_m)
    if simplices is None:
        return None
    keep = alpha_kept_triangles(pts, simplices, radius)
    edges = alpha_boundary_edges(simplices, neighbors, keep, len(pts))
    if len(edges) < 3:
        return None
    loop_vertices, loop_starts, simple = simple_loops(edges, len(pts))
    several_loops = not simple or loop_starts.shape[0] > 2
    if several_loops and filled_pieces(neighbors, keep) > 1:  # what GEOS or the test below would find
        return None
    if not simple:  # a vertex shared by several boundary loops: let GEOS sort it out
        shape = shapely.union_all(shapely.get_parts(shapely.polygonize(shapely.linestrings(pts[edges]))))
        if not isinstance(shape, shapely.Polygon) or shape.is_empty:
            return None
        ring = shapely.get_coordinates(shape.exterior)[:-1]
    else:
        # Vertex-disjoint loops: union of the faces (holes filled) is one polygon iff the
        # largest loop encloses all others.
        rings = [pts[loop_vertices[a:b]] for a, b in zip(loop_starts[:-1], loop_starts[1:])]
        if len(rings) > 1:
            ring = rings[int(np.argmax([abs(signed_area(r)) for r in rings]))]
            others = np.array([r[0] for r in rings if r is not ring])
            if not shapely.contains_xy(shapely.Polygon(ring), others[:, 0], others[:, 1]).all():
                return None
        else:
            ring = rings[0]
    if signed_area(ring) < 0:
        ring = ring[::-1]
    return np.ascontiguousarray(ring)


def signed_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    x_next, y_next = np.concatenate((x[1:], x[:1])), np.concatenate((y[1:], y[:1]))  # np.roll(., -1)
    return 0.5 * float(np.dot(x, y_next) - np.dot(x_next, y))


def inside_box(xy: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Which points (..., 2) lie in box (x_min, x_max, y_min, y_max), margin already applied."""
    return (xy[..., 0] >= box[0]) & (xy[..., 0] <= box[1]) & (xy[..., 1] >= box[2]) & (xy[..., 1] <= box[3])


def simplified_outline_edges(ring: np.ndarray, box: np.ndarray, tolerance: float) -> np.ndarray:
    """Edges (n, 2, 2) of the outline ring simplified by Douglas-Peucker, only where inside the box.

    The unsimplified rule keeps the edges with both ends in the box; these form runs of
    consecutive inside vertices (or the whole ring). Each run is simplified on its own with its
    ends fixed, so the simplified edges cover exactly the kept part of the outline: a long
    straight side running out of the box is not lost with its last vertex.
    """
    inside = inside_box(ring, box)
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

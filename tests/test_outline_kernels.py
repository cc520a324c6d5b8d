"""The outlines' compiled kernels (`mapping.primitives.outline_kernels`): the Delaunay triangulation
against qhull and against the definition (no point inside a triangle's circumcircle), the alpha
complex's boundary, its loops and its filled pieces against their plain definitions, the convex hull against qhull's.
(Outlines from the compiled triangulation against qhull's: tests/test_segment_to_primitives.py.)"""

from __future__ import annotations

import numpy as np
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull, Delaunay, QhullError

from meridian_torch.mapping.primitives.outline import alpha_shape_outline
from meridian_torch.mapping.primitives.outline_kernels import (
    alpha_boundary_edges,
    alpha_kept_triangles,
    convex_hull,
    delaunay,
    filled_pieces,
    minor_variance_lower_bound,
    simple_loops,
)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _edges_to_neighbours(triangles: np.ndarray, neighbours: np.ndarray) -> dict:
    """{(triangle's sorted corners, the shared edge's sorted corners): neighbour's sorted corners or None}."""
    out = {}
    for t, tri in enumerate(triangles):
        for c in range(3):
            edge = tuple(sorted((int(tri[(c + 1) % 3]), int(tri[(c + 2) % 3]))))
            other = neighbours[t, c]
            out[tuple(sorted(tri.tolist())), edge] = tuple(sorted(triangles[other].tolist())) if other >= 0 else None
    return out


def _points_inside_circumcircles(xy: np.ndarray, triangles: np.ndarray) -> int:
    """How many (triangle, point) pairs have the point strictly inside the triangle's circumcircle,
    by the in-circle determinant relative to its scale (the plain definition, every pair)."""
    count = 0
    for a, b, c in triangles:
        rows = np.stack([np.concatenate([xy[v] - xy, ((xy[v] - xy) ** 2).sum(1, keepdims=True)], 1) for v in (a, b, c)], 1)
        det = np.sign(_cross(xy[b] - xy[a], xy[c] - xy[a])) * np.linalg.det(rows)  # (n,): one per point d
        inside = det > 1e-9 * np.abs(rows).max((1, 2)) ** 2
        inside[[a, b, c]] = False
        count += int(inside.sum())
    return count


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 300), st.sampled_from([1.0, 1e3]))
def test_random_points_give_qhulls_triangles_and_neighbours(seed: int, n: int, scale: float):
    """Points in general position have one Delaunay triangulation: qhull's triangles and neighbours,
    in another order; counter-clockwise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-scale, scale, (n, 2)) + rng.uniform(-5e3, 5e3, 2)
    triangles, neighbours, ok = delaunay(xy)
    assert ok
    reference = Delaunay(xy)
    assert _edges_to_neighbours(triangles, neighbours) == _edges_to_neighbours(reference.simplices, reference.neighbors)
    a, b, c = (xy[triangles[:, k]] for k in range(3))
    assert (_cross(b - a, c - a) > 0).all()


def test_jittered_lattices_are_delaunay_and_cover_their_hull():
    """The outline's input (lattice points of a segment, jittered far below the grid): every circumcircle
    is empty of points, the triangles tile the convex hull and use every point."""
    rng = np.random.default_rng(5)
    for trial in range(12):
        side = int(rng.integers(4, 14))
        g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2) * 0.25
        g = g[rng.random(len(g)) < (1.0 if trial % 3 == 0 else 0.7)]
        xy = g + rng.uniform(-2e3, 2e3, 2) + rng.uniform(-1e-6, 1e-6, g.shape) * 0.25
        if len(xy) < 3:
            continue
        triangles, _, ok = delaunay(xy)
        assert ok
        assert _points_inside_circumcircles(xy, triangles) == 0
        a, b, c = (xy[triangles[:, k]] for k in range(3))
        assert np.isclose(0.5 * _cross(b - a, c - a).sum(), ConvexHull(xy).volume, rtol=1e-9)
        assert set(triangles.ravel().tolist()) == set(range(len(xy)))


def test_degenerate_input_is_reported():
    line = np.stack([np.arange(10.0), 2.0 * np.arange(10.0)], 1)
    with_nan = np.random.default_rng(0).uniform(0, 10, (20, 2))
    with_nan[7, 1] = np.nan
    for xy in (np.zeros((2, 2)), np.zeros((5, 2)), line, with_nan):
        triangles, neighbours, ok = delaunay(xy)
        assert not ok and triangles.shape == neighbours.shape == (0, 3)
    blob = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2) * 0.3
    assert alpha_shape_outline(blob, 1.0, 0.25) is not None
    blob[37, 0] = np.inf
    assert alpha_shape_outline(blob, 1.0, 0.25) is None


def _reference_loops(edges: np.ndarray) -> list[list[int]] | None:
    """The loops by their definition: every vertex has two edges; from the smallest unvisited vertex,
    step to the other end of its first edge (in `edges` order), then always onward."""
    neighbours: dict[int, list[int]] = {}
    for a, b in edges.tolist():
        neighbours.setdefault(a, []).append(b)
        neighbours.setdefault(b, []).append(a)
    if any(len(n) != 2 for n in neighbours.values()):
        return None
    loops, visited = [], set()
    for start in sorted(neighbours):
        if start in visited:
            continue
        loop, prev, cur = [start], start, neighbours[start][0]
        visited.add(start)
        while cur != start:
            loop.append(cur)
            visited.add(cur)
            a, b = neighbours[cur]
            prev, cur = cur, (a if a != prev else b)
        loops.append(loop)
    return loops


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(st.integers(3, 12), min_size=1, max_size=5), st.booleans())
def test_simple_loops_equal_the_plain_walk(seed: int, loop_sizes: list[int], pinch: bool):
    """Disjoint polygons' edges (sorted as the outline sorts them) give the walk's loops; a vertex with
    four edges (two loops pinched together) or a dangling edge gives no loops."""
    rng = np.random.default_rng(seed)
    n_points = sum(loop_sizes) + 5
    ids = rng.permutation(n_points)
    edges, used = [], 0
    for size in loop_sizes:
        ring = ids[used : used + size]
        used += size
        edges += [sorted((int(ring[k]), int(ring[(k + 1) % size]))) for k in range(size)]
    if pinch and len(loop_sizes) > 1:  # the first vertex of loop 2 becomes the first vertex of loop 1
        edges = [[int(ids[0]) if v == ids[loop_sizes[0]] else v for v in e] for e in edges]
        edges = [sorted(e) for e in edges]
    elif pinch:
        edges.append(sorted((int(ids[0]), int(ids[-1]))))  # a dangling edge
    edges = np.array(edges, dtype=np.int64)
    edges = edges[np.argsort(edges[:, 0] * n_points + edges[:, 1])]
    vertices, starts, ok = simple_loops(edges, n_points)
    expected = _reference_loops(edges)
    assert ok == (expected is not None) and ok != pinch
    if ok:
        assert [vertices[a:b].tolist() for a, b in zip(starts[:-1], starts[1:])] == expected


def test_alpha_boundary_edges_are_the_edges_of_exactly_one_kept_triangle():
    """On qhull triangulations of segment-like lattices: the kept triangles are those with
    circumradius < r (abc / (4 area), the plain formula), and the boundary is every edge that
    exactly one kept triangle has, sorted."""
    rng = np.random.default_rng(13)
    checked = 0
    for _ in range(30):
        side = int(rng.integers(5, 25))
        g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2) * 0.3
        g = g[(rng.random(len(g)) < 0.85) & (np.linalg.norm(g - g.mean(0), axis=1) < rng.uniform(1.0, 6.0))]
        if len(g) < 4:
            continue
        pts = g + rng.uniform(-1e3, 1e3, 2)
        tri = Delaunay(pts + rng.uniform(-1e-7, 1e-7, pts.shape))
        radius = float(rng.choice([0.25, 0.5, 1.0]))
        simplices = tri.simplices.astype(np.int64)
        keep = alpha_kept_triangles(pts, simplices, radius)
        edges = alpha_boundary_edges(simplices, tri.neighbors.astype(np.int64), keep, len(pts))
        count: dict[tuple[int, int], int] = {}
        for t in tri.simplices:
            a, b, c = pts[t]
            sides = np.linalg.norm(b - a) * np.linalg.norm(c - b) * np.linalg.norm(a - c)
            area = 0.5 * abs(_cross(b - a, c - a))
            if area > 0 and sides / (4.0 * area) < radius * (1 - 1e-9):
                for k in range(3):
                    edge = tuple(sorted((int(t[k]), int(t[(k + 1) % 3]))))
                    count[edge] = count.get(edge, 0) + 1
        expected = sorted(edge for edge, c in count.items() if c == 1)
        assert edges.tolist() == [list(e) for e in expected]
        checked += len(expected) > 0
    assert checked > 20


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1), n=st.integers(3, 400), lattice=st.booleans(), turn=st.sampled_from([0.0, 0.3]),
    offset=st.sampled_from([0.0, 4321.7, -2999.95, 9876.5]),
)
def test_convex_hull_corners_are_qhulls_vertices(seed: int, n: int, lattice: bool, turn: float, offset: float):
    """Random points, and pixel-centre lattices (many collinear points on the hull's sides, turned
    or not) far from the origin as in a map frame: the corners are qhull's vertices, counter-clockwise."""
    rng = np.random.default_rng(seed)
    if lattice:
        xy = np.unique((rng.integers(0, max(3, int(np.sqrt(n))), (n, 2)) + 0.5) * 0.3, axis=0)
        xy = xy @ np.array([[np.cos(turn), np.sin(turn)], [-np.sin(turn), np.cos(turn)]])
    else:
        xy = rng.normal(0.0, rng.uniform(0.1, 30.0), (n, 2))
    xy = xy + offset
    try:
        expected = set(ConvexHull(xy).vertices.tolist())
    except QhullError:  # collinear lattice draws: qhull refuses them
        assert len(convex_hull(xy)) < 3
        return
    corners = convex_hull(xy)
    assert set(corners.tolist()) == expected and len(corners) == len(expected)
    ring = xy[corners] - xy[corners].mean(0)
    assert (_cross(np.roll(ring, -1, 0) - ring, np.roll(ring, -2, 0) - np.roll(ring, -1, 0)) > 0).all()


def test_convex_hull_of_degenerate_input_has_fewer_than_three_corners():
    line = np.stack([np.arange(10.0), 2.0 * np.arange(10.0)], 1)
    for xy in (np.zeros((0, 2)), np.ones((1, 2)), np.zeros((5, 2)), line, line[::-1]):
        assert len(convex_hull(xy)) < 3
    assert len(convex_hull(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]]))) == 3



def _ragged_lattice(rng: np.random.Generator) -> np.ndarray:
    """Lattice points (0.3 m) of one or two blobs with pixels dropped at random: pinches, holes, islands."""
    side = int(rng.integers(6, 30))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2) * 0.3
    inside = np.zeros(len(g), bool)
    for _ in range(int(rng.integers(1, 3))):
        inside |= np.linalg.norm(g - rng.uniform(0.0, 0.3 * side, 2), axis=1) < rng.uniform(0.6, 0.2 * side)
    return g[inside & (rng.random(len(g)) >= rng.choice([0.0, 0.15, 0.3]))] + rng.uniform(-1e3, 1e3, 2)


def test_filled_pieces_count_the_parts_of_the_polygonized_boundary():
    """The kept triangles' filled pieces are the parts of what the outline's GEOS path builds from the
    boundary edges (their faces polygonized and unioned), on qhull triangulations of ragged lattices."""
    rng = np.random.default_rng(17)
    counts: dict[int, int] = {}
    for _ in range(80):
        pts = _ragged_lattice(rng)
        if len(pts) < 4:
            continue
        tri = Delaunay(pts + rng.uniform(-1e-7, 1e-7, pts.shape))
        simplices, neighbours = tri.simplices.astype(np.int64), tri.neighbors.astype(np.int64)
        keep = alpha_kept_triangles(pts, simplices, float(rng.choice([0.25, 0.5, 1.0])))
        edges = alpha_boundary_edges(simplices, neighbours, keep, len(pts))
        union = shapely.union_all(shapely.get_parts(shapely.polygonize(shapely.linestrings(pts[edges]))))
        expected = 0 if union.is_empty else shapely.get_num_geometries(union)
        pieces = filled_pieces(neighbours, keep)
        assert pieces == expected
        counts[min(pieces, 2)] = counts.get(min(pieces, 2), 0) + 1
    assert counts[1] > 10 and counts[2] > 10


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1), n=st.integers(1, 3000), thin=st.sampled_from([0.0, 1e-3, 0.1, 1.0]),
    offset=st.sampled_from([0.0, 4321.7, -29876.5]),
)
def test_minor_variance_bound_is_below_lapacks_eigenvalue_and_close(seed: int, n: int, thin: float, offset: float):
    """The bound never exceeds the smallest eigenvalue NumPy/LAPACK find for the population
    covariance (so a bound above a threshold decides the thin-line rule as before), and is within
    rounding of it; thin, turned bars far from the origin included."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, np.pi)
    turn = np.array([[np.cos(angle), np.sin(angle)], [-np.sin(angle), np.cos(angle)]])
    xy = (rng.normal(0.0, 1.0, (n, 2)) * [rng.uniform(0.5, 20.0), thin]) @ turn + offset
    centred = xy - xy.mean(axis=0)
    covariance = centred.T @ centred / n
    smallest = np.linalg.eigh(covariance)[0][0]
    bound = minor_variance_lower_bound(xy)
    assert bound <= smallest
    assert smallest - bound <= 2e-9 * np.trace(covariance) + 1e-12

"""Segment → primitive conversion on hand-built segments (dense point grids at 0.1 m)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from scipy import ndimage
from scipy.spatial import Delaunay

from meridian_torch.config.mapping import PrimitiveConfig
from meridian_torch.mapping.primitives import conversion, line_fusion, outline
from meridian_torch.mapping.primitives.conversion import (
    _covariance,
    _diameter,
    fit_circle,
    segments_to_primitives,
)
from meridian_torch.mapping.primitives.line_fusion import fuse_indexed_lines, fuse_lines, mergeable_line_pairs
from meridian_torch.mapping.primitives.outline import (
    alpha_shape_outline,
    inside_box,
    simplified_outline_edges,
)
from meridian_torch.mapping.primitives.outline_kernels import boundary_band, grid_means
from meridian_torch.types import LineKind

SPACING = 0.1
# The reference's rules (outline edges unsimplified); the default simplification is tested separately.
CFG = PrimitiveConfig(outline_simplify_m=0.0)


def grid(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    xs = np.arange(x0, x1 + 1e-9, SPACING)
    ys = np.arange(y0, y1 + 1e-9, SPACING)
    return np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)


def disc(radius: float, centre: tuple[float, float]) -> np.ndarray:
    g = grid(-radius, radius, -radius, radius)
    return g[np.linalg.norm(g, axis=1) <= radius] + np.asarray(centre)


def rotate(points: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return points @ np.array([[c, -s], [s, c]]).T


def convert(segments: list[np.ndarray], descriptors: torch.Tensor | None = None, cfg: PrimitiveConfig = CFG, **kwargs):
    if descriptors is None:
        descriptors = torch.eye(8)[: len(segments)]
    areas = np.array([len(p) * SPACING**2 for p in segments])  # pixel-count areas, aerial style
    return segments_to_primitives(segments, descriptors, cfg, areas_m2=areas, **kwargs)


def lengths(endpoints: torch.Tensor) -> np.ndarray:
    e = endpoints.double().numpy()
    return np.linalg.norm(e[:, 1] - e[:, 0], axis=1)


# Line ends may miss a corner by one outline-grid cell diagonal: at some rotations the 0.25 m grid
# cuts a corner by one short edge too oblique to fuse (hypothesis found 0.350 m; the diagonal is 0.354 m).
CORNER_CUT_M = math.sqrt(2.0) * CFG.alpha_grid_m


def assert_matches_side(
    line: np.ndarray, a: np.ndarray, b: np.ndarray, tol_m: float = 0.3, tol_deg: float = 2.0,
    tol_end_m: float = CORNER_CUT_M + 0.02,
):
    """Line within tol_m of side a-b's line, within tol_deg of its direction, ending within tol_end_m of a and b.

    The end tolerance exceeds tol_m slightly: see CORNER_CUT_M.
    """
    u = (b - a) / np.linalg.norm(b - a)
    t = np.sort((line - a) @ u)
    offset = np.abs((line - a) @ np.array([-u[1], u[0]]))
    assert offset.max() < tol_m
    assert abs(t[0]) < tol_end_m and abs(t[1] - np.linalg.norm(b - a)) < tol_end_m
    d = line[1] - line[0]
    sin = abs(d[0] * u[1] - d[1] * u[0]) / np.linalg.norm(d)
    assert math.degrees(math.asin(min(sin, 1.0))) < tol_deg


def test_small_disc_is_one_point_at_its_centre():
    for out in (convert([disc(1.0, (3.3, -4.1))]), segments_to_primitives([disc(1.0, (3.3, -4.1))], torch.eye(4)[:1], CFG)):
        assert out.points_xy.shape == (1, 2) and out.line_endpoints.shape[0] == 0
        assert torch.allclose(out.points_xy[0], torch.tensor([3.3, -4.1]), atol=0.02)
        assert out.point_segment_ids.tolist() == [0]


def test_thin_bar_is_one_line_along_it():
    bar = rotate(grid(0.0, 8.0, 0.0, 0.15), 0.4) + np.array([5.0, 2.0])
    out = convert([bar])
    assert out.points_xy.shape[0] == 0 and out.line_endpoints.shape[0] == 1
    assert abs(lengths(out.line_endpoints)[0] - 8.0) < 0.1
    a = np.array([5.0, 2.0]) + rotate(np.array([[0.0, 0.07]]), 0.4)[0]
    b = np.array([5.0, 2.0]) + rotate(np.array([[8.0, 0.07]]), 0.4)[0]
    assert_matches_side(out.line_endpoints[0].double().numpy(), a, b, tol_m=0.1, tol_deg=0.5, tol_end_m=0.1)


def test_midsize_disc_is_a_circle_point():
    out = convert([disc(3.5, (1.0, 2.0))])
    assert out.points_xy.shape == (1, 2) and out.line_endpoints.shape[0] == 0
    assert torch.allclose(out.points_xy[0], torch.tensor([1.0, 2.0]), atol=0.05)


@pytest.mark.xfail(strict=True, reason="known defect: 0.35 m outline simplification can bend a 2 m end piece of a "
                   "side 10.6 deg off it, past the 10 deg fusion angle, so the side splits (found by hypothesis). "
                   "Relaxing the angle to asin(2 grid / length) fixes this case but merged 12 % of the demo map's "
                   "lines and cut unknown-rotation top-1 registration from 29 to 15 %, so it is not done")
def test_simplified_square_side_stays_one_line_near_axis_aligned():
    angle, shift = 3.068359375, np.array([1.46875, 1.015625])
    square = rotate(grid(0.0, 20.0, 0.0, 20.0) - 10.0, angle) + shift
    out = convert([square], cfg=PrimitiveConfig())
    assert (lengths(out.line_endpoints) > 18.5).sum() == 4


@settings(max_examples=25, deadline=None)
@given(
    angle=st.floats(0.0, 2.0 * math.pi),
    tx=st.floats(-500.0, 500.0),
    ty=st.floats(-500.0, 500.0),
)
def test_large_square_becomes_its_four_sides(angle: float, tx: float, ty: float):
    square = rotate(grid(0.0, 20.0, 0.0, 20.0) - 10.0, angle) + np.array([tx, ty])
    corners = rotate(np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]), angle) + np.array([tx, ty])
    # Simplifying the outline may cut the rounded corners into chamfer edges (up to ~1.5 m at
    # 0.35 m tolerance): a side's ends may then move off the side by up to the tolerance, and
    # along it by up to ~4 tolerances (1.35 m worst over 240 random poses at 0.35 m).
    default = PrimitiveConfig()
    tol = default.outline_simplify_m
    corner = 1.0 + 1.5 * tol / 0.35
    cut = CORNER_CUT_M + 0.02
    cases = ((CFG, 1.0, 1.0, 0.3, cut), (default, corner, 4 * corner, 0.3 + tol, cut + 4 * tol))
    for cfg, corner_m, leftover_m, tol_m, tol_end_m in cases:
        out = convert([square], cfg=cfg)
        assert out.points_xy.shape[0] == 0
        ln = lengths(out.line_endpoints)
        long = out.line_endpoints[torch.from_numpy(ln > corner_m)].double().numpy()
        assert len(long) == 4 and ln[ln <= corner_m].sum() < leftover_m  # leftovers: corner edges only
        for k in range(4):
            a, b = corners[k], corners[(k + 1) % 4]
            matching = [line for line in long if np.linalg.norm(line.mean(axis=0) - (a + b) / 2) < 1.0]
            assert len(matching) == 1
            assert_matches_side(matching[0], a, b, tol_m=tol_m, tol_end_m=tol_end_m)
        assert (out.line_kinds == int(LineKind.SEGMENT)).all()


def test_point_outside_the_border_box_is_dropped():
    box = (0.0, 10.0, 0.0, 10.0)
    assert convert([disc(1.0, (5.0, 5.0))], border_box=box).points_xy.shape[0] == 1
    out = convert([disc(1.0, (0.3, 5.0))], border_box=box)  # centre within the 0.5 m margin
    assert out.points_xy.shape[0] == 0 and out.line_endpoints.shape[0] == 0


def test_square_at_the_border_keeps_only_the_sides_inside():
    out = convert([grid(0.0, 20.0, 0.0, 20.0)], border_box=(-5.0, 20.0, -5.0, 25.0))
    ends = out.line_endpoints.double().numpy()
    assert (ends[..., 0] <= 19.5 + 1e-6).all()  # nothing from the right side (x = 20)
    long = ends[lengths(out.line_endpoints) > 1.0]
    assert len(long) == 3
    assert_matches_side(next(ln for ln in long if ln[:, 0].max() < 1.0), np.array([0.0, 0.0]), np.array([0.0, 20.0]))
    for y in (0.0, 20.0):
        side = next(ln for ln in long if abs(ln[:, 1].mean() - y) < 0.5)
        assert_matches_side(side, np.array([0.0, y]), np.array([19.5, y]))


def test_collinear_lines_fuse_only_with_similar_descriptors():
    lines = np.array([[[0.0, 0.0], [3.0, 0.0]], [[3.5, 0.05], [6.5, 0.05]]])
    apart = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    close = torch.tensor([[1.0, 0.0], [0.9, math.sqrt(1 - 0.81)]])
    ends, desc, members = fuse_lines(lines, apart, CFG)
    assert len(ends) == 2 and [m.tolist() for m in members] == [[0], [1]]
    ends, desc, members = fuse_lines(lines, close, CFG)
    assert len(ends) == 1 and members[0].tolist() == [0, 1]
    assert abs(np.linalg.norm(ends[0, 1] - ends[0, 0]) - 6.5) < 0.01
    expected = torch.nn.functional.normalize(3.0 * close[0] + 3.0 * close[1], dim=0)
    assert torch.allclose(desc[0], expected, atol=1e-6)


def slow_merge_test(a: np.ndarray, b: np.ndarray, da: np.ndarray, db: np.ndarray, cfg: PrimitiveConfig) -> bool:
    """The reference's merge test of lines A (earlier) and B, one pair at a time."""
    la, lb = np.linalg.norm(a[1] - a[0]), np.linalg.norm(b[1] - b[0])
    if np.linalg.norm(a[0] - b[0]) > la + lb + cfg.line_merge_dist_m:
        return False
    ua, ub = (a[1] - a[0]) / la, (b[1] - b[0]) / lb
    sin = abs(ua[0] * ub[1] - ua[1] * ub[0])
    tol = math.radians(cfg.line_merge_angle_deg)
    if min(la, lb) < cfg.line_merge_short_m:
        tol = max(tol, min(tol * cfg.line_merge_short_m / min(la, lb), math.pi / 4))
    if sin >= math.sin(tol) or float(da @ db) < cfg.line_merge_semantic_sim:
        return False

    def point_segment(p, s):
        d = s[1] - s[0]
        t = min(max(float((p - s[0]) @ d / (d @ d)), 0.0), 1.0)
        return s[0] + t * d

    def line_dist(p, s, u):
        w = p - s[0]
        return abs(u[0] * w[1] - u[1] * w[0])

    candidates = [(a[0], point_segment(a[0], b)), (a[1], point_segment(a[1], b))]
    candidates += [(point_segment(b[0], a), b[0]), (point_segment(b[1], a), b[1])]
    on_a, on_b = min(candidates, key=lambda pq: np.linalg.norm(pq[0] - pq[1]))
    gap = np.linalg.norm(on_a - on_b)
    if sin < 1e-3:
        return line_dist(b[0], a, ua) <= cfg.line_merge_perp_dist_m and gap < cfg.line_merge_dist_m
    shapely_gap = shapely.distance(shapely.LineString(a), shapely.LineString(b))
    if shapely_gap == 0.0:  # crossing segments: both closest points are the crossing
        return True
    return (
        line_dist(on_a, b, ub) <= cfg.line_merge_perp_dist_m
        and line_dist(on_b, a, ua) <= cfg.line_merge_perp_dist_m
        and gap < cfg.line_merge_dist_m
    )


def test_vectorized_merge_test_equals_slow_pairwise_loop():
    rng = np.random.default_rng(7)
    n = 160
    start = rng.uniform(0.0, 8.0, (n, 2))
    angle = rng.choice([0.0, 0.05, 0.3, 1.2], n) + rng.normal(0.0, 0.05, n)
    length = rng.choice([0.2, 0.6, 2.0, 5.0], n) * rng.uniform(0.8, 1.2, n)
    ends = np.stack([start, start + length[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)], 1)
    ends[::7, :, 1] = ends[::7, :1, 1] + rng.uniform(-0.4, 0.4, (len(ends[::7]), 1))  # exactly parallel ones
    clusters = np.eye(16)[:3]
    noise = rng.normal(0.0, rng.choice([0.03, 0.12], n)[:, None], (n, 16))  # similarities near 0.8 too
    desc = torch.nn.functional.normalize(torch.from_numpy(clusters[rng.integers(0, 3, n)] + noise), dim=-1)
    pairs, _ = mergeable_line_pairs(ends, desc, CFG)
    d = desc.numpy()
    slow = {(i, j) for i in range(n) for j in range(i + 1, n) if slow_merge_test(ends[i], ends[j], d[i], d[j], CFG)}
    assert len(slow) > 50  # the scene exercises the test
    assert {tuple(p) for p in pairs.tolist()} == slow


def test_outline_band_equals_full_triangulation():
    rng = np.random.default_rng(3)
    for spacing in (0.1, 0.3):
        xs = np.arange(-8.0, 8.0, spacing)
        g = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
        inside = (np.linalg.norm(g - [-2.0, 0.0], axis=1) < 4.5) | ((np.abs(g[:, 0] - 3.0) < 3.5) & (np.abs(g[:, 1]) < 1.5))
        inside &= np.linalg.norm(g - rng.uniform(-2, 2, 2), axis=1) > 1.2  # a hole
        pts = g[inside]
        ring = alpha_shape_outline(pts, CFG.alpha, CFG.alpha_grid_m)
        # reference: all cell-mean points, Delaunay, circumradius < 1 m, polygonize + union
        cells = np.floor(pts / CFG.alpha_grid_m).astype(np.int64)
        _, inv = np.unique(cells, axis=0, return_inverse=True)
        inv = inv.ravel()
        means = np.stack([np.bincount(inv, pts[:, k]) for k in range(2)], 1) / np.bincount(inv)[:, None]
        tri = Delaunay(means).simplices
        keep = [shapely.Polygon(means[t]) for t in tri if _circumradius(means[t]) < 1.0 / CFG.alpha]
        full = shapely.union_all(keep)
        assert isinstance(full, shapely.Polygon)
        expected = shapely.get_coordinates(full.exterior)[:-1]
        assert ring is not None and {tuple(np.round(p, 9)) for p in ring} == {tuple(np.round(p, 9)) for p in expected}


def segment_like_points(rng: np.random.Generator, max_radius: float) -> np.ndarray:
    """Pixel centres (0.1 or 0.3 m lattice) of a segment-like shape: a rotated box and a disc, minus
    a notch or a hole."""
    spacing, r = rng.choice([0.1, 0.3]), rng.uniform(1.0, max_radius)
    xs = np.arange(-r, r, spacing)
    g = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
    q = rotate(g, rng.uniform(0.0, np.pi))
    inside = (np.abs(q[:, 0]) < r * rng.uniform(0.3, 1.0)) & (np.abs(q[:, 1]) < r * rng.uniform(0.1, 1.0))
    inside |= np.linalg.norm(g - rng.uniform(-r, r, 2), axis=1) < rng.uniform(0.5, r)
    inside &= np.linalg.norm(g - rng.uniform(-r, r, 2), axis=1) > rng.uniform(0.0, 1.5)  # notches, holes
    return g[inside]


def test_outline_without_band_equals_outline_with_band(monkeypatch):
    """Small point sets skip the boundary band; that gives bit-identical outlines."""
    rng = np.random.default_rng(11)
    shapes = 0
    for _ in range(60):
        pts = segment_like_points(rng, 5.0) + rng.uniform(-300.0, 300.0, 2)
        outlines = []
        for band_min in (10**9, 0):  # never / always the band
            monkeypatch.setattr(outline, "BAND_MIN_POINTS", band_min)
            outlines.append(alpha_shape_outline(pts, CFG.alpha, CFG.alpha_grid_m))
        assert (outlines[0] is None) == (outlines[1] is None)
        if outlines[0] is not None:
            shapes += 1
            assert np.array_equal(outlines[0], outlines[1])
    assert shapes > 40


def test_outlines_equal_those_of_qhulls_triangulation(monkeypatch):
    """Segment-like shapes get the same outline from the compiled triangulation (which resolves the
    jittered lattice's near-cocircular quads by the jitter) as from qhull's (which splits them
    either way: the two triangles of such a quad share one circumcircle)."""
    rng = np.random.default_rng(21)
    shapes = 0
    for _ in range(60):
        pts = segment_like_points(rng, 8.0) + rng.uniform(-2000.0, 2000.0, 2)
        compiled = alpha_shape_outline(pts, CFG.alpha, CFG.alpha_grid_m)
        with monkeypatch.context() as m:
            m.setattr(outline, "delaunay", lambda xy: (None, None, False))  # always ask qhull
            reference = alpha_shape_outline(pts, CFG.alpha, CFG.alpha_grid_m)
        assert (compiled is None) == (reference is None)
        if compiled is not None:
            shapes += 1
            assert np.array_equal(compiled, reference)
    assert shapes > 40


def test_outlines_are_the_same_without_the_filled_pieces_shortcut(monkeypatch):
    """Shapes whose boundary has several loops (holes, islands, pinches) are refused by counting the
    filled pieces before GEOS or the ring test see them; without that shortcut the outlines (and
    refusals) are the same."""
    rng = np.random.default_rng(23)
    several = refused = 0
    calls = []
    counting = outline.filled_pieces
    monkeypatch.setattr(outline, "filled_pieces", lambda *a: calls.append(counting(*a)) or calls[-1])
    for _ in range(80):
        pts = segment_like_points(rng, 6.0)
        if rng.random() < 0.5:  # a second shape, overlapping, touching or apart
            pts = np.concatenate([pts, segment_like_points(rng, 4.0) + rng.uniform(-12.0, 12.0, 2)])
        pts = pts[rng.random(len(pts)) >= rng.choice([0.0, 0.2, 0.4])] + rng.uniform(-900.0, 900.0, 2)
        n_calls = len(calls)
        shortcut = alpha_shape_outline(pts, CFG.alpha, CFG.alpha_grid_m)
        several += len(calls) > n_calls
        refused += len(calls) > n_calls and calls[-1] > 1
        with monkeypatch.context() as m:
            m.setattr(outline, "filled_pieces", lambda *a: 1)
            reference = alpha_shape_outline(pts, CFG.alpha, CFG.alpha_grid_m)
        assert (shortcut is None) == (reference is None)
        if shortcut is not None:
            assert np.array_equal(shortcut, reference)
    assert several > 20 and refused > 10


def test_conversion_is_the_same_without_the_thin_line_screen(monkeypatch):
    """The thin-line rule's bound only spares segments LAPACK's eigen-decomposition: without it
    (every segment decomposed) the primitives are the same, bit for bit, thin bars included."""
    rng = np.random.default_rng(29)
    segments = [segment_like_points(rng, 5.0) + rng.uniform(-500.0, 500.0, 2) for _ in range(40)]
    for width in (0.1, 0.2, 0.3):  # bars 1-3 pixels wide: variance near the rule's threshold
        bar = rotate(grid(0.0, rng.uniform(2.0, 12.0), 0.0, width), rng.uniform(0.0, np.pi))
        segments.append(bar + rng.uniform(-500.0, 500.0, 2))
    descriptors = torch.from_numpy(rng.normal(size=(len(segments), 8)))
    screened = convert(segments, descriptors)
    monkeypatch.setattr(conversion, "minor_variance_lower_bound", lambda points: -np.inf)
    reference = convert(segments, descriptors)
    assert len(reference.line_endpoints) > 0 and len(reference.points_xy) > 0
    for field in ("points_xy", "point_segment_ids", "line_endpoints", "line_segment_ids", "line_descriptors"):
        assert torch.equal(getattr(screened, field), getattr(reference, field))


def test_grid_downsample_one_point_per_cell_equals_the_cell_means():
    """The one-point-per-cell shortcut returns bit for bit the summed cell means (and cells) of the general path."""
    rng = np.random.default_rng(8)
    for trial in range(40):
        pitch = 0.3 if trial % 2 else 0.1  # 0.3 m pixels: one per 0.25 m cell; 0.1 m: several per cell
        xs = np.arange(-4.0, 4.0, pitch)
        g = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
        pts = g[rng.random(len(g)) < rng.uniform(0.2, 1.0)] + rng.choice([0.0, rng.uniform(-500.0, 500.0)], size=2)
        pts = pts[rng.permutation(len(pts))]
        pts[: trial % 3] = -0.0  # negative zeros: summing from 0.0 makes them 0.0
        cells_all = np.floor(pts / CFG.alpha_grid_m).astype(np.int64)
        uniq, inv, counts = np.unique(cells_all, axis=0, return_inverse=True, return_counts=True)
        inv = inv.ravel()
        sums = np.zeros((len(uniq), 2))
        for i, cell in enumerate(inv):  # the mean of every cell, one point at a time
            sums[cell] += pts[i]
        means, cells = grid_means(pts, CFG.alpha_grid_m)
        assert np.array_equal(cells, uniq)
        expected = sums / counts[:, None]
        assert means.tobytes() == expected.tobytes()


def test_boundary_band_equals_closing_and_distance_transform():
    """The erosion band equals its definition: closing, then Euclidean distance to an empty cell <= BAND_CELLS."""
    rng = np.random.default_rng(9)
    sizes = set()
    for trial in range(80):
        side = int(rng.integers(4, 60))
        occupied = rng.random((side, side)) < rng.uniform(0.5, 1.0)  # speckle: gaps the closing fills or not
        yy, xx = np.mgrid[:side, :side]
        occupied &= (yy - rng.uniform(0, side)) ** 2 + (xx - rng.uniform(0, side)) ** 2 > rng.uniform(0, side) ** 2
        if trial % 4 == 0:
            occupied[:, int(rng.integers(0, side))] = False  # an empty column, as 0.3 m pixels leave
        cells = np.argwhere(occupied) + rng.integers(-1000, 1000, size=2)
        if len(cells) == 0:
            continue
        lo = cells.min(axis=0) - 2
        grid_cells = np.zeros(tuple(cells.max(axis=0) - lo + 3), dtype=bool)
        grid_cells[tuple((cells - lo).T)] = True
        closed = ndimage.binary_closing(grid_cells, structure=np.ones((3, 3), dtype=bool))
        expected = ndimage.distance_transform_edt(closed)[tuple((cells - lo).T)] <= outline.BAND_CELLS
        band = boundary_band(cells, outline.BAND_CELLS)
        sizes.add((bool(expected.all()), bool(expected.any())))
        assert np.array_equal(band, expected)
    assert (False, True) in sizes  # some cells deep inside, some in the band


def _circumradius(t: np.ndarray) -> float:
    a, b, c = (np.linalg.norm(t[i] - t[(i + 1) % 3]) for i in range(3))
    area = 0.5 * abs((t[1, 0] - t[0, 0]) * (t[2, 1] - t[0, 1]) - (t[1, 1] - t[0, 1]) * (t[2, 0] - t[0, 0]))
    return math.inf if area == 0 else a * b * c / (4.0 * area)


def _fuse_full_sweeps(original, table, rows, cfg):
    """Fusion as before the incremental pair list: every sweep recomputes all mergeable pairs."""
    current, label = original.copy(), np.arange(len(original))
    for _ in range(cfg.line_merge_max_sweeps):
        if len(current) < 2:
            break
        pairs, sin = line_fusion._mergeable(current, table, rows, cfg)
        if len(pairs) == 0:
            break
        merged = line_fusion._greedy_matching(pairs, sin, len(current))
        a, b = merged[:, 0], merged[:, 1]
        mixed = rows[a] != rows[b]
        if mixed.any():
            lengths = torch.from_numpy(np.linalg.norm(current[:, 1] - current[:, 0], axis=1)).to(table)
            new = lengths[a[mixed], None] * table[rows[a[mixed]]] + lengths[b[mixed], None] * table[rows[b[mixed]]]
            rows = rows.copy()
            rows[a[mixed]] = len(table) + np.arange(int(mixed.sum()))
            table = torch.cat([table, torch.nn.functional.normalize(new, dim=-1)])
        keep = np.ones(len(current), dtype=bool)
        keep[b] = False
        target = np.arange(len(current))
        target[b] = a
        remap = (np.cumsum(keep) - 1)[target]
        label = remap[label]
        current, rows = current[keep], rows[keep]
        groups = np.sort(remap[a])
        current[groups] = line_fusion._refit(original, label, groups)
    return current, table, rows, label


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_candidate_pairs_are_the_line_pairs_with_samples_within_the_radius(seed: int):
    """The grid search's pairs equal every pair of lines with two samples within the search radius
    (all sample pairs), also when only pairs touching some lines are asked for."""
    rng = np.random.default_rng(seed)
    n = 150
    start = rng.uniform(0.0, 25.0, (n, 2)) + rng.choice([0.0, 3210.4])
    angle = rng.uniform(0.0, np.pi, n)
    length = rng.choice([0.3, 2.0, 12.0], n) * rng.uniform(0.8, 1.2, n)
    ends = np.stack([start, start + length[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)], 1)
    max_dist = CFG.line_merge_dist_m
    h = 0.5 * max_dist
    radius = (max_dist + h) * (1.0 + 1e-9)
    samples, owner = line_fusion._line_samples(ends, h)
    near = ((samples[:, None, :] - samples[None, :, :]) ** 2).sum(-1) <= radius * radius
    a, b = np.nonzero(near)
    every = {(int(min(i, j)), int(max(i, j))) for i, j in zip(owner[a], owner[b]) if i != j}
    assert len(every) > 100  # the scene has neighbours
    for query in (None, np.arange(0, n, 7), np.array([3])):
        expected = every if query is None else {p for p in every if p[0] in set(query) or p[1] in set(query)}
        pairs = line_fusion._candidate_pairs(ends, max_dist, query)
        assert pairs.tolist() == sorted(map(list, expected))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 300), offset=st.sampled_from([0.0, 4321.7]))
def test_principal_axes_covariance_is_numpys_bit_for_bit(seed: int, n: int, offset: float):
    rng = np.random.default_rng(seed)
    points = rng.normal(0.0, rng.uniform(0.1, 20.0), (n, 2)) * rng.uniform(0.05, 1.0, 2) + offset
    centred = points - points.mean(axis=0)
    assert _covariance(centred).tobytes() == np.cov(centred, rowvar=False, bias=True).tobytes()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 200), offset=st.sampled_from([0.0, 4321.7]))
def test_diameter_is_the_largest_distance_of_any_two_points(seed: int, n: int, offset: float):
    """Bit for bit over the hull's corners; collinear points (two here) take the extent along
    their principal axis, equal to rounding."""
    rng = np.random.default_rng(seed)
    points = rng.normal(0.0, rng.uniform(0.1, 20.0), (n, 2)) + offset
    every = float(np.sqrt(((points[:, None, :] - points[None, :, :]) ** 2).sum(-1).max()))
    if n == 2:
        assert _diameter(points) == pytest.approx(every, rel=1e-9, abs=1e-9)
    else:
        assert _diameter(points) == every


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_incremental_fusion_equals_full_sweeps(seed: int):
    """Keeping the untouched pairs between sweeps gives bit-identical fused lines."""
    rng = np.random.default_rng(seed)
    segments, seg_of = [], []
    for k in range(12):  # outline edges of overlapping rotated rectangles and discs, as in an aerial patch
        c = rng.uniform(0.0, 30.0, 2)
        if k % 3:
            pts = rotate(grid(0.0, rng.uniform(3.0, 12.0), 0.0, rng.uniform(2.0, 8.0)), rng.uniform(0, np.pi)) + c
        else:
            pts = disc(rng.uniform(2.0, 5.0), tuple(c))
        ring = alpha_shape_outline(pts + rng.normal(0.0, 0.03, pts.shape), CFG.alpha, CFG.alpha_grid_m)
        segments.append(np.stack([ring, np.roll(ring, -1, axis=0)], axis=1))
        seg_of.append(np.full(len(ring), k))
    lines, seg_of = np.concatenate(segments), np.concatenate(seg_of)
    clusters = np.eye(8)[rng.integers(0, 3, 12)]  # several segments per class: mixed merges happen
    desc = torch.nn.functional.normalize(torch.from_numpy(clusters + rng.normal(0.0, 0.08, (12, 8))), dim=-1)
    fast = fuse_indexed_lines(lines, desc, seg_of, CFG)
    slow = _fuse_full_sweeps(lines, desc, seg_of, CFG)
    assert len(fast[0]) < len(lines) // 3  # the scene exercises several sweeps
    assert np.array_equal(fast[0], slow[0]) and np.array_equal(fast[3], slow[3])
    assert torch.equal(fast[1][torch.from_numpy(fast[2])], slow[1][torch.from_numpy(slow[2])])


@pytest.mark.parametrize("angle", [0.0, 0.3, 1.1])
def test_simplified_outline_keeps_the_sides(angle: float):
    cfg = PrimitiveConfig(outline_simplify_m=0.1)
    square = rotate(grid(0.0, 20.0, 0.0, 20.0) - 10.0, angle) + np.array([40.0, 40.0])
    plain = segments_to_primitives([square], torch.eye(2)[:1], CFG)
    simple = segments_to_primitives([square], torch.eye(2)[:1], cfg)
    corners = rotate(np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]), angle) + 40.0
    for out in (plain, simple):
        long = out.line_endpoints[torch.from_numpy(lengths(out.line_endpoints) > 1.0)].double().numpy()
        assert len(long) == 4
        for k in range(4):
            a, b = corners[k], corners[(k + 1) % 4]
            assert_matches_side(next(ln for ln in long if np.linalg.norm(ln.mean(0) - (a + b) / 2) < 1.0), a, b)
    # the simplified edges are outline vertices, lie inside the box, and stay within tolerance
    ring = alpha_shape_outline(square, CFG.alpha, CFG.alpha_grid_m)
    box = np.array([-np.inf, np.inf, -np.inf, np.inf])
    edges = simplified_outline_edges(ring, box, 0.1)
    assert len(edges) < len(ring) / 3 and np.array_equal(edges[1:, 0], edges[:-1, 1])
    assert {tuple(p) for p in edges.reshape(-1, 2)} <= {tuple(p) for p in ring}
    simplified = shapely.LineString(np.concatenate([edges[:, 0], edges[-1:, 1]]))
    assert shapely.LineString(np.concatenate([ring, ring[:1]])).hausdorff_distance(simplified) < 0.1 + 1e-9


def test_simplified_outline_is_cut_at_the_border_box():
    ring = alpha_shape_outline(grid(0.0, 20.0, 0.0, 20.0), CFG.alpha, CFG.alpha_grid_m)
    box = np.array([-5.0, 19.5, -5.0, 25.0])  # the side x = 20 is outside
    plain = np.stack([ring, np.roll(ring, -1, axis=0)], axis=1)
    plain = plain[inside_box(plain, box).all(axis=1)]
    edges = simplified_outline_edges(ring, box, 0.1)
    assert inside_box(edges, box).all() and len(edges) < len(plain) / 3
    covered = shapely.union_all(shapely.linestrings(edges))
    assert abs(covered.length - shapely.union_all(shapely.linestrings(plain)).length) < 0.05
    assert covered.length > 3 * 19.0  # three sides, none lost with its last vertex


def test_fit_circle_recovers_a_circle():
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    centre, radius, residual = fit_circle(np.stack([3 + 2 * np.cos(t), -1 + 2 * np.sin(t)], 1))
    assert np.allclose(centre, [3, -1]) and abs(radius - 2) < 1e-9 and residual < 1e-9
    assert fit_circle(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])) is None


def test_outputs_are_unit_norm_and_typed():
    segments = [disc(1.0, (0.0, 0.0)), grid(5.0, 25.0, 0.0, 20.0), grid(25.2, 40.0, 0.0, 20.0), disc(3.5, (-10.0, 0.0))]
    desc = torch.randn(4, 32, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 5.0
    out = convert(segments, desc, segment_ids=[10, 11, 12, 13])
    assert out.points_xy.dtype == torch.float64 and out.line_endpoints.dtype == torch.float64
    assert out.points_xy.shape[0] == 2 and out.line_endpoints.shape[0] >= 8
    for d in (out.point_descriptors, out.line_descriptors):
        assert torch.allclose(d.norm(dim=-1), torch.ones(len(d), dtype=torch.float64))
    assert set(out.line_segment_ids.tolist()) == {11, 12}
    assert set(out.point_segment_ids.tolist()) == {10, 13}
    out32 = convert(segments, desc.float())
    assert out32.line_endpoints.dtype == torch.float32


def test_long_lines_become_infinite_when_configured():
    cfg = PrimitiveConfig(line_len_to_infinite=15.0)
    out = segments_to_primitives([grid(0.0, 20.0, 0.0, 10.0)], torch.eye(2)[:1], cfg)
    long = torch.from_numpy(lengths(out.line_endpoints) > 15.0)
    assert long.sum() == 2
    assert (out.line_kinds[long] == int(LineKind.INFINITE)).all() and (out.line_kinds[~long] == int(LineKind.SEGMENT)).all()


def test_config_rejects_bad_values():
    with pytest.raises(ValidationError):
        PrimitiveConfig(line_merge_perp_dist_m=2.0, line_merge_dist_m=1.0)
    with pytest.raises(ValidationError):
        PrimitiveConfig(unknown_key=1.0)

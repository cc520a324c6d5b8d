"""The raster outline of a segment (`outline.mask_outline`) against the plain alpha shape of its pixel
centres, and segment conversion with it (`segments_to_primitives(..., segment_pixels=...)`)."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.config.mapping import PrimitiveConfig
from meridian_torch.mapping.primitives import outline
from meridian_torch.mapping.primitives.conversion import segments_to_primitives
from meridian_torch.mapping.primitives.outline import (
    RasterFrame,
    alpha_shape_outline,
    mask_outline,
    signed_area,
)

PIXEL_M = 0.3  # aerial pixels
ALPHA = 1.0  # alpha-shape radius 1 m
RADIUS_PX = 1.0 / ALPHA / PIXEL_M
FRAME = RasterFrame(x0=12.0, y0=-7.0, pixel_size_m=PIXEL_M)


@pytest.fixture(autouse=True)
def plain_alpha_shape(monkeypatch):
    """The reference: the alpha shape of every grid point (no boundary band)."""
    monkeypatch.setattr(outline, "BAND_MIN_POINTS", 10**9)


def pixels(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.nonzero(mask)
    return rows, cols


def alpha_polygon(mask: np.ndarray) -> shapely.Polygon | None:
    """The alpha shape of the pixel centres, in pixel (row, col) units."""
    rows, cols = pixels(mask)
    ring = alpha_shape_outline(FRAME.centres(rows, cols), ALPHA, 0.25)
    if ring is None:
        return None
    rc = np.stack([(FRAME.y0 - ring[:, 1]) / PIXEL_M - 0.5, (ring[:, 0] - FRAME.x0) / PIXEL_M - 0.5], axis=1)
    return shapely.Polygon(rc)


def mask_polygon(mask: np.ndarray) -> shapely.Polygon | None:
    ring = mask_outline(*pixels(mask), RADIUS_PX)
    return None if ring is None else shapely.Polygon(ring)


def same(a: shapely.Polygon, b: shapely.Polygon) -> bool:
    """Equal up to the rounding of the metric round trip of the reference."""
    return a.symmetric_difference(b).area < 1e-6


def test_raster_frame_centres():
    centres = FRAME.centres(np.array([0, 3]), np.array([0, 5]))
    np.testing.assert_array_equal(centres, [[12.0 + 0.5 * PIXEL_M, -7.0 - 0.5 * PIXEL_M],
                                            [12.0 + 5.5 * PIXEL_M, -7.0 - 3.5 * PIXEL_M]])


@given(h=st.integers(2, 40), w=st.integers(2, 40), r0=st.integers(-50, 50), c0=st.integers(-50, 50))
@settings(max_examples=40, deadline=None)
def test_rectangle_is_the_alpha_shape(h, w, r0, c0):
    mask = np.zeros((h + 4, w + 4), dtype=bool)
    mask[2 : 2 + h, 2 : 2 + w] = True
    ring = mask_outline(*pixels(mask), RADIUS_PX)
    assert ring is not None
    assert same(mask_polygon(mask), alpha_polygon(mask))
    assert abs(signed_area(ring)) == (h - 1) * (w - 1)
    rows, cols = pixels(mask)
    shifted = mask_outline(rows + r0, cols + c0, RADIUS_PX)  # translation moves the ring, nothing else
    np.testing.assert_array_equal(shifted, ring + [r0, c0])


@st.composite
def blobs(draw) -> np.ndarray:
    """Masks of 1-3 overlapping or separate discs and rectangles (notches, gaps, necks)."""
    mask = np.zeros((48, 48), dtype=bool)
    rr, cc = np.mgrid[:48, :48]
    for _ in range(draw(st.integers(1, 3))):
        r, c = draw(st.integers(6, 41)), draw(st.integers(6, 41))
        if draw(st.booleans()):
            radius = draw(st.floats(2.0, 9.0))
            mask |= (rr - r) ** 2 + (cc - c) ** 2 <= radius**2
        else:
            hh, ww = draw(st.integers(2, 14)), draw(st.integers(2, 14))
            mask[r - hh // 2 : r + hh - hh // 2, c - ww // 2 : c + ww - ww // 2] = True
    return mask


@given(mask=blobs())
@settings(max_examples=60, deadline=None)
def test_blobs_close_to_the_alpha_shape(mask):
    """Vertices are the segment's own pixels; where the alpha shape is one polygon of some size the
    raster outline is too and covers nearly the same area (the two differ only where a gap is
    about as wide as the alpha-shape diameter, or where the alpha shape touches itself)."""
    ring = mask_outline(*pixels(mask), RADIUS_PX)
    if ring is not None:
        assert mask[ring[:, 0].astype(int), ring[:, 1].astype(int)].all()
        assert shapely.Polygon(ring).area > 0
    reference = alpha_polygon(mask)
    if ring is None or reference is None or not reference.is_valid:
        return
    ours = shapely.Polygon(ring).buffer(0)
    assert ours.intersection(reference).area / ours.union(reference).area > 0.8


def test_gaps_bridged_below_the_alpha_diameter():
    for gap_px, joined in ((4, True), (6, True), (7, False), (12, False)):  # 2 / alpha = 6.7 px
        mask = np.zeros((30, 50), dtype=bool)
        mask[5:25, 5:20] = True
        mask[5:25, 20 + gap_px - 1 : 40] = True  # pixel centres gap_px apart across the gap
        assert (mask_outline(*pixels(mask), RADIUS_PX) is not None) == joined
        assert (alpha_polygon(mask) is not None) == joined


def test_pixel_lines_enclose_nothing():
    line = np.zeros((5, 40), dtype=bool)
    line[2, 3:35] = True
    assert mask_outline(*pixels(line), RADIUS_PX) is None
    assert alpha_polygon(line) is None

    block = np.zeros((30, 60), dtype=bool)
    block[5:25, 5:25] = True
    spur = block.copy()
    spur[15, 25:55] = True  # a spur one pixel wide: dropped but for its base, as by the alpha shape
    assert mask_polygon(spur).difference(mask_polygon(block).buffer(RADIUS_PX)).area == 0
    # the fillets where the spur meets the block differ by a few pixels (a 20 x 20 px block)
    assert mask_polygon(spur).symmetric_difference(alpha_polygon(spur)).area <= 10

    bridged = block.copy()
    bridged[5:25, 40:58] = True
    bridged[15, 25:40] = True  # two blocks joined by a line of pixels: not one polygon
    assert mask_outline(*pixels(bridged), RADIUS_PX) is None
    assert alpha_polygon(bridged) is None


def test_one_pixel_rim_opens_a_hole():
    for rim_px in (1, 2, 3):
        mask = np.ones((60, 60), dtype=bool)
        mask[10:50, rim_px:50] = False
        ours = mask_polygon(mask)
        assert ours.symmetric_difference(alpha_polygon(mask)).area <= 4  # corners of the opening
        assert ours.area < 59 * 59 / 2 if rim_px == 1 else ours.area == 59 * 59


def test_without_spurs_drops_out_and_back_runs():
    assert outline._without_spurs([1, 2, 3, 9, 8, 9, 3, 4]) == [1, 2, 3, 4]
    # a spur across the seam: 5 -> 6 -> 5 with the ring starting at the tip
    assert outline._without_spurs([6, 5, 1, 2, 3, 5]) == [5, 1, 2, 3]
    assert outline._without_spurs([1, 1, 2, 3, 3, 1]) == [1, 2, 3]


def test_conversion_with_pixels_matches_the_alpha_shape_on_simple_shapes():
    cfg = PrimitiveConfig(outline_simplify_m=0.0)  # every outline edge a fine line: no dependence on the ring's start
    masks = []
    building = np.zeros((120, 120), dtype=bool)
    building[20:80, 10:100] = True
    masks.append(building)
    tree = np.zeros((120, 120), dtype=bool)
    rr, cc = np.mgrid[:120, :120]
    tree |= (rr - 100) ** 2 + (cc - 60) ** 2 <= 4**2  # 5 m^2: a point
    masks.append(tree)
    rows_cols = [np.stack(pixels(m), axis=1) for m in masks]
    points = [FRAME.centres(rc[:, 0], rc[:, 1]) for rc in rows_cols]
    areas = np.array([len(p) * PIXEL_M**2 for p in points])
    desc = torch.eye(4)[:2]
    plain = segments_to_primitives(points, desc, cfg, areas_m2=areas)
    raster = segments_to_primitives(points, desc, cfg, areas_m2=areas, segment_pixels=rows_cols, raster_frame=FRAME)
    torch.testing.assert_close(raster.points_xy, plain.points_xy)
    assert len(plain.points_xy) == 1 and len(plain.line_endpoints) == 4
    plain_lines = sorted(map(tuple, np.round(plain.line_endpoints.double().numpy().reshape(-1, 4), 6)))
    raster_lines = sorted(map(tuple, np.round(raster.line_endpoints.double().numpy().reshape(-1, 4), 6)))
    assert plain_lines == raster_lines


def test_segment_pixels_need_their_frame():
    with pytest.raises(ValueError, match="raster_frame"):
        segments_to_primitives([np.zeros((4, 2))], torch.ones(1, 3), PrimitiveConfig(),
                               segment_pixels=[np.zeros((4, 2), dtype=np.int64)])

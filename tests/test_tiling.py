from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.io.ortho import Orthophoto
from meridian_torch.mapping.tiling import crop_offsets, tile_image


@settings(max_examples=60, deadline=None)
@given(
    st.integers(1, 700),
    st.integers(1, 700),
    st.sampled_from([0.1, 0.3, 0.5, 1.0]),
    st.sampled_from([0.0, 0.25, 0.5]),
)
def test_tiling_covers_every_pixel(width: int, height: int, mpp: float, overlap: float) -> None:
    grid = tile_image(width, height, mpp, (100.0, 500.0), 60.0, overlap)
    covered = np.zeros((height, width), dtype=np.int32)
    for c0, r0, c1, r1 in grid.pixel_boxes:
        assert 0 <= c0 < c1 <= width and 0 <= r0 < r1 <= height
        covered[r0:r1, c0:c1] += 1
    assert covered.min() >= 1
    patch_px = round(60.0 / mpp)
    sizes = grid.pixel_boxes[:, 2:] - grid.pixel_boxes[:, :2]
    # every patch has the full size unless the image itself is smaller
    assert np.all(sizes[:, 0] == min(patch_px, width)) and np.all(sizes[:, 1] == min(patch_px, height))
    # no two patches share a grid index
    assert len({tuple(g) for g in grid.grid_index}) == len(grid)


def test_world_geometry_matches_the_orthophoto_convention() -> None:
    ortho = Orthophoto(np.zeros((700, 450, 3), np.uint8), 0.3, (1000.0, 2000.0))
    grid = tile_image(450, 700, 0.3, ortho.origin_xy, 60.0, 0.5)
    for (c0, r0, c1, r1), (x_min, x_max, y_min, y_max), centre in zip(grid.pixel_boxes, grid.bounds_xy, grid.centres_xy):
        top_left = ortho.pixel_to_world(np.array([c0 - 0.5, r0 - 0.5]))  # pixel corner, not centre
        bottom_right = ortho.pixel_to_world(np.array([c1 - 0.5, r1 - 0.5]))
        assert np.allclose(top_left, [x_min, y_max]) and np.allclose(bottom_right, [x_max, y_min])
        assert np.allclose(centre, [(x_min + x_max) / 2, (y_min + y_max) / 2])
    # stride is half the patch: 30 m between neighbouring interior patch centres
    xs = np.unique(grid.centres_xy[:, 0].round(6))
    assert np.isclose(xs[1] - xs[0], 30.0)


def test_crop_offsets_spread_evenly() -> None:
    assert list(crop_offsets(200, 133)) == [0, 67]
    assert list(crop_offsets(100, 200)) == [0]
    offsets = crop_offsets(1000, 300)
    assert offsets[0] == 0 and offsets[-1] == 700 and len(offsets) == 4

"""Windowed orthophoto reading: every box equals the same box of the whole-image reader."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from meridian_torch.errors import OrthophotoError
from meridian_torch.io.ortho import Orthophoto, read_orthophoto, write_geotiff, write_orthophoto
from meridian_torch.io.ortho_source import open_orthophoto


def _random_boxes(width: int, height: int, n: int = 20) -> np.ndarray:
    rng = np.random.default_rng(3)
    c = np.sort(rng.integers(0, width + 1, (n, 2)), axis=1)
    r = np.sort(rng.integers(0, height + 1, (n, 2)), axis=1)
    c[:, 1] = np.maximum(c[:, 1], c[:, 0] + 1).clip(max=width)
    r[:, 1] = np.maximum(r[:, 1], r[:, 0] + 1).clip(max=height)
    c[:, 0] = np.minimum(c[:, 0], c[:, 1] - 1)
    r[:, 0] = np.minimum(r[:, 0], r[:, 1] - 1)
    return np.stack([c[:, 0], r[:, 0], c[:, 1], r[:, 1]], axis=1)


def _assert_boxes_equal(path: Path) -> None:
    whole = read_orthophoto(path)
    with open_orthophoto(path) as source:
        assert (source.meters_per_pixel, source.origin_xy, source.crs, source.size_px) == (
            whole.meters_per_pixel, whole.origin_xy, whole.crs, whole.size_px)
        for box in [np.array([0, 0, *whole.size_px]), *_random_boxes(*whole.size_px)]:
            part = source.read_box(box)
            assert part.dtype == np.uint8 and part.shape == (box[3] - box[1], box[2] - box[0], 3)
            np.testing.assert_array_equal(part, whole.read_box(box), err_msg=str(box))


def _ortho(h: int = 70, w: int = 90) -> Orthophoto:
    rng = np.random.default_rng(0)
    return Orthophoto(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), 0.3, (500000.0, 5200000.0), "EPSG:32632")


def _write_raw(path: Path, data: np.ndarray, nodata=None, tiled: bool = False) -> None:
    import rasterio
    from rasterio.transform import from_origin

    extra = {"tiled": True, "blockxsize": 16, "blockysize": 16} if tiled else {}
    with rasterio.open(path, "w", driver="GTiff", width=data.shape[2], height=data.shape[1], count=data.shape[0],
                       dtype=data.dtype, crs="EPSG:32632", nodata=nodata,
                       transform=from_origin(1000.0, 2000.0, 0.5, 0.5), **extra) as ds:
        ds.write(data)


def test_png_boxes(tmp_path: Path) -> None:
    write_orthophoto(tmp_path, _ortho())
    _assert_boxes_equal(tmp_path / "ortho.png")


def test_rgb_geotiff_boxes(tmp_path: Path) -> None:
    write_geotiff(tmp_path / "o.tif", _ortho())
    _assert_boxes_equal(tmp_path / "o.tif")


def test_tiled_geotiff_boxes(tmp_path: Path) -> None:
    _write_raw(tmp_path / "t.tif", np.moveaxis(_ortho(75, 83).image, -1, 0).copy(), tiled=True)
    _assert_boxes_equal(tmp_path / "t.tif")


def test_uint16_grey_with_nodata_is_stretched_by_the_whole_band(tmp_path: Path) -> None:
    data = np.tile(np.arange(100, dtype=np.uint16) * 100 + 1000, (50, 1))[None]
    data[0, :5, :5] = 0  # nodata
    _write_raw(tmp_path / "grey.tif", data, nodata=0, tiled=True)
    _assert_boxes_equal(tmp_path / "grey.tif")
    with open_orthophoto(tmp_path / "grey.tif") as source:
        left = source.read_box(np.array([0, 10, 10, 11]))
    assert left[0, 0, 0] == 0 and 0 < left[0, -1, 0] < 255, "stretched by the whole band, not the box"


def test_float_rgba_with_nan(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    data = rng.uniform(0.0, 1.0, (4, 40, 30)).astype(np.float32)
    data[3] = 1.0
    data[1, 3:7, 2:9] = np.nan
    _write_raw(tmp_path / "f.tif", data)
    _assert_boxes_equal(tmp_path / "f.tif")


def test_a_pickled_source_carries_the_path_not_the_handle(tmp_path: Path) -> None:
    write_geotiff(tmp_path / "o.tif", _ortho())
    write_orthophoto(tmp_path, _ortho())
    for path in (tmp_path / "o.tif", tmp_path / "ortho.png"):
        with open_orthophoto(path) as source:
            box = np.array([5, 7, 40, 30])
            expected = source.read_box(box)  # opened (or decoded) in this process
            copy = pickle.loads(pickle.dumps(source))
            assert copy._opened is None and len(pickle.dumps(source)) < 2_000
            np.testing.assert_array_equal(copy.read_box(box), expected)
            copy.close()
            assert source.content_sha256() == copy.content_sha256()


def test_open_checks_the_header_and_georeference(tmp_path: Path) -> None:
    write_orthophoto(tmp_path, _ortho())
    (tmp_path / "ortho.json").write_text('{"meters_per_pixel": -1, "origin": [0, 0]}')
    with pytest.raises(OrthophotoError, match="ortho.json: key 'meters_per_pixel' must be"):
        open_orthophoto(tmp_path)
    with pytest.raises(OrthophotoError, match="nothing: not found"):
        open_orthophoto(tmp_path / "nothing")

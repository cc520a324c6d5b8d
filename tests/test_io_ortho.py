"""Orthophotos: georeference convention, PNG+JSON and GeoTIFF reading/writing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.errors import OrthophotoError
from meridian_torch.io.ortho import (
    Orthophoto,
    check_orthophoto,
    read_orthophoto,
    write_geotiff,
    write_orthophoto,
)

SHARED = Path(__file__).resolve().parents[2] / "shared"


def make_ortho(h: int = 40, w: int = 60, crs: str | None = "EPSG:32632") -> Orthophoto:
    rng = np.random.default_rng(0)
    return Orthophoto(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), 0.3, (500000.0, 5200000.0), crs)


def write_geotiff_raw(path: Path, data: np.ndarray, crs: str | None, transform=None, nodata=None) -> None:
    import rasterio
    from rasterio.transform import from_origin

    with rasterio.open(
        path, "w", driver="GTiff", width=data.shape[2], height=data.shape[1], count=data.shape[0],
        dtype=data.dtype, crs=crs, nodata=nodata,
        transform=transform or from_origin(1000.0, 2000.0, 0.5, 0.5),
    ) as ds:
        ds.write(data)


@settings(max_examples=100, deadline=None)
@given(
    mpp=st.floats(0.01, 10.0),
    x0=st.floats(-1e6, 1e6),
    y0=st.floats(-1e7, 1e7),
    col=st.floats(-100.0, 5000.0),
    row=st.floats(-100.0, 5000.0),
)
def test_world_pixel_round_trip(mpp: float, x0: float, y0: float, col: float, row: float) -> None:
    ortho = Orthophoto(np.zeros((1, 1, 3), np.uint8), mpp, (x0, y0))
    colrow = np.array([col, row])
    np.testing.assert_allclose(ortho.world_to_pixel(ortho.pixel_to_world(colrow)), colrow, atol=1e-6)


def test_pixel_centre_convention() -> None:
    ortho = make_ortho()
    x0, y0 = ortho.origin_xy
    # Pixel (0, 0) centre is half a pixel right of and below the origin corner.
    np.testing.assert_allclose(ortho.pixel_to_world(np.array([0.0, 0.0])), [x0 + 0.15, y0 - 0.15])
    np.testing.assert_allclose(ortho.pixel_to_world(np.array([2.0, 3.0])), [x0 + 2.5 * 0.3, y0 - 3.5 * 0.3])
    np.testing.assert_allclose(ortho.world_to_pixel(np.array([x0, y0])), [-0.5, -0.5])
    # North up: increasing y (north) means decreasing row.
    assert ortho.world_to_pixel(np.array([x0, y0 + 1.0]))[1] < ortho.world_to_pixel(np.array([x0, y0]))[1]


@pytest.mark.parametrize("crs", [None, "EPSG:32632"])
def test_png_json_round_trip(tmp_path: Path, crs: str | None) -> None:
    ortho = make_ortho(crs=crs)
    write_orthophoto(tmp_path / "seq" / "aerial", ortho)
    assert json.loads((tmp_path / "seq/aerial/ortho.json").read_text()).get("crs") == crs
    for where in ("seq", "seq/aerial", "seq/aerial/ortho.png"):
        back = read_orthophoto(tmp_path / where)
        np.testing.assert_array_equal(back.image, ortho.image)
        assert (back.meters_per_pixel, back.origin_xy, back.crs) == (0.3, ortho.origin_xy, crs)
    assert check_orthophoto(tmp_path / "seq") == []
    # No temporary files left behind by the atomic writes.
    assert sorted(p.name for p in (tmp_path / "seq/aerial").iterdir()) == ["ortho.json", "ortho.png"]


def test_jpeg_with_own_json(tmp_path: Path) -> None:
    import cv2

    cv2.imwrite(str(tmp_path / "tile.jpg"), np.full((10, 20), 128, np.uint8))  # grey -> replicated
    (tmp_path / "tile.json").write_text('{"meters_per_pixel": 1.5, "origin": [10, 20]}')
    ortho = read_orthophoto(tmp_path / "tile.jpg")
    assert ortho.image.shape == (10, 20, 3) and ortho.meters_per_pixel == 1.5 and ortho.crs is None
    assert np.all(np.abs(ortho.image.astype(int) - 128) <= 1)


@pytest.mark.parametrize(
    ("georef", "key"),
    [
        ({"origin": [0, 0]}, "missing key 'meters_per_pixel'"),
        ({"meters_per_pixel": 0.3}, "missing key 'origin'"),
        ({"meters_per_pixel": -0.3, "origin": [0, 0]}, "key 'meters_per_pixel' must be"),
        ({"meters_per_pixel": 0.3, "origin": [0]}, "key 'origin' must be"),
        ({"meters_per_pixel": 0.3, "origin": [0, 0], "mpp": 1}, "unknown key 'mpp'"),
        ({"meters_per_pixel": 0.3, "origin": [0, 0], "crs": "EPSG:4326"}, "reproject it to UTM"),
    ],
)
def test_bad_ortho_json(tmp_path: Path, georef: dict, key: str) -> None:
    write_orthophoto(tmp_path, make_ortho(crs=None))
    (tmp_path / "ortho.json").write_text(json.dumps(georef))
    with pytest.raises(OrthophotoError, match="ortho.json") as info:
        read_orthophoto(tmp_path)
    assert key in str(info.value)
    assert any(key in p and "ortho.json" in p for p in check_orthophoto(tmp_path))


def test_missing_aerial_image_and_json(tmp_path: Path) -> None:
    (tmp_path / "aerial").mkdir()
    with pytest.raises(OrthophotoError, match="no orthophoto found"):
        read_orthophoto(tmp_path)
    write_orthophoto(tmp_path / "aerial", make_ortho())
    (tmp_path / "aerial/ortho.json").unlink()
    assert "ortho.json: file not found" in check_orthophoto(tmp_path)[0]


# Projected CRSs of real orthophotos, with a corner where such an orthophoto would be: UTM north
# and south, Swiss LV95 (7-digit eastings), British National Grid, Web Mercator.
PROJECTED = [
    ("EPSG:32632", (457944.9, 5429415.0)),
    ("EPSG:32755", (334000.0, 5812000.0)),
    ("EPSG:2056", (2600000.0, 1200000.0)),
    ("EPSG:27700", (530000.0, 180000.0)),
    ("EPSG:3857", (950000.0, 6000000.0)),
]


@pytest.mark.parametrize("crs, origin", PROJECTED)
def test_geotiff_round_trip(tmp_path: Path, crs: str, origin: tuple[float, float]) -> None:
    ortho = Orthophoto(make_ortho().image, 0.3, origin, crs)
    write_geotiff(tmp_path / "aerial" / "ortho.tif", ortho)
    back = read_orthophoto(tmp_path)
    np.testing.assert_array_equal(back.image, ortho.image)
    assert (back.meters_per_pixel, back.origin_xy, back.crs) == (0.3, origin, crs)
    assert check_orthophoto(tmp_path) == []


@pytest.mark.parametrize("crs, origin", PROJECTED)
def test_latlon_outputs_agree_with_pyproj(crs: str, origin: tuple[float, float]) -> None:
    from pyproj import Transformer

    from meridian_torch.io.results import to_latlon

    xy = np.asarray(origin) + np.random.default_rng(0).uniform(-5000.0, 5000.0, (50, 2))
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(xy[:, 0], xy[:, 1])
    latlon = to_latlon(xy, crs)
    np.testing.assert_allclose(latlon[:, 0], lat, atol=1e-9, rtol=0)  # 1e-9 deg: 0.1 mm
    np.testing.assert_allclose(latlon[:, 1], lon, atol=1e-9, rtol=0)


def test_geotiff_uint16_grey_stretch_and_nodata(tmp_path: Path) -> None:
    data = np.tile(np.arange(100, dtype=np.uint16) * 100 + 1000, (50, 1))[None]
    data[0, :5, :5] = 0  # nodata
    path = tmp_path / "grey.tif"
    write_geotiff_raw(path, data, "EPSG:32616", nodata=0)
    ortho = read_orthophoto(path)
    assert ortho.image.shape == (50, 100, 3) and ortho.image.dtype == np.uint8
    assert (ortho.meters_per_pixel, ortho.origin_xy, ortho.crs) == (0.5, (1000.0, 2000.0), "EPSG:32616")
    np.testing.assert_array_equal(ortho.image[..., 0], ortho.image[..., 2])  # grey replicated
    assert np.all(ortho.image[:5, :5] == 0)
    row = ortho.image[10, :, 0].astype(int)
    assert row[0] == 0 and row[-1] == 255 and np.all(np.diff(row) >= 0)  # 2..98 % stretch saturates ends


def test_geotiff_rgba_float_drops_alpha(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    data = rng.uniform(0.0, 1.0, (4, 20, 30)).astype(np.float32)
    data[3] = 1.0
    write_geotiff_raw(tmp_path / "f.tif", data, "EPSG:32632")
    assert read_orthophoto(tmp_path / "f.tif").image.shape == (20, 30, 3)


def test_geotiff_geographic_crs_is_an_error(tmp_path: Path) -> None:
    from rasterio.transform import from_origin

    data = np.zeros((3, 10, 10), np.uint8)
    write_geotiff_raw(tmp_path / "geo.tif", data, "EPSG:4326", transform=from_origin(8.5, 47.4, 1e-5, 1e-5))
    with pytest.raises(OrthophotoError, match=r"geo.tif: CRS EPSG:4326 is geographic.*reproject it to UTM"):
        read_orthophoto(tmp_path / "geo.tif")
    assert "geographic" in check_orthophoto(tmp_path / "geo.tif")[0]


def test_geotiff_rotated_or_non_square_is_an_error(tmp_path: Path) -> None:
    from affine import Affine

    data = np.zeros((3, 10, 10), np.uint8)
    write_geotiff_raw(tmp_path / "rot.tif", data, "EPSG:32632", transform=Affine(0.5, 0.1, 0, 0.1, -0.5, 0))
    with pytest.raises(OrthophotoError, match="rot.tif: geotransform is rotated"):
        read_orthophoto(tmp_path / "rot.tif")
    write_geotiff_raw(tmp_path / "rect.tif", data, "EPSG:32632", transform=Affine(0.5, 0, 0, 0, -0.6, 0))
    with pytest.raises(OrthophotoError, match="rect.tif: pixels are not square"):
        read_orthophoto(tmp_path / "rect.tif")
    write_geotiff_raw(tmp_path / "south.tif", data, "EPSG:32632", transform=Affine(0.5, 0, 0, 0, 0.5, 0))
    with pytest.raises(OrthophotoError, match="south.tif: image is not north-up"):
        read_orthophoto(tmp_path / "south.tif")


def test_real_spacenet_geotiff() -> None:
    path = SHARED / "data" / "solaris_spacenet" / "sample_geotiff.tif"
    if not path.is_file():
        pytest.skip(f"{path} not available")
    ortho = read_orthophoto(path)
    assert ortho.image.shape == (900, 900, 3) and ortho.image.dtype == np.uint8
    assert ortho.meters_per_pixel == pytest.approx(0.5)
    assert ortho.crs == "EPSG:32616"
    assert ortho.origin_xy == pytest.approx((733601.0, 3725139.0))
    assert 0 < ortho.image.mean() < 255

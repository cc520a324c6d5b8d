"""Georeferenced orthophotos: north-up RGB images with a metric world frame."""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from meridian_torch.errors import OrthophotoError
from meridian_torch.io.atomic import atomic_path, write_text_atomic

if TYPE_CHECKING:
    from rasterio.io import DatasetReader
    from rasterio.windows import Window

__all__ = [
    "Orthophoto",
    "ORTHO_NAMES",
    "find_orthophoto",
    "georeference_path",
    "read_orthophoto",
    "check_orthophoto",
    "write_orthophoto",
    "write_geotiff",
]


@dataclass(frozen=True)
class Orthophoto:
    """Pixel centre (col, row) lies at x = x0 + (col + 0.5) * mpp, y = y0 - (row + 0.5) * mpp."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    meters_per_pixel: float
    origin_xy: tuple[float, float]  # world x, y of the top-left corner of pixel (0, 0)
    crs: str | None = None  # projected CRS (e.g. "EPSG:32632") when world is georeferenced

    @property
    def size_px(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.image.shape[1], self.image.shape[0]

    def read_box(self, box: np.ndarray) -> np.ndarray:
        """(r1 - r0, c1 - c0, 3) uint8 pixels of the pixel box (c0, r0, c1, r1) (a view)."""
        c0, r0, c1, r1 = (int(v) for v in box)
        return self.image[r0:r1, c0:c1]

    def content_sha256(self) -> str:
        """Hex SHA-256 of the pixels (resumed builds check they describe the same image)."""
        return hashlib.sha256(np.ascontiguousarray(self.image).tobytes()).hexdigest()

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) world x, y -> (..., 2) continuous (col, row); pixel centres at integers."""
        xy = np.asarray(xy, dtype=np.float64)
        col = (xy[..., 0] - self.origin_xy[0]) / self.meters_per_pixel - 0.5
        row = (self.origin_xy[1] - xy[..., 1]) / self.meters_per_pixel - 0.5
        return np.stack([col, row], axis=-1)

    def pixel_to_world(self, colrow: np.ndarray) -> np.ndarray:
        colrow = np.asarray(colrow, dtype=np.float64)
        x = self.origin_xy[0] + (colrow[..., 0] + 0.5) * self.meters_per_pixel
        y = self.origin_xy[1] - (colrow[..., 1] + 0.5) * self.meters_per_pixel
        return np.stack([x, y], axis=-1)


ORTHO_NAMES = ("ortho.png", "ortho.jpg", "ortho.tif")  # looked up in this order
GEOTIFF_SUFFIXES = (".tif", ".tiff")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_GEOREF_KEYS = ("meters_per_pixel", "origin", "crs")
_STRETCH_PERCENTILES = (2.0, 98.0)


def find_orthophoto(path: str | os.PathLike[str]) -> Path:
    """The orthophoto image of a sequence folder, its aerial/ folder, or an image path itself.

    In a folder the first of ortho.png, ortho.jpg, ortho.tif that exists is used.
    """
    path = Path(path)
    if path.is_dir():
        folder = path / "aerial" if (path / "aerial").is_dir() else path
        for name in ORTHO_NAMES:
            if (folder / name).is_file():
                return folder / name
        raise OrthophotoError(f"{folder}: no orthophoto found (expected one of {', '.join(ORTHO_NAMES)})")
    if not path.is_file():
        raise OrthophotoError(f"{path}: not found")
    return path


def georeference_path(image_path: str | os.PathLike[str]) -> Path:
    """The JSON georeference of a PNG/JPEG orthophoto: `<stem>.json` if present, else ortho.json."""
    image_path = Path(image_path)
    own = image_path.with_suffix(".json")
    return own if own.is_file() else image_path.parent / "ortho.json"


def _is_number(v: object) -> bool:
    # bool is an int subclass, but `true` is never a valid coordinate.
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_crs(crs: object, where: str, problems: list[str]) -> str | None:
    """Validate that `crs` (text or rasterio CRS) is projected and metric; returns its text."""
    from rasterio.crs import CRS
    from rasterio.errors import CRSError

    try:
        parsed = crs if isinstance(crs, CRS) else CRS.from_user_input(crs)
    except CRSError as e:
        problems.append(f"{where}: unrecognised CRS {crs!r} ({e})")
        return None
    text = parsed.to_string()
    if parsed.is_geographic:
        problems.append(
            f"{where}: CRS {text} is geographic (degrees); the orthophoto must be in a projected metric "
            "CRS: reproject it to UTM, e.g. `gdalwarp -t_srs EPSG:326NN in.tif ortho.tif`"
        )
        return None
    if not parsed.is_projected:
        problems.append(f"{where}: CRS {text} is not a projected CRS; reproject the orthophoto to UTM")
        return None
    unit, factor = parsed.linear_units_factor
    if abs(factor - 1.0) > 1e-12:
        problems.append(f"{where}: CRS {text} is in {unit}, not metres; reproject the orthophoto to UTM")
        return None
    return crs if isinstance(crs, str) else text


def parse_georeference(
    path: Path, problems: list[str]
) -> tuple[float, tuple[float, float], str | None] | None:
    """(meters_per_pixel, origin, crs) from an ortho.json; None (and problems) if invalid."""
    n_before = len(problems)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        problems.append(f"{path}: file not found (the georeference of the orthophoto)")
        return None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        problems.append(f"{path}: not valid JSON ({e})")
        return None
    if not isinstance(data, dict):
        problems.append(f"{path}: expected a JSON object with keys {', '.join(_GEOREF_KEYS)}")
        return None
    for key in data:
        if key not in _GEOREF_KEYS:
            problems.append(f"{path}: unknown key {key!r} (allowed: {', '.join(_GEOREF_KEYS)})")
    for key in _GEOREF_KEYS[:2]:
        if key not in data:
            problems.append(f"{path}: missing key {key!r}")
    mpp = data.get("meters_per_pixel")
    if "meters_per_pixel" in data and not (_is_number(mpp) and mpp > 0):
        problems.append(f"{path}: key 'meters_per_pixel' must be a finite number > 0, got {mpp!r}")
    origin = data.get("origin")
    if "origin" in data and not (
        isinstance(origin, list) and len(origin) == 2 and all(_is_number(v) for v in origin)
    ):
        problems.append(f"{path}: key 'origin' must be [x0, y0] with finite numbers, got {origin!r}")
    crs = data.get("crs")
    if crs is not None:
        if isinstance(crs, str):
            crs = _check_crs(crs, f"{path}: key 'crs'", problems)
        else:
            problems.append(f"{path}: key 'crs' must be a string such as \"EPSG:32632\", got {crs!r}")
    if len(problems) > n_before:
        return None
    return float(mpp), (float(origin[0]), float(origin[1])), crs


def decode_rgb8(path: Path, problems: list[str]) -> np.ndarray | None:
    """8-bit PNG/JPEG -> (H, W, 3) uint8 RGB; grey is replicated, alpha dropped."""
    import cv2

    try:
        # np.fromfile + imdecode instead of imread: imread fails silently on non-ASCII paths.
        img = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except FileNotFoundError:
        problems.append(f"{path}: file not found")
        return None
    if img is None:
        problems.append(f"{path}: cannot decode image")
        return None
    if img.dtype != np.uint8:
        problems.append(f"{path}: {img.dtype} image; the orthophoto must be 8-bit (or a GeoTIFF)")
        return None
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    problems.append(f"{path}: {img.shape[2]} channels; expected grey, RGB or RGBA")
    return None


def geotiff_georeference(
    ds: DatasetReader, path: Path, problems: list[str]
) -> tuple[float, tuple[float, float], str | None] | None:
    n_before = len(problems)
    t = ds.transform
    if t.is_identity and ds.crs is None:
        problems.append(f"{path}: GeoTIFF has no georeference (no geotransform)")
        return None
    if t.b != 0 or t.d != 0:
        problems.append(
            f"{path}: geotransform is rotated or sheared; warp it north-up first (`gdalwarp in.tif out.tif`)"
        )
    elif t.a <= 0 or t.e >= 0:
        problems.append(
            f"{path}: image is not north-up (pixel size x {t.a}, y {t.e}; expected x > 0, y < 0)"
        )
    elif abs(t.a + t.e) > 1e-9 * t.a:
        problems.append(
            f"{path}: pixels are not square ({t.a} x {-t.e}); resample with `gdalwarp -tr RES RES`"
        )
    crs = _check_crs(ds.crs, f"{path}", problems) if ds.crs is not None else None
    if len(problems) > n_before:
        return None
    return float(t.a), (float(t.c), float(t.f)), crs


def geotiff_bands(ds: DatasetReader, path: Path, problems: list[str]) -> list[int] | None:
    """1-based band indexes giving R, G, B."""
    from rasterio.enums import ColorInterp

    interp = list(ds.colorinterp)
    rgb = [ColorInterp.red, ColorInterp.green, ColorInterp.blue]
    if all(c in interp for c in rgb):
        return [interp.index(c) + 1 for c in rgb]
    if ds.count in (1, 2):  # grey, or grey + alpha
        return [1, 1, 1]
    if ds.count in (3, 4):  # RGB, or RGB + alpha
        return [1, 2, 3]
    problems.append(f"{path}: {ds.count} bands without RGB colour interpretation; expected 1, 3 or 4 bands")
    return None


def stretch_limits(band: np.ndarray, valid: np.ndarray) -> tuple[float, float] | None:
    """The band values stretched to 0 and 255 (2nd and 98th percentiles of the valid pixels);
    None when no pixel is valid."""
    values = band[valid]
    if values.size == 0:
        return None
    lo, hi = np.percentile(values, _STRETCH_PERCENTILES)
    return float(lo), float(hi)


def stretch_to_uint8(band: np.ndarray, limits: tuple[float, float] | None) -> np.ndarray:
    """A non-8-bit band (or any box of it) stretched linearly by `limits` (stretch_limits)."""
    if limits is None:
        return np.zeros(band.shape, dtype=np.uint8)
    lo, hi = limits
    scaled = (band.astype(np.float64) - lo) / max(hi - lo, np.finfo(np.float64).tiny)
    return np.round(np.clip(np.nan_to_num(scaled), 0.0, 1.0) * 255.0).astype(np.uint8)


def geotiff_layout(
    ds: DatasetReader, path: Path
) -> tuple[tuple[float, tuple[float, float], str | None], list[int]]:
    """(georeference, RGB band indexes) of an open GeoTIFF; its first problem raises OrthophotoError."""
    problems: list[str] = []
    georef = geotiff_georeference(ds, path, problems)
    bands = geotiff_bands(ds, path, problems)
    if problems:
        raise OrthophotoError(problems[0])
    assert georef is not None and bands is not None
    return georef, bands


def read_geotiff_bands(
    ds: DatasetReader, bands: list[int], window: Window | None = None
) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """The distinct `bands` of `window` (None: the whole image) and the mask of its valid pixels
    (nodata values, alpha band, internal masks, non-finite floats in any band)."""
    unique = sorted(set(bands))
    data = dict(zip(unique, ds.read(unique, window=window)))
    valid = ds.dataset_mask(window=window) != 0
    for b in unique:
        if np.issubdtype(data[b].dtype, np.floating):
            valid &= np.isfinite(data[b])
    return data, valid


def geotiff_rgb(
    data: dict[int, np.ndarray], valid: np.ndarray, bands: list[int],
    limits: dict[int, tuple[float, float] | None],
) -> np.ndarray:
    """(H, W, 3) uint8 RGB from read_geotiff_bands; non-8-bit bands stretched by their `limits`."""
    converted = {b: v if v.dtype == np.uint8 else stretch_to_uint8(v, limits[b]) for b, v in data.items()}
    image = np.stack([converted[b] for b in bands], axis=-1)
    image[~valid] = 0
    return np.ascontiguousarray(image)


def open_geotiff(path: Path) -> DatasetReader:
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    try:
        with warnings.catch_warnings():
            # A missing georeference is reported as an error below, not as a warning.
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            return rasterio.open(path)
    except RasterioIOError as e:
        raise OrthophotoError(f"{path}: cannot open GeoTIFF ({e})") from e


def _read_geotiff(path: Path) -> Orthophoto:
    with open_geotiff(path) as ds:
        georef, bands = geotiff_layout(ds, path)
        data, valid = read_geotiff_bands(ds, bands)
    limits = {b: stretch_limits(v, valid) for b, v in data.items() if v.dtype != np.uint8}
    mpp, origin, crs = georef
    return Orthophoto(geotiff_rgb(data, valid, bands, limits), mpp, origin, crs)


def read_orthophoto(path: str | os.PathLike[str]) -> Orthophoto:
    """Read an orthophoto from a sequence folder, its aerial/ folder, a PNG/JPEG or a GeoTIFF.

    PNG/JPEG: 8-bit, georeferenced by `<stem>.json` or `ortho.json` next to it (README, Formats).
    GeoTIFF: must be north-up with square pixels and, if it has a CRS, a projected metric one;
    1 band is grey (replicated to RGB), 4 bands are RGBA (alpha dropped), bands with RED/GREEN/
    BLUE colour interpretation are used as such. Non-8-bit bands (uint16, float) are linearly
    stretched per band so that their 2nd..98th percentiles (over valid pixels) map to 0..255.
    Nodata / masked pixels become 0. Raises OrthophotoError naming the file and problem.
    """
    image_path = find_orthophoto(path)
    suffix = image_path.suffix.lower()
    if suffix in GEOTIFF_SUFFIXES:
        return _read_geotiff(image_path)
    if suffix not in IMAGE_SUFFIXES:
        raise OrthophotoError(f"{image_path}: unsupported orthophoto type (expected PNG, JPEG or GeoTIFF)")
    problems: list[str] = []
    georef = parse_georeference(georeference_path(image_path), problems)
    image = decode_rgb8(image_path, problems) if not problems else None
    if problems:
        raise OrthophotoError(problems[0])
    assert georef is not None and image is not None
    mpp, origin, crs = georef
    return Orthophoto(image, mpp, origin, crs)


def check_orthophoto(path: str | os.PathLike[str]) -> list[str]:
    """Every problem of an orthophoto (see read_orthophoto); empty list if it is valid.

    A GeoTIFF is only checked from its header (georeference, CRS, bands), as it may be huge.
    """
    try:
        image_path = find_orthophoto(path)
    except OrthophotoError as e:
        return [str(e)]
    suffix = image_path.suffix.lower()
    problems: list[str] = []
    if suffix in GEOTIFF_SUFFIXES:
        try:
            with open_geotiff(image_path) as ds:
                geotiff_georeference(ds, image_path, problems)
                geotiff_bands(ds, image_path, problems)
        except OrthophotoError as e:
            problems.append(str(e))
    elif suffix in IMAGE_SUFFIXES:
        parse_georeference(georeference_path(image_path), problems)
        decode_rgb8(image_path, problems)
    else:
        problems.append(f"{image_path}: unsupported orthophoto type (expected PNG, JPEG or GeoTIFF)")
    return problems


def _validate_for_writing(ortho: Orthophoto) -> None:
    img = ortho.image
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"orthophoto image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
    if not (_is_number(ortho.meters_per_pixel) and ortho.meters_per_pixel > 0):
        raise ValueError(f"meters_per_pixel must be finite and > 0, got {ortho.meters_per_pixel}")
    if not all(_is_number(v) for v in ortho.origin_xy):
        raise ValueError(f"origin_xy must be finite, got {ortho.origin_xy}")


def write_orthophoto(folder: str | os.PathLike[str], ortho: Orthophoto) -> None:
    """Write `folder`/ortho.png and `folder`/ortho.json (README, Formats), each atomically."""
    import cv2

    _validate_for_writing(ortho)
    folder = Path(folder)
    with atomic_path(folder / "ortho.png") as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(ortho.image, cv2.COLOR_RGB2BGR)):
            raise OSError(f"cannot write {folder / 'ortho.png'}")
    georef: dict[str, object] = {
        "meters_per_pixel": float(ortho.meters_per_pixel),
        "origin": [float(ortho.origin_xy[0]), float(ortho.origin_xy[1])],
    }
    if ortho.crs is not None:
        georef["crs"] = ortho.crs
    write_text_atomic(folder / "ortho.json", json.dumps(georef, indent=1) + "\n")


def write_geotiff(path: str | os.PathLike[str], ortho: Orthophoto) -> None:
    """Write `ortho` as an RGB GeoTIFF (deflate) georeferenced by its geotransform and CRS, atomically."""
    import rasterio
    from rasterio.transform import from_origin

    _validate_for_writing(ortho)
    height, width = ortho.image.shape[:2]
    mpp = ortho.meters_per_pixel
    transform = from_origin(ortho.origin_xy[0], ortho.origin_xy[1], mpp, mpp)
    with atomic_path(path) as tmp:
        with rasterio.open(
            tmp, "w", driver="GTiff", width=width, height=height, count=3, dtype="uint8",
            crs=ortho.crs, transform=transform, photometric="RGB", compress="deflate",
        ) as ds:
            ds.write(np.moveaxis(ortho.image, -1, 0))

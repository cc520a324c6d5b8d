"""Orthophoto files read one pixel box at a time (windowed reading for maps of whole regions).

`open_orthophoto` reads the georeference and size from the header; `OrthophotoSource.read_box`
returns the same pixels as `read_orthophoto(path).image[r0:r1, c0:c1]`, bit for bit.

- GeoTIFF: each box is read through a rasterio window, so a tiled (or COG) GeoTIFF costs memory
  for the box and the tiles it touches (GDAL's tile cache is held to 64 MiB), not for the image.
  A striped (untiled) GeoTIFF works too, but each box then decodes whole rows. Non-8-bit bands are stretched by
  percentiles of the whole band (io.ortho), which `open_orthophoto` computes once by reading the
  bands whole; only the limits are kept, and copies sent to other processes carry them.
- PNG/JPEG: the codecs cannot decode part of an image, so the whole image is decoded on the first
  read, once per process, and kept for the next boxes. Use a GeoTIFF for large areas.

A source sent to another process (pickled) carries its path, not its pixels or file handle: each
process opens the file itself on its first read.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from meridian_torch.errors import OrthophotoError
from meridian_torch.io.ortho import (
    GEOTIFF_SUFFIXES,
    IMAGE_SUFFIXES,
    decode_rgb8,
    find_orthophoto,
    georeference_path,
    geotiff_layout,
    geotiff_rgb,
    open_geotiff,
    parse_georeference,
    read_geotiff_bands,
    stretch_limits,
)

__all__ = ["OrthophotoSource", "open_orthophoto"]

_HASH_CHUNK_BYTES = 1 << 20
# GDAL's tile cache while reading boxes. Its default (5 % of RAM) filled with every tile read: 4 km^2
# read patch by patch grew by 300 MiB. Patches come row by row, so the cache needs the tiles of
# about one patch row: 512 px RGB tiles across a 25 km^2 (16 667 px) image are about 50 MiB.
_GDAL_CACHE_BYTES = 64 << 20


@dataclass(eq=False)
class OrthophotoSource:
    """An orthophoto file: georeference and size (as `Orthophoto`), pixels read by box."""

    path: Path
    meters_per_pixel: float
    origin_xy: tuple[float, float]  # world x, y of the top-left corner of pixel (0, 0)
    size_px: tuple[int, int]  # (width, height)
    crs: str | None = None
    bands: list[int] | None = None  # GeoTIFF: 1-based band indexes giving R, G, B; None: PNG/JPEG
    stretch: dict[int, tuple[float, float] | None] = field(default_factory=dict)  # non-8-bit bands
    _opened: Any = field(default=None, init=False, repr=False)  # rasterio dataset or decoded image

    def read_box(self, box: np.ndarray) -> np.ndarray:
        """(r1 - r0, c1 - c0, 3) uint8 RGB of the pixel box (c0, r0, c1, r1)."""
        c0, r0, c1, r1 = (int(v) for v in box)
        if self.bands is None:
            return self._decoded()[r0:r1, c0:c1]
        import rasterio
        from rasterio.windows import Window

        if self._opened is None:
            self._opened = open_geotiff(self.path)
        with rasterio.Env(GDAL_CACHEMAX=_GDAL_CACHE_BYTES):
            data, valid = read_geotiff_bands(self._opened, self.bands, Window(c0, r0, c1 - c0, r1 - r0))
        return geotiff_rgb(data, valid, self.bands, self.stretch)

    def _decoded(self) -> np.ndarray:
        if self._opened is None:
            problems: list[str] = []
            image = decode_rgb8(self.path, problems)
            if problems:
                raise OrthophotoError(problems[0])
            assert image is not None
            if (image.shape[1], image.shape[0]) != self.size_px:
                raise OrthophotoError(f"{self.path}: decoded {image.shape[1]}x{image.shape[0]} px, "
                                      f"header said {self.size_px[0]}x{self.size_px[1]}")
            self._opened = image
        return self._opened

    def content_sha256(self) -> str:
        """Hex SHA-256 of the file's bytes, read in chunks (resumed builds check the file is the same)."""
        digest = hashlib.sha256()
        with open(self.path, "rb") as fh:
            while chunk := fh.read(_HASH_CHUNK_BYTES):
                digest.update(chunk)
        return digest.hexdigest()

    def close(self) -> None:
        """Close the file or drop the decoded image (a later read opens it again)."""
        if hasattr(self._opened, "close"):
            self._opened.close()
        self._opened = None

    def __enter__(self) -> OrthophotoSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> dict[str, Any]:
        return {**vars(self), "_opened": None}  # file handles are not picklable; each process opens its own


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, UnidentifiedImageError) as e:
        raise OrthophotoError(f"{path}: cannot read the image header ({e})") from e


def open_orthophoto(path: str | os.PathLike[str]) -> OrthophotoSource:
    """The orthophoto of a sequence folder, its aerial/ folder, a PNG/JPEG or a GeoTIFF, as a source
    that reads boxes (formats and errors as `read_orthophoto`; pixels are checked when read)."""
    image_path = find_orthophoto(path)
    suffix = image_path.suffix.lower()
    problems: list[str] = []
    if suffix in GEOTIFF_SUFFIXES:
        with open_geotiff(image_path) as ds:
            georef, bands = geotiff_layout(ds, image_path)
            size = (ds.width, ds.height)
            stretch: dict[int, tuple[float, float] | None] = {}
            if any(np.dtype(ds.dtypes[b - 1]) != np.uint8 for b in bands):  # limits need the whole bands
                data, valid = read_geotiff_bands(ds, bands)
                stretch = {b: stretch_limits(v, valid) for b, v in data.items() if v.dtype != np.uint8}
                del data, valid
        return OrthophotoSource(image_path, georef[0], georef[1], size, georef[2], bands, stretch)
    if suffix not in IMAGE_SUFFIXES:
        raise OrthophotoError(f"{image_path}: unsupported orthophoto type (expected PNG, JPEG or GeoTIFF)")
    georef = parse_georeference(georeference_path(image_path), problems)
    if problems:
        raise OrthophotoError(problems[0])
    assert georef is not None
    return OrthophotoSource(image_path, georef[0], georef[1], _image_size(image_path), georef[2])

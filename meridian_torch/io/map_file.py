"""The aerial map file (`.mtm`), format version 3.

A `.mtm` file is a zip archive (numpy `.npz` layout) holding:
- `header.json` (stored as a uint8 array): `format` = "meridian-torch aerial map",
  `format_version`, `package_version`, `georeference` (meters_per_pixel, origin [x0, y0],
  crs, image_size [width, height], local_origin [x, y]: the world position of the map frame's
  origin, version 2 on), `config` (the resolved config blocks that shaped the map),
  `backends` (segmenter / describer names), `source` (orthophoto path and sha256),
  `content_hash` (sha256 over the rest of the header and every array);
- padded per-patch arrays, P patches:
  `patch_pixel_boxes (P, 4) int64` col0, row0, col1, row1 in the orthophoto;
  `patch_grid_index (P, 2) int64`; `patch_bounds_xy (P, 4) float64` x_min, x_max, y_min, y_max;
  `patch_centres_xy (P, 2) float64`;
  `points_xy (P, Np, 2)`, `point_descriptors (P, Np, D)`, `point_valid (P, Np) bool`;
  `line_endpoints (P, Nl, 2, 2)`, `line_kinds (P, Nl) int64` (0 segment, 1 ray, 2 infinite),
  `line_descriptors (P, Nl, D)`, `line_valid (P, Nl) bool`;
  `global_descriptors (P, Dg)`.
All coordinates are metres (x east, y north) in the map frame: world minus `local_origin`, so
that float32 arrays stay exact to the millimetre in a projected CRS (UTM northings are ~5e6 m).
Version 1 files (world coordinates, no local origin) are read with a local origin of (0, 0).
Version 3 stores the arrays uncompressed at aligned offsets (`io.npz_container`), so a map is
opened as memory maps of the file: only the pages a reader touches come into memory, and the
kernel can drop them again. Versions 1 and 2 (compressed) are read whole into memory.
Files are written atomically, from a map in memory (`save_aerial_map`) or patch by patch
(`save_aerial_map_patches`: the same file, holding one block of patches at a time).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meridian_torch.errors import MeridianError
from meridian_torch.io.npz_container import StreamedArray, read_container, write_container
from meridian_torch.types import AerialMap, PatchGrid, PrimitiveBatch

__all__ = [
    "MAP_FORMAT", "MAP_FORMAT_VERSION", "MapFileError", "PatchReader", "georeference_mismatches", "load_aerial_map",
    "save_aerial_map", "save_aerial_map_patches",
]

MAP_FORMAT = "meridian-torch aerial map"
MAP_FORMAT_VERSION = 3
_READABLE_VERSIONS = (1, 2, 3)  # version 1: world coordinates = map frame; 1 and 2: compressed

_PRIMITIVE_FIELDS = (
    "points_xy", "point_descriptors", "point_valid",
    "line_endpoints", "line_kinds", "line_descriptors", "line_valid",
)
_PATCH_FIELDS = ("global_descriptors", *(name for name in _PRIMITIVE_FIELDS if not name.endswith("_valid")))
_BLOCK_PATCHES = 256  # patches per block written by save_aerial_map_patches

PatchReader = Callable[[int, tuple[str, ...]], dict[str, np.ndarray]]
"""(patch index, names) -> that patch's arrays, unpadded: `global_descriptors` (Dg,), `points_xy`
(Np, 2), `point_descriptors` (Np, D), `line_endpoints` (Nl, 2, 2), `line_kinds` (Nl,),
`line_descriptors` (Nl, D)."""


class MapFileError(MeridianError):
    """An aerial map file is unreadable, corrupted, or from another version or config."""


def _grid_arrays(patches: PatchGrid) -> dict[str, np.ndarray]:
    return {
        "patch_pixel_boxes": np.ascontiguousarray(patches.pixel_boxes),
        "patch_grid_index": np.ascontiguousarray(patches.grid_index),
        "patch_bounds_xy": np.ascontiguousarray(patches.bounds_xy),
        "patch_centres_xy": np.ascontiguousarray(patches.centres_xy),
    }


def _arrays(aerial_map: AerialMap) -> dict[str, np.ndarray]:
    arrays = {**_grid_arrays(aerial_map.patches), "global_descriptors": aerial_map.global_descriptors.detach().cpu().numpy()}
    for name in _PRIMITIVE_FIELDS:
        arrays[name] = getattr(aerial_map.primitives, name).detach().cpu().numpy()
    return {k: np.ascontiguousarray(v) for k, v in arrays.items()}


def _header(aerial_map: AerialMap) -> dict[str, Any]:
    return _header_of(aerial_map.meters_per_pixel, aerial_map.origin_xy, aerial_map.image_size,
                      aerial_map.local_origin_xy, aerial_map.crs, aerial_map.config, aerial_map.backends,
                      aerial_map.source)


def _header_of(
    meters_per_pixel: float, origin_xy: tuple[float, float], image_size: tuple[int, int],
    local_origin_xy: tuple[float, float], crs: str | None, config: dict[str, Any], backends: dict[str, str],
    source: dict[str, str],
) -> dict[str, Any]:
    return {
        "georeference": {
            "meters_per_pixel": meters_per_pixel,
            "origin": list(origin_xy),
            "crs": crs,
            "image_size": list(image_size),
            "local_origin": [float(v) for v in local_origin_xy],
        },
        "config": config,
        "backends": backends,
        "source": source,
    }


def save_aerial_map(aerial_map: AerialMap, path: Path) -> str:
    """Write `aerial_map` to `path` atomically and return its content hash."""
    digest = write_container(
        path, MAP_FORMAT, MAP_FORMAT_VERSION, _header(aerial_map), _arrays(aerial_map), compressed=False
    )
    aerial_map.content_hash = digest
    return digest


def save_aerial_map_patches(
    path: Path, patches: PatchGrid, read_patch: PatchReader, *, meters_per_pixel: float,
    origin_xy: tuple[float, float], image_size: tuple[int, int], local_origin_xy: tuple[float, float],
    crs: str | None, config: dict[str, Any], backends: dict[str, str], source: dict[str, str],
) -> str:
    """Write the map of `patches` to `path` atomically, reading each patch's arrays from `read_patch`,
    and return its content hash: the file `save_aerial_map` writes for the same patches (padded as
    `types.stack_primitive_sets` pads them), holding one block of patches at a time instead of
    the map. Every patch is read once for its point and line counts (the padded widths), then
    once for each array; the other arguments are the `AerialMap` fields of the same names."""
    if len(patches) == 0:
        raise ValueError("an aerial map needs at least one patch")
    counts = np.array([[len(arrays["points_xy"]), len(arrays["line_kinds"])]
                       for arrays in (read_patch(i, ("points_xy", "line_kinds")) for i in range(len(patches)))])
    first = read_patch(0, _PATCH_FIELDS)  # dtypes and trailing shapes
    arrays: dict[str, np.ndarray | StreamedArray] = {
        **_grid_arrays(patches),
        "global_descriptors": _streamed(read_patch, "global_descriptors", len(patches), first["global_descriptors"]),
    }
    for name in _PRIMITIVE_FIELDS:
        patch_counts = counts[:, 0 if name.startswith("point") else 1]
        if name.endswith("_valid"):
            arrays[name] = _streamed_valid(patch_counts)
        else:
            arrays[name] = _streamed(read_patch, name, len(patches), first[name], patch_counts)
    header = _header_of(meters_per_pixel, origin_xy, image_size, local_origin_xy, crs, config, backends, source)
    return write_container(path, MAP_FORMAT, MAP_FORMAT_VERSION, header, arrays, compressed=False)


def _patch_blocks(n_patches: int) -> Iterator[range]:
    for start in range(0, n_patches, _BLOCK_PATCHES):
        yield range(start, min(start + _BLOCK_PATCHES, n_patches))


def _streamed(
    read_patch: PatchReader, name: str, n_patches: int, first: np.ndarray, counts: np.ndarray | None = None
) -> StreamedArray:
    """Array `name` of every patch, stacked, or with `counts` (rows per patch) padded with zeros
    to the largest count."""
    row_shape = first.shape if counts is None else (int(counts.max()), *first.shape[1:])

    def blocks() -> Iterator[np.ndarray]:
        for block_range in _patch_blocks(n_patches):
            block = np.zeros((len(block_range), *row_shape), first.dtype)
            for k, i in enumerate(block_range):
                array = read_patch(i, (name,))[name]
                expected = first.shape if counts is None else (int(counts[i]), *first.shape[1:])
                if array.shape != expected or array.dtype != first.dtype:
                    raise ValueError(f"patch {i}: {name} is {array.dtype} {array.shape}, expected {first.dtype} {expected}")
                block[k, : len(array)] = array
            yield block

    return StreamedArray(first.dtype, (n_patches, *row_shape), blocks)


def _streamed_valid(counts: np.ndarray) -> StreamedArray:
    """Which padded rows of each patch hold a primitive."""
    width = int(counts.max())

    def blocks() -> Iterator[np.ndarray]:
        for block_range in _patch_blocks(len(counts)):
            yield np.arange(width)[None, :] < counts[block_range.start : block_range.stop, None]

    return StreamedArray(np.dtype(bool), (len(counts), width), blocks)


def _config_differences(stored: Any, expected: Any, prefix: str = "") -> list[str]:
    if isinstance(stored, dict) and isinstance(expected, dict):
        diffs = []
        for key in sorted(set(stored) | set(expected)):
            diffs += _config_differences(stored.get(key), expected.get(key), f"{prefix}{key}.")
        return diffs
    return [] if stored == expected else [f"{prefix.rstrip('.')}: file has {stored!r}, expected {expected!r}"]


def load_aerial_map(path: Path, expected_config: dict[str, Any] | None = None) -> AerialMap:
    """Read and verify a map file; `expected_config` (if given) must equal the stored config.

    The arrays of a version 3 file are memory maps of it (copy-on-write: writing to a tensor never
    changes the file); the whole file is hashed first, in chunks, without keeping it in memory."""
    header, arrays = read_container(path, MAP_FORMAT, _READABLE_VERSIONS, MapFileError, "aerial map file", "rebuild the map")
    if expected_config is not None:
        diffs = _config_differences(header["config"], expected_config)
        if diffs:
            raise MapFileError(f"{path}: built with another config; rebuild the map. Differences: " + "; ".join(diffs))
    geo = header["georeference"]
    return AerialMap(
        patches=PatchGrid(
            pixel_boxes=arrays["patch_pixel_boxes"],
            grid_index=arrays["patch_grid_index"],
            bounds_xy=arrays["patch_bounds_xy"],
            centres_xy=arrays["patch_centres_xy"],
        ),
        primitives=PrimitiveBatch(**{name: torch.from_numpy(arrays[name]) for name in _PRIMITIVE_FIELDS}),
        global_descriptors=torch.from_numpy(arrays["global_descriptors"]),
        meters_per_pixel=float(geo["meters_per_pixel"]),
        origin_xy=(float(geo["origin"][0]), float(geo["origin"][1])),
        image_size=(int(geo["image_size"][0]), int(geo["image_size"][1])),
        crs=geo.get("crs"),
        config=header["config"],
        backends=header["backends"],
        source=header["source"],
        content_hash=header["content_hash"],
        local_origin_xy=tuple(float(v) for v in geo.get("local_origin", (0.0, 0.0))),
    )


def georeference_mismatches(aerial_map: AerialMap, ortho: Any) -> list[str]:
    """How the map's georeference differs from an orthophoto's (`io.ortho.Orthophoto`): CRS, pixel
    size, origin (to a thousandth of a pixel) and image size. Empty when the map was built from it
    (or from imagery of the same extent and grid)."""
    problems = []
    if aerial_map.crs != ortho.crs:
        problems.append(f"CRS {aerial_map.crs} vs {ortho.crs}")
    if not np.isclose(aerial_map.meters_per_pixel, ortho.meters_per_pixel, rtol=1e-9, atol=0.0):
        problems.append(f"meters_per_pixel {aerial_map.meters_per_pixel} vs {ortho.meters_per_pixel}")
    offset = np.subtract(aerial_map.origin_xy, ortho.origin_xy)
    if np.abs(offset).max() > 1e-3 * ortho.meters_per_pixel:
        problems.append(f"origin {list(aerial_map.origin_xy)} vs {list(ortho.origin_xy)} "
                        f"({np.hypot(*offset):.3f} m apart)")
    if tuple(aerial_map.image_size) != tuple(ortho.size_px):
        problems.append(f"image size {list(aerial_map.image_size)} vs {list(ortho.size_px)} px")
    return problems

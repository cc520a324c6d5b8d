"""The aerial map file (`.mtm`), format version 1.

A `.mtm` file is a zip archive (numpy `.npz` layout) holding:
- `header.json` (stored as a uint8 array): `format` = "meridian-torch aerial map",
  `format_version`, `package_version`, `georeference` (meters_per_pixel, origin [x0, y0],
  crs, image_size [width, height]), `config` (the resolved config blocks that shaped the map),
  `backends` (segmenter / describer names), `source` (orthophoto path and sha256),
  `content_hash` (sha256 over the rest of the header and every array);
- padded per-patch arrays, P patches:
  `patch_pixel_boxes (P, 4) int64` col0, row0, col1, row1 in the orthophoto;
  `patch_grid_index (P, 2) int64`; `patch_bounds_xy (P, 4) float64` world x_min, x_max, y_min, y_max;
  `patch_centres_xy (P, 2) float64`;
  `points_xy (P, Np, 2)`, `point_descriptors (P, Np, D)`, `point_valid (P, Np) bool`;
  `line_endpoints (P, Nl, 2, 2)`, `line_kinds (P, Nl) int64` (0 segment, 1 ray, 2 infinite),
  `line_descriptors (P, Nl, D)`, `line_valid (P, Nl) bool`;
  `global_descriptors (P, Dg)`.
All coordinates are world metres (x east, y north). Files are written atomically.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meridian_torch import __version__
from meridian_torch.errors import MeridianError
from meridian_torch.io.atomic import atomic_path
from meridian_torch.mapping.tiling import PatchGrid
from meridian_torch.types import PrimitiveBatch

__all__ = ["MAP_FORMAT", "MAP_FORMAT_VERSION", "AerialMap", "MapFileError", "save_aerial_map", "load_aerial_map"]

MAP_FORMAT = "meridian-torch aerial map"
MAP_FORMAT_VERSION = 1

_PRIMITIVE_FIELDS = (
    "points_xy", "point_descriptors", "point_valid",
    "line_endpoints", "line_kinds", "line_descriptors", "line_valid",
)


class MapFileError(MeridianError):
    """An aerial map file is unreadable, corrupted, or from another version or config."""


@dataclass
class AerialMap:
    patches: PatchGrid
    primitives: PrimitiveBatch
    global_descriptors: torch.Tensor  # (P, Dg)
    meters_per_pixel: float
    origin_xy: tuple[float, float]
    image_size: tuple[int, int]  # (width, height) of the orthophoto in pixels
    crs: str | None = None
    config: dict[str, Any] = field(default_factory=dict)
    backends: dict[str, str] = field(default_factory=dict)
    source: dict[str, str] = field(default_factory=dict)
    content_hash: str = ""

    def __len__(self) -> int:
        return len(self.patches)


def _arrays(aerial_map: AerialMap) -> dict[str, np.ndarray]:
    arrays = {
        "patch_pixel_boxes": aerial_map.patches.pixel_boxes,
        "patch_grid_index": aerial_map.patches.grid_index,
        "patch_bounds_xy": aerial_map.patches.bounds_xy,
        "patch_centres_xy": aerial_map.patches.centres_xy,
        "global_descriptors": aerial_map.global_descriptors.detach().cpu().numpy(),
    }
    for name in _PRIMITIVE_FIELDS:
        arrays[name] = getattr(aerial_map.primitives, name).detach().cpu().numpy()
    return {k: np.ascontiguousarray(v) for k, v in arrays.items()}


def _header(aerial_map: AerialMap) -> dict[str, Any]:
    return {
        "format": MAP_FORMAT,
        "format_version": MAP_FORMAT_VERSION,
        "package_version": __version__,
        "georeference": {
            "meters_per_pixel": aerial_map.meters_per_pixel,
            "origin": list(aerial_map.origin_xy),
            "crs": aerial_map.crs,
            "image_size": list(aerial_map.image_size),
        },
        "config": aerial_map.config,
        "backends": aerial_map.backends,
        "source": aerial_map.source,
    }


def _content_hash(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256(json.dumps({k: v for k, v in header.items() if k != "content_hash"}, sort_keys=True).encode())
    for name in sorted(arrays):
        a = arrays[name]
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_aerial_map(aerial_map: AerialMap, path: Path) -> str:
    """Write `aerial_map` to `path` atomically and return its content hash."""
    arrays = _arrays(aerial_map)
    header = _header(aerial_map)
    header["content_hash"] = _content_hash(header, arrays)
    arrays["header.json"] = np.frombuffer(json.dumps(header, indent=1).encode(), dtype=np.uint8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    aerial_map.content_hash = header["content_hash"]
    return header["content_hash"]


def _config_differences(stored: Any, expected: Any, prefix: str = "") -> list[str]:
    if isinstance(stored, dict) and isinstance(expected, dict):
        diffs = []
        for key in sorted(set(stored) | set(expected)):
            diffs += _config_differences(stored.get(key), expected.get(key), f"{prefix}{key}.")
        return diffs
    return [] if stored == expected else [f"{prefix.rstrip('.')}: file has {stored!r}, expected {expected!r}"]


def load_aerial_map(path: Path, expected_config: dict[str, Any] | None = None) -> AerialMap:
    """Read and verify a map file; `expected_config` (if given) must equal the stored config."""
    path = Path(path)
    if not path.is_file():
        raise MapFileError(f"{path}: aerial map file not found")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise MapFileError(f"{path}: not a readable aerial map file ({exc})") from None
    try:
        header = json.loads(arrays.pop("header.json").tobytes().decode())
    except (KeyError, UnicodeDecodeError, json.JSONDecodeError):
        raise MapFileError(f"{path}: missing or unreadable header.json") from None
    if header.get("format") != MAP_FORMAT:
        raise MapFileError(f"{path}: not a meridian-torch aerial map (format {header.get('format')!r})")
    if header.get("format_version") != MAP_FORMAT_VERSION:
        raise MapFileError(
            f"{path}: map format version {header.get('format_version')} (written by meridian-torch "
            f"{header.get('package_version')}), this version reads {MAP_FORMAT_VERSION}; rebuild the map"
        )
    if _content_hash(header, arrays) != header.get("content_hash"):
        raise MapFileError(f"{path}: content hash mismatch, the file is corrupted; rebuild the map")
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
    )

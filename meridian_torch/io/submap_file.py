"""The ground submap file (`.mts`), format version 1.

A `.mts` file is a zip archive (numpy `.npz` layout) holding S submaps of one sequence:
- `header.json` (stored as a uint8 array): `format` = "meridian-torch ground submaps",
  `format_version`, `package_version`, `num_submaps`, `config` (the resolved config blocks that
  shaped the submaps), `source` (e.g. the sequence path), `content_hash` (sha256 over the rest
  of the header and every array);
- per-submap arrays: `index (S,) int64`, `time (S,) float64` seconds, `T_odom_base (S, 4, 4)
  float64`, `path_length_m (S,) float64`;
- flat arrays of all submaps with an owner column (submap position 0..S-1, non-decreasing):
  points `points_xy (Np, 2)`, `point_descriptors (Np, D)`, `point_segment_ids (Np,) int64`,
  `point_submap (Np,) int64`; lines `line_endpoints (Nl, 2, 2)`, `line_kinds (Nl,) int64`
  (0 segment, 1 ray, 2 infinite), `line_descriptors (Nl, D)`, `line_segment_ids (Nl,) int64`,
  `line_submap (Nl,) int64`; `frame_descriptors (F, Dg)`, `frame_descriptor_submap (F,) int64`;
  `segment_ids (K,) int64`, `segment_id_submap (K,) int64`.
Coordinates are metres in the odometry frame's x-y plane. Files are written atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from meridian_torch.errors import MeridianError
from meridian_torch.io.npz_container import read_container, write_container
from meridian_torch.types import GroundSubmap, PrimitiveSet

__all__ = ["SUBMAP_FORMAT", "SUBMAP_FORMAT_VERSION", "SubmapFileError", "save_ground_submaps", "load_ground_submaps"]

SUBMAP_FORMAT = "meridian-torch ground submaps"
SUBMAP_FORMAT_VERSION = 1

_POINT_FIELDS = ("points_xy", "point_descriptors", "point_segment_ids")
_LINE_FIELDS = ("line_endpoints", "line_kinds", "line_descriptors", "line_segment_ids")


class SubmapFileError(MeridianError):
    """A ground submap file is unreadable, corrupted, or from another format version."""


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy())


def _flat(parts: list[np.ndarray], empty_shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(empty_shape, dtype=dtype)


def _arrays(submaps: list[GroundSubmap], descriptor_dim: int, global_dim: int) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {
        "index": np.array([s.index for s in submaps], dtype=np.int64),
        "time": np.array([s.time for s in submaps], dtype=np.float64),
        "T_odom_base": np.array([s.T_odom_base for s in submaps], dtype=np.float64).reshape(-1, 4, 4),
        "path_length_m": np.array([s.path_length_m for s in submaps], dtype=np.float64),
    }
    empty = {"points_xy": (0, 2), "point_descriptors": (0, descriptor_dim), "point_segment_ids": (0,),
             "line_endpoints": (0, 2, 2), "line_kinds": (0,), "line_descriptors": (0, descriptor_dim),
             "line_segment_ids": (0,)}
    for name in _POINT_FIELDS + _LINE_FIELDS:
        dtype = np.int64 if name.endswith(("ids", "kinds")) else np.float32
        arrays[name] = _flat([_np(getattr(s.primitives, name)) for s in submaps], empty[name], dtype)
    owner = np.arange(len(submaps))
    arrays["point_submap"] = np.repeat(owner, [s.primitives.points_xy.shape[0] for s in submaps]).astype(np.int64)
    arrays["line_submap"] = np.repeat(owner, [s.primitives.line_endpoints.shape[0] for s in submaps]).astype(np.int64)
    arrays["frame_descriptors"] = _flat([_np(s.frame_descriptors) for s in submaps], (0, global_dim), np.float32)
    arrays["frame_descriptor_submap"] = np.repeat(owner, [s.frame_descriptors.shape[0] for s in submaps]).astype(np.int64)
    arrays["segment_ids"] = _flat([_np(s.segment_ids) for s in submaps], (0,), np.int64)
    arrays["segment_id_submap"] = np.repeat(owner, [len(s.segment_ids) for s in submaps]).astype(np.int64)
    return arrays


def save_ground_submaps(
    submaps: list[GroundSubmap],
    path: Path,
    *,
    config: dict[str, Any] | None = None,
    source: dict[str, str] | None = None,
    descriptor_dim: int | None = None,
    global_descriptor_dim: int | None = None,
) -> str:
    """Write `submaps` to `path` atomically; returns the content hash. The descriptor dimensions
    are only needed to give an empty list its array shapes."""
    d = descriptor_dim if not submaps else submaps[0].primitives.descriptor_dim
    dg = global_descriptor_dim if not submaps else int(submaps[0].frame_descriptors.shape[1])
    arrays = _arrays(submaps, int(d or 0), int(dg or 0))
    header = {"num_submaps": len(submaps), "config": config or {}, "source": source or {}}
    return write_container(path, SUBMAP_FORMAT, SUBMAP_FORMAT_VERSION, header, arrays)


def load_ground_submaps(path: Path) -> tuple[list[GroundSubmap], dict[str, Any]]:
    """Read and verify a submap file: (submaps, header)."""
    header, arrays = read_container(
        path, SUBMAP_FORMAT, SUBMAP_FORMAT_VERSION, SubmapFileError, "ground submap file", "map the sequence again"
    )

    def rows(owner: str, s: int) -> slice:
        o = arrays[owner]
        return slice(int(np.searchsorted(o, s)), int(np.searchsorted(o, s, side="right")))

    submaps = []
    for s in range(len(arrays["index"])):
        p, l_ = rows("point_submap", s), rows("line_submap", s)
        prims = PrimitiveSet(
            **{name: torch.from_numpy(arrays[name][p]) for name in _POINT_FIELDS},
            **{name: torch.from_numpy(arrays[name][l_]) for name in _LINE_FIELDS},
        )
        submaps.append(GroundSubmap(
            index=int(arrays["index"][s]),
            time=float(arrays["time"][s]),
            T_odom_base=arrays["T_odom_base"][s].copy(),
            path_length_m=float(arrays["path_length_m"][s]),
            primitives=prims,
            frame_descriptors=torch.from_numpy(arrays["frame_descriptors"][rows("frame_descriptor_submap", s)]),
            segment_ids=torch.from_numpy(arrays["segment_ids"][rows("segment_id_submap", s)]),
        ))
    return submaps, header

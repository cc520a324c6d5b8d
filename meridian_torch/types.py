"""Primitive containers shared by the aerial and ground sides and by matching.

A `PrimitiveSet` holds the points and lines of one aerial patch or one ground submap in one
metric frame (world for aerial, odom x-y for ground). A `PrimitiveBatch` stacks P sets into
padded tensors with `valid` masks, the form every batched stage consumes.

Lines are stored by two endpoints plus a kind:
- SEGMENT: a bounded segment between endpoints[0] and endpoints[1];
- RAY: starts at endpoints[0] and extends without bound through endpoints[1];
- INFINITE: the unbounded line through both endpoints.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields
from enum import IntEnum
from typing import Any

import numpy as np
import torch

__all__ = ["LineKind", "PrimitiveSet", "PrimitiveBatch", "stack_primitive_sets", "GroundSubmap", "PatchGrid", "AerialMap"]


class LineKind(IntEnum):
    SEGMENT = 0
    RAY = 1
    INFINITE = 2


def _moved(container, device: torch.device | str | None, dtype: torch.dtype | None) -> dict[str, torch.Tensor]:
    """The tensors of a dataclass of tensors moved to `device`; floating ones also to `dtype`."""
    tensors = {f.name: getattr(container, f.name) for f in fields(container)}
    return {name: t.to(device=device, dtype=dtype if t.is_floating_point() else None) for name, t in tensors.items()}


@dataclass(frozen=True)
class PrimitiveSet:
    points_xy: torch.Tensor  # (Np, 2) metres
    point_descriptors: torch.Tensor  # (Np, D) L2-normalized
    point_segment_ids: torch.Tensor  # (Np,) int64 id of the source segment
    line_endpoints: torch.Tensor  # (Nl, 2, 2) metres
    line_kinds: torch.Tensor  # (Nl,) int64 LineKind
    line_descriptors: torch.Tensor  # (Nl, D) L2-normalized
    line_segment_ids: torch.Tensor  # (Nl,) int64 id of a source segment

    def __post_init__(self) -> None:
        n_points, n_lines = self.points_xy.shape[0], self.line_endpoints.shape[0]
        expected = {
            "points_xy": (n_points, 2),
            "point_segment_ids": (n_points,),
            "line_endpoints": (n_lines, 2, 2),
            "line_kinds": (n_lines,),
            "line_segment_ids": (n_lines,),
        }
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"PrimitiveSet.{name}: expected shape {shape}, got {tuple(getattr(self, name).shape)}")
        if self.point_descriptors.shape[0] != n_points or self.line_descriptors.shape[0] != n_lines:
            raise ValueError("PrimitiveSet: one descriptor per point and per line expected")
        if self.point_descriptors.shape[1] != self.line_descriptors.shape[1]:
            raise ValueError("PrimitiveSet: points and lines must share the descriptor dimension")

    @property
    def descriptor_dim(self) -> int:
        return int(self.point_descriptors.shape[1])

    @classmethod
    def empty(cls, descriptor_dim: int, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> "PrimitiveSet":
        f = dict(dtype=dtype, device=device)
        i = dict(dtype=torch.int64, device=device)
        return cls(
            points_xy=torch.zeros(0, 2, **f),
            point_descriptors=torch.zeros(0, descriptor_dim, **f),
            point_segment_ids=torch.zeros(0, **i),
            line_endpoints=torch.zeros(0, 2, 2, **f),
            line_kinds=torch.zeros(0, **i),
            line_descriptors=torch.zeros(0, descriptor_dim, **f),
            line_segment_ids=torch.zeros(0, **i),
        )

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "PrimitiveSet":
        """Move every tensor to `device`; floating tensors also to `dtype`."""
        return PrimitiveSet(**_moved(self, device, dtype))

    def arrays(self) -> dict[str, np.ndarray]:
        """The tensors as CPU NumPy arrays by field name (for part files and worker processes)."""
        return {f.name: getattr(self, f.name).cpu().numpy() for f in fields(self)}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "PrimitiveSet":
        """The set of `arrays()` (the arrays are shared, not copied)."""
        return cls(**{name: torch.from_numpy(a) for name, a in arrays.items()})


@dataclass(frozen=True)
class PrimitiveBatch:
    """P primitive sets padded to common sizes; padded entries are zero and invalid."""

    points_xy: torch.Tensor  # (P, Np, 2)
    point_descriptors: torch.Tensor  # (P, Np, D)
    point_valid: torch.Tensor  # (P, Np) bool
    line_endpoints: torch.Tensor  # (P, Nl, 2, 2)
    line_kinds: torch.Tensor  # (P, Nl) int64
    line_descriptors: torch.Tensor  # (P, Nl, D)
    line_valid: torch.Tensor  # (P, Nl) bool

    def __len__(self) -> int:
        return int(self.points_xy.shape[0])

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "PrimitiveBatch":
        """Move every tensor to `device`; floating tensors also to `dtype`."""
        return PrimitiveBatch(**_moved(self, device, dtype))

    def select(self, index: slice | torch.Tensor) -> "PrimitiveBatch":
        """The patches `index` (a slice or an index tensor) as a batch."""
        if isinstance(index, torch.Tensor):
            index = index.to(self.points_xy.device)
        return PrimitiveBatch(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def used_lengths(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(P,) int64 point and line axis lengths each patch uses: up to its last valid entry."""

        def used(valid: torch.Tensor) -> torch.Tensor:
            last = valid * torch.arange(1, valid.shape[1] + 1, device=valid.device)
            return torch.cat([last.new_zeros(len(valid), 1), last], 1).amax(1)

        return used(self.point_valid), used(self.line_valid)

    def trimmed(self) -> "PrimitiveBatch":
        """The same patches without the padding none of them uses: the point and line axes end
        at the last valid entry of any patch (one entry stays when there were any, so padded
        indices remain addressable). Unified indices (lines after points, see `Associations`)
        shift with the point axis."""
        n_p, n_l = (
            max(int(used.max()) if len(used) else 0, min(1, valid.shape[1]))
            for used, valid in zip(self.used_lengths(), (self.point_valid, self.line_valid))
        )
        return PrimitiveBatch(
            points_xy=self.points_xy[:, :n_p],
            point_descriptors=self.point_descriptors[:, :n_p],
            point_valid=self.point_valid[:, :n_p],
            line_endpoints=self.line_endpoints[:, :n_l],
            line_kinds=self.line_kinds[:, :n_l],
            line_descriptors=self.line_descriptors[:, :n_l],
            line_valid=self.line_valid[:, :n_l],
        )

    def unbatch(self, index: int) -> PrimitiveSet:
        """The index-th set without padding (segment ids are not kept in batches: -1)."""
        pv, lv = self.point_valid[index], self.line_valid[index]
        n_p, n_l = int(pv.sum()), int(lv.sum())
        return PrimitiveSet(
            points_xy=self.points_xy[index][pv],
            point_descriptors=self.point_descriptors[index][pv],
            point_segment_ids=torch.full((n_p,), -1, dtype=torch.int64, device=pv.device),
            line_endpoints=self.line_endpoints[index][lv],
            line_kinds=self.line_kinds[index][lv],
            line_descriptors=self.line_descriptors[index][lv],
            line_segment_ids=torch.full((n_l,), -1, dtype=torch.int64, device=lv.device),
        )


def _pad(tensors: list[torch.Tensor], length: int) -> torch.Tensor:
    out = tensors[0].new_zeros((len(tensors), length) + tuple(tensors[0].shape[1:]))
    for k, t in enumerate(tensors):
        out[k, : t.shape[0]] = t
    return out


def stack_primitive_sets(sets: list[PrimitiveSet], min_points: int = 0, min_lines: int = 0) -> PrimitiveBatch:
    """Pad and stack primitive sets (all with one descriptor dimension) into a batch."""
    if not sets:
        raise ValueError("stack_primitive_sets needs at least one set")
    n_p = max([min_points] + [s.points_xy.shape[0] for s in sets])
    n_l = max([min_lines] + [s.line_endpoints.shape[0] for s in sets])
    device = sets[0].points_xy.device
    ar_p = torch.arange(n_p, device=device)
    ar_l = torch.arange(n_l, device=device)
    counts_p = torch.tensor([s.points_xy.shape[0] for s in sets], device=device)
    counts_l = torch.tensor([s.line_endpoints.shape[0] for s in sets], device=device)
    return PrimitiveBatch(
        points_xy=_pad([s.points_xy for s in sets], n_p),
        point_descriptors=_pad([s.point_descriptors for s in sets], n_p),
        point_valid=ar_p[None, :] < counts_p[:, None],
        line_endpoints=_pad([s.line_endpoints for s in sets], n_l),
        line_kinds=_pad([s.line_kinds for s in sets], n_l),
        line_descriptors=_pad([s.line_descriptors for s in sets], n_l),
        line_valid=ar_l[None, :] < counts_l[:, None],
    )


@dataclass(frozen=True)
class GroundSubmap:
    """One ground submap: what the localizer needs to match it and place it in the pose graph.

    Primitives are in the odom frame's x-y plane (metres); matching returns T_world_odom, and
    T_world_base at the submap time is T_world_odom composed with `T_odom_base` (in SE(2)).
    """

    index: int  # 0, 1, 2, ... in creation order
    time: float  # submap centre time, seconds (non-decreasing over submaps)
    T_odom_base: np.ndarray  # (4, 4) odometry pose of the base at `time`
    path_length_m: float  # odometry path length from the first frame to `time`
    primitives: PrimitiveSet  # odom x-y frame
    frame_descriptors: torch.Tensor  # (F, Dg) L2-normalized global descriptors of frames, F >= 1 ((0, Dg) or (0, 0): not computed)
    segment_ids: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.int64))  # (S,) 3D segments used


@dataclass(frozen=True)
class PatchGrid:
    """P patches of an image: pixel windows and their world-metre geometry."""

    pixel_boxes: np.ndarray  # (P, 4) int64 col0, row0, col1, row1 (exclusive ends)
    grid_index: np.ndarray  # (P, 2) int64 (i, j): column and row index in the patch grid
    bounds_xy: np.ndarray  # (P, 4) float64 world x_min, x_max, y_min, y_max of the patch
    centres_xy: np.ndarray  # (P, 2) float64 world centre of the patch

    def __len__(self) -> int:
        return len(self.pixel_boxes)


@dataclass
class AerialMap:
    """An aerial map: its patch grid, the primitives and global descriptor of every patch, the
    orthophoto's georeference, and how it was built (`io.map_file` reads and writes it)."""

    patches: PatchGrid
    primitives: PrimitiveBatch
    global_descriptors: torch.Tensor  # (P, Dg)
    meters_per_pixel: float
    origin_xy: tuple[float, float]  # world x, y of the orthophoto's top-left corner
    image_size: tuple[int, int]  # (width, height) of the orthophoto in pixels
    crs: str | None = None
    config: dict[str, Any] = field(default_factory=dict)
    backends: dict[str, str] = field(default_factory=dict)
    source: dict[str, str] = field(default_factory=dict)
    content_hash: str = ""
    local_origin_xy: tuple[float, float] = (0.0, 0.0)  # world x, y of the map frame's origin

    def __len__(self) -> int:
        return len(self.patches)

    @property
    def global_descriptor_backend(self) -> str | None:
        """The back end that computed `global_descriptors` (perception.global_descriptor.backend of
        the build), None when the map does not record it."""
        perception = self.config.get("perception")
        block = perception.get("global_descriptor") if isinstance(perception, dict) else None
        backend = block.get("backend") if isinstance(block, dict) else None
        return backend if isinstance(backend, str) else None

    def to(self, device: torch.device | str) -> "AerialMap":
        """The map with its primitives and global descriptors on `device` (the same map when
        they are there already)."""
        return dataclasses.replace(self, primitives=self.primitives.to(device=device),
                                   global_descriptors=self.global_descriptors.to(device))

"""Building the aerial map: orthophoto -> patches -> segments -> point/line primitives + descriptors.

Resumable: every finished patch is stored in a work folder next to the output (one small file
per patch, keyed by the orthophoto's and the config's hashes), so an interrupted build continues
where it stopped; the folder is removed once the map file is written. The map file is written
from these part files patch by patch (`io.map_file.save_aerial_map_patches`), so neither the build
nor the write holds the whole map: memory does not grow with the area.

Map frame: every coordinate in the map (patch bounds, primitives) is in metres relative to a
local origin near the orthophoto (`map_frame_origin`), so that float32 tensors keep millimetres
and polygon operations stay robust when the orthophoto is georeferenced in a projected CRS with
coordinates like (458000, 5429000); `AerialMap.local_origin_xy` (float64) converts back.

Windowed: `build_map_file` opens the orthophoto as an `OrthophotoSource` and patches are read box
by box (io/ortho_source.py), so a tiled GeoTIFF is never held whole in memory.

Engines (mapping/aerial_engines.py): blocks of `aerial_map.batch_size` patches are described in
this process, in `aerial_map.workers` local processes, or on a Ray cluster; the map is the same.
Classical segmentation and segment -> primitive conversion are single-threaded Python/NumPy, so
processes, not torch threads, are what use a second core.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from meridian_torch import __version__
from meridian_torch.config import AerialMapConfig, PerceptionConfig
from meridian_torch.config.mapping import PrimitiveConfig
from meridian_torch.config.perception import active_backend_dict
from meridian_torch.io.atomic import atomic_path, write_text_atomic
from meridian_torch.io.map_file import MapFileError, load_aerial_map, save_aerial_map_patches
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.io.ortho_source import OrthophotoSource, open_orthophoto
from meridian_torch.mapping.aerial_engines import described_blocks
from meridian_torch.mapping.primitives.conversion import segments_to_primitives
from meridian_torch.mapping.tiling import crop_offsets, tile_image
from meridian_torch.perception.factory import build_global_describer, build_segment_describer, build_segmenter
from meridian_torch.perception.protocols import GlobalDescriber, Segmentation, SegmentDescriber, Segmenter
from meridian_torch.types import AerialMap, PatchGrid, PrimitiveSet, stack_primitive_sets

__all__ = [
    "AerialMapper", "build_aerial_map", "build_map_file", "map_config_dict", "map_frame_origin", "write_aerial_map",
]

_LOCAL_ORIGIN_STEP_M = 10_000.0  # round numbers, and 0 for every orthophoto within 5 km of its CRS origin


def map_frame_origin(ortho: Orthophoto | OrthophotoSource) -> tuple[float, float]:
    """World x, y of the map frame's origin: the orthophoto's corner rounded to 10 km."""
    return tuple(float(np.round(v / _LOCAL_ORIGIN_STEP_M) * _LOCAL_ORIGIN_STEP_M) for v in ortho.origin_xy)


def _corner_in_map_frame(ortho: Orthophoto | OrthophotoSource) -> tuple[float, float]:
    """The orthophoto's top-left corner in the map frame (float64)."""
    local = map_frame_origin(ortho)
    return ortho.origin_xy[0] - local[0], ortho.origin_xy[1] - local[1]


def map_config_dict(aerial: AerialMapConfig, perception: PerceptionConfig, primitives: PrimitiveConfig) -> dict[str, Any]:
    """The config blocks that shape an aerial map (stored in the map file and compared on load)."""
    return {
        "aerial_map": aerial.model_dump(mode="json", exclude={"batch_size", "workers", "engine", "ray_address"}),
        "perception": {
            "aerial_segmenter": active_backend_dict(perception.aerial_segmenter),
            "descriptor": active_backend_dict(perception.descriptor),
            "global_descriptor": active_backend_dict(perception.global_descriptor),
        },
        "primitives": primitives.model_dump(mode="json"),
    }


@dataclass
class AerialMapper:
    """The perception back ends and settings of one aerial-map build."""

    segmenter: Segmenter
    describer: SegmentDescriber
    global_describer: GlobalDescriber
    aerial: AerialMapConfig
    primitives: PrimitiveConfig
    config: dict[str, Any]
    device: torch.device = torch.device("cpu")

    @classmethod
    def from_config(
        cls, aerial: AerialMapConfig, perception: PerceptionConfig, primitives: PrimitiveConfig,
        device: torch.device | str = "cpu",
    ) -> "AerialMapper":
        return cls(
            segmenter=build_segmenter(perception.aerial_segmenter),
            describer=build_segment_describer(perception.descriptor),
            global_describer=build_global_describer(perception.global_descriptor),
            aerial=aerial,
            primitives=primitives,
            config=map_config_dict(aerial, perception, primitives),
            device=torch.device(device),
        )

    def describe_patches(
        self, ortho: Orthophoto | OrthophotoSource, grid: PatchGrid, indices: np.ndarray
    ) -> list[tuple[PrimitiveSet, torch.Tensor]]:
        """Primitives and global descriptor of the patches `indices` (one block), read box by box."""
        mpp = ortho.meters_per_pixel
        boxes = grid.pixel_boxes[indices]
        patches = _to_tensor([ortho.read_box(box) for box in boxes], self.device)
        global_desc = self.global_describer.describe(patches)

        # Segmentation crops: the whole patch (default), or square sub-crops as the reference does.
        h_px, w_px = patches.shape[-2:]
        if self.aerial.segmentation_crop_m is None:
            crops_t = patches
            crop_origin_px = [(b, c0, r0) for b, (c0, r0, _, _) in enumerate(boxes)]
        else:
            crop_px = max(1, int(round(self.aerial.segmentation_crop_m / mpp)))
            ch, cw = min(crop_px, h_px), min(crop_px, w_px)
            crops, crop_origin_px = [], []
            for b, (c0, r0, _, _) in enumerate(boxes):
                for dr in crop_offsets(h_px, ch):
                    for dc in crop_offsets(w_px, cw):
                        crops.append(patches[b, :, dr : dr + ch, dc : dc + cw])
                        crop_origin_px.append((b, c0 + dc, r0 + dr))
            crops_t = torch.stack(crops)
        seg = self.segmenter.segment(crops_t, mpp)
        desc = self.describer.describe(crops_t, seg.masks, seg.valid)

        per_patch: list[list[tuple[np.ndarray, torch.Tensor, np.ndarray, np.ndarray]]] = [[] for _ in boxes]
        for k, (b, col0, row0) in enumerate(crop_origin_px):
            h, w = seg.masks.shape[-2:]
            # Mask pixel centres in map-frame metres (the pixel-centre convention of the README's Formats).
            x0, y0 = _corner_in_map_frame(ortho)
            rows, cols, counts = _segment_pixels(seg, k)
            xy = np.stack([x0 + (col0 + cols + 0.5) * mpp, y0 - (row0 + rows + 0.5) * mpp], axis=1)
            points = np.split(xy, np.cumsum(counts)[:-1])
            box = np.array([x0 + col0 * mpp, x0 + (col0 + w) * mpp, y0 - (row0 + h) * mpp, y0 - row0 * mpp])
            per_patch[b].append((points, desc[k][seg.valid[k]], counts * mpp * mpp, box))

        results = []
        for b, crops_of_patch in enumerate(per_patch):
            points = [p for c in crops_of_patch for p in c[0]]
            descs = torch.cat([c[1] for c in crops_of_patch])
            areas = np.concatenate([c[2] for c in crops_of_patch])
            boxes_per_segment = np.concatenate([np.repeat(c[3][None], len(c[0]), axis=0) for c in crops_of_patch])
            prims = segments_to_primitives(points, descs, self.primitives, areas_m2=areas, border_box=boxes_per_segment)
            results.append((prims.to(device="cpu"), global_desc[b].cpu()))
        return results


def _segment_pixels(seg: Segmentation, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (rows, columns) of image k's valid segments, segment after segment and row-major
    within one (as `torch.nonzero` of the masks), and each segment's pixel count."""
    n = int(seg.valid[k].sum())
    if seg.labels is None:
        idx_m, rows, cols = torch.nonzero(seg.masks[k][seg.valid[k]], as_tuple=True)
        return rows.cpu().numpy(), cols.cpu().numpy(), torch.bincount(idx_m, minlength=n).cpu().numpy()
    # A partition: one stable sort of the label image (a radix sort at <= 16 bits) instead of a
    # pass over every mask.
    labels = seg.labels[k].cpu().numpy()
    if labels.size and not 0 <= labels.min() <= labels.max() < n:
        raise ValueError(f"segmentation labels of image {k} span {labels.min()}..{labels.max()}, "
                         f"not the {n} valid masks")
    flat = labels.ravel().astype(np.min_scalar_type(max(n - 1, 0)))
    order = np.argsort(flat, kind="stable")
    return order // labels.shape[1], order % labels.shape[1], np.bincount(flat, minlength=n)


def _to_tensor(images: list[np.ndarray], device: torch.device) -> torch.Tensor:
    batch = torch.from_numpy(np.stack(images)).to(device)
    return batch.permute(0, 3, 1, 2).float().div_(255.0)


def _work_key(ortho: Orthophoto | OrthophotoSource, config: dict[str, Any]) -> str:
    h = hashlib.sha256(json.dumps([__version__, config, ortho.meters_per_pixel, list(ortho.origin_xy)],
                                  sort_keys=True).encode())
    h.update(ortho.content_sha256().encode())
    return h.hexdigest()[:16]


def _part_path(work_dir: Path, index: int) -> Path:
    return work_dir / f"patch_{index:06d}.npz"


def _save_patch(path: Path, prims: PrimitiveSet, global_desc: torch.Tensor) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, global_desc=global_desc.numpy(), **prims.arrays())


def _load_patch(path: Path) -> tuple[PrimitiveSet, torch.Tensor] | None:
    """A finished patch, or None when its part file is damaged (it is then built again)."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        global_desc = torch.from_numpy(arrays.pop("global_desc"))
        return PrimitiveSet.from_arrays(arrays), global_desc
    except (OSError, ValueError, EOFError, KeyError, TypeError, zipfile.BadZipFile):
        return None


def _damaged_part(path: Path, detail: str) -> MapFileError:
    """A part file found damaged after the build (it is removed, so the next run builds it again)."""
    path.unlink(missing_ok=True)
    return MapFileError(f"{path}: damaged part file ({detail}); run build-map again to build that patch again")


def _read_part(work_dir: Path, index: int, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Arrays of one finished patch by `io.map_file` name (`io.map_file.PatchReader`)."""
    path = _part_path(work_dir, index)
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {name: npz["global_desc" if name == "global_descriptors" else name] for name in names}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:
        raise _damaged_part(path, str(e)) from None


def _patch_grid(ortho: Orthophoto | OrthophotoSource, mapper: AerialMapper) -> PatchGrid:
    return tile_image(*ortho.size_px, ortho.meters_per_pixel, _corner_in_map_frame(ortho),
                      mapper.aerial.patch_size_m, mapper.aerial.patch_overlap)


def _map_fields(ortho: Orthophoto | OrthophotoSource, mapper: AerialMapper, source: dict[str, str] | None) -> dict[str, Any]:
    """The `AerialMap` fields besides the patches and their arrays."""
    return {
        "meters_per_pixel": ortho.meters_per_pixel,
        "origin_xy": ortho.origin_xy,
        "local_origin_xy": map_frame_origin(ortho),
        "image_size": ortho.size_px,
        "crs": ortho.crs,
        "config": mapper.config,
        "backends": {
            "segmenter": type(mapper.segmenter).__name__,
            "describer": type(mapper.describer).__name__,
            "global_describer": type(mapper.global_describer).__name__,
        },
        "source": source or {},
    }


def _describe_missing(
    ortho: Orthophoto | OrthophotoSource, mapper: AerialMapper, grid: PatchGrid, done: set[int],
    keep: Callable[[int, tuple[PrimitiveSet, torch.Tensor]], None], progress: Callable[[int, int], None] | None,
) -> None:
    """Describe the patches not in `done`, block by block on the mapper's engine, handing each to `keep`."""
    todo = np.array([i for i in range(len(grid)) if i not in done], dtype=np.int64)
    n_done = len(grid) - len(todo)
    if progress is not None:
        progress(n_done, len(grid))
    block = mapper.aerial.batch_size
    blocks = [todo[start : start + block] for start in range(0, len(todo), block)]
    for indices, described in zip(blocks, described_blocks(ortho, grid, mapper, blocks)):
        for i, result in zip(indices, described):
            keep(int(i), result)
        n_done += len(indices)
        if progress is not None:
            progress(n_done, len(grid))


def _build_parts(
    ortho: Orthophoto | OrthophotoSource, mapper: AerialMapper, grid: PatchGrid, work_dir: Path,
    progress: Callable[[int, int], None] | None, on_message: Callable[[str], None] | None,
) -> None:
    """Every patch of `grid` as a part file in `work_dir`: those of an interrupted build of the same
    orthophoto and config are kept (damaged ones built again), the others built. Holds no patch
    beyond the engine's blocks in flight."""
    key = _work_key(ortho, mapper.config)
    key_file = work_dir / "key.txt"
    if work_dir.exists() and (not key_file.is_file() or key_file.read_text() != key):
        shutil.rmtree(work_dir)  # another orthophoto or config: nothing to resume
    work_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(key_file, key)
    done = set()
    for path in sorted(work_dir.glob("patch_*.npz")):
        if _load_patch(path) is None:
            path.unlink()
            if on_message is not None:
                on_message(f"{path}: damaged part file, building that patch again")
        else:
            done.add(int(path.stem.split("_")[1]))
    _describe_missing(ortho, mapper, grid, done, lambda i, result: _save_patch(_part_path(work_dir, i), *result),
                      progress)


def build_aerial_map(
    ortho: Orthophoto | OrthophotoSource,
    mapper: AerialMapper,
    *,
    work_dir: Path | None = None,
    source: dict[str, str] | None = None,
    progress: Callable[[int, int], None] | None = None,
    on_message: Callable[[str], None] | None = None,
) -> AerialMap:
    """Build the aerial map of `ortho` (in memory, or a source read box by box) on the engine of
    `mapper.aerial`, in memory. With `work_dir`, finished patches are kept there and reused on any
    engine (damaged part files are built again, reported through `on_message`). For large areas
    use `write_aerial_map`, which never holds the whole map."""
    grid = _patch_grid(ortho, mapper)
    if work_dir is None:
        results: dict[int, tuple[PrimitiveSet, torch.Tensor]] = {}
        _describe_missing(ortho, mapper, grid, set(), results.__setitem__, progress)
        ordered = [results[i] for i in range(len(grid))]
    else:
        _build_parts(ortho, mapper, grid, work_dir, progress, on_message)
        ordered = [_load_patch(_part_path(work_dir, i)) for i in range(len(grid))]
        for i, loaded in enumerate(ordered):
            if loaded is None:
                raise _damaged_part(_part_path(work_dir, i), "unreadable")
    return AerialMap(
        patches=grid,
        primitives=stack_primitive_sets([r[0] for r in ordered]),
        global_descriptors=torch.stack([r[1] for r in ordered]),
        **_map_fields(ortho, mapper, source),
    )


def write_aerial_map(
    ortho: Orthophoto | OrthophotoSource,
    mapper: AerialMapper,
    out: Path,
    *,
    source: dict[str, str] | None = None,
    progress: Callable[[int, int], None] | None = None,
    on_message: Callable[[str], None] | None = None,
) -> AerialMap:
    """Build the aerial map of `ortho` into the file `out` and return it opened from there (memory
    mapped). Resumable through `out`.parts/ (see `build_aerial_map`); the file is written from the
    part files one block of patches at a time, atomically, and the parts are removed after it."""
    work_dir = out.with_name(out.name + ".parts")
    grid = _patch_grid(ortho, mapper)
    _build_parts(ortho, mapper, grid, work_dir, progress, on_message)
    save_aerial_map_patches(out, grid, lambda i, names: _read_part(work_dir, i, names),
                            **_map_fields(ortho, mapper, source))
    shutil.rmtree(work_dir, ignore_errors=True)
    return load_aerial_map(out)


def build_map_file(
    ortho_path: Path,
    out: Path,
    aerial: AerialMapConfig,
    perception: PerceptionConfig,
    primitives: PrimitiveConfig,
    *,
    device: torch.device | str = "cpu",
    progress: Callable[[int, int], None] | None = None,
    on_message: Callable[[str], None] | None = None,
) -> AerialMap:
    """Orthophoto file or folder -> aerial map saved at `out` (`write_aerial_map`), resumable through
    `out`.parts/, returned memory mapped from `out`. The orthophoto is read box by box
    (io/ortho_source.py)."""
    mapper = AerialMapper.from_config(aerial, perception, primitives, device=device)
    with open_orthophoto(ortho_path) as ortho:
        return write_aerial_map(ortho, mapper, out, progress=progress, on_message=on_message,
                                source={"orthophoto": str(ortho.path.resolve())})

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from meridian_torch.io import map_file
from meridian_torch.io.map_file import MapFileError, load_aerial_map, save_aerial_map
from meridian_torch.io.npz_container import write_container
from meridian_torch.mapping.tiling import tile_image
from meridian_torch.types import AerialMap, PrimitiveSet, stack_primitive_sets


def _random_set(gen: torch.Generator, n_points: int, n_lines: int, dim: int = 8) -> PrimitiveSet:
    desc = torch.nn.functional.normalize(torch.rand(n_points + n_lines, dim, generator=gen), dim=1)
    return PrimitiveSet(
        points_xy=torch.rand(n_points, 2, generator=gen) * 60,
        point_descriptors=desc[:n_points],
        point_segment_ids=torch.arange(n_points),
        line_endpoints=torch.rand(n_lines, 2, 2, generator=gen) * 60,
        line_kinds=torch.randint(0, 3, (n_lines,), generator=gen),
        line_descriptors=desc[n_points:],
        line_segment_ids=torch.arange(n_lines),
    )


def _map() -> AerialMap:
    gen = torch.Generator().manual_seed(0)
    grid = tile_image(400, 300, 0.3, (500.0, 900.0), 60.0, 0.5)
    sets = [_random_set(gen, int(n), int(m)) for n, m in zip(range(len(grid)), range(len(grid), 0, -1))]
    return AerialMap(
        patches=grid,
        primitives=stack_primitive_sets(sets),
        global_descriptors=torch.rand(len(grid), 16, generator=gen),
        meters_per_pixel=0.3,
        origin_xy=(500.0, 900.0),
        image_size=(400, 300),
        crs="EPSG:32632",
        config={"aerial_map": {"patch_size_m": 60.0}},
        backends={"segmenter": "classical"},
        local_origin_xy=(460000.0, 5430000.0),
    )


def test_round_trip(tmp_path: Path) -> None:
    original = _map()
    digest = save_aerial_map(original, tmp_path / "m.mtm")
    loaded = load_aerial_map(tmp_path / "m.mtm", expected_config={"aerial_map": {"patch_size_m": 60.0}})
    assert loaded.content_hash == digest and len(loaded) == len(original)
    for name in ("points_xy", "point_valid", "line_endpoints", "line_kinds", "line_descriptors", "line_valid"):
        assert torch.equal(getattr(loaded.primitives, name), getattr(original.primitives, name))
    assert np.array_equal(loaded.patches.bounds_xy, original.patches.bounds_xy)
    assert torch.equal(loaded.global_descriptors, original.global_descriptors)
    assert (loaded.crs, loaded.origin_xy, loaded.image_size) == ("EPSG:32632", (500.0, 900.0), (400, 300))
    assert loaded.local_origin_xy == (460000.0, 5430000.0)
    assert not list(tmp_path.glob(".*")), "no temporary files left behind"


def _all_arrays(aerial_map: AerialMap) -> dict[str, np.ndarray]:
    return {**map_file._arrays(aerial_map), **{f"patches.{k}": v for k, v in vars(aerial_map.patches).items()}}


def _save_version_2(aerial_map: AerialMap, path: Path) -> None:
    """The file version 2 wrote: the same arrays, compressed."""
    write_container(path, map_file.MAP_FORMAT, 2, map_file._header(aerial_map), map_file._arrays(aerial_map))


def _data_offsets(path: Path) -> dict[str, int]:
    """File offset of each stored array's first data byte (after the zip and .npy headers)."""
    import struct
    import zipfile

    offsets = {}
    with zipfile.ZipFile(path) as zf, open(path, "rb") as fh:
        for info in zf.infolist():
            assert info.compress_type == zipfile.ZIP_STORED
            fh.seek(info.header_offset + 26)
            name_len, extra_len = struct.unpack("<HH", fh.read(4))
            fh.seek(info.header_offset + 30 + name_len + extra_len)
            np.lib.format.read_magic(fh)
            np.lib.format.read_array_header_1_0(fh)  # the writer's headers are version 1.0
            offsets[info.filename.removesuffix(".npy")] = fh.tell()
    return offsets


def test_mapped_map_equals_the_compressed_one(tmp_path: Path) -> None:
    """A version 3 map is read as memory maps of its file and gives exactly the arrays of the same
    map written as version 2 (compressed, read whole), which still loads."""
    original = _map()
    _save_version_2(original, tmp_path / "v2.mtm")
    save_aerial_map(original, tmp_path / "v3.mtm")
    eager, mapped = load_aerial_map(tmp_path / "v2.mtm"), load_aerial_map(tmp_path / "v3.mtm")
    for name, array in _all_arrays(eager).items():
        other = _all_arrays(mapped)[name]
        assert array.dtype == other.dtype and np.array_equal(array, other), name
    maps = Path("/proc/self/maps")
    if maps.exists():
        assert str(tmp_path / "v3.mtm") in maps.read_text() and str(tmp_path / "v2.mtm") not in maps.read_text()
    assert all(offset % 64 == 0 for offset in _data_offsets(tmp_path / "v3.mtm").values())


def test_writing_to_a_mapped_map_never_changes_the_file(tmp_path: Path) -> None:
    path = tmp_path / "m.mtm"
    save_aerial_map(_map(), path)
    before = path.read_bytes()
    loaded = load_aerial_map(path)
    loaded.primitives.points_xy.add_(1.0)  # copy-on-write: the process's own pages
    loaded.patches.bounds_xy[:] = 0.0
    assert path.read_bytes() == before
    assert torch.equal(load_aerial_map(path).primitives.points_xy, _map().primitives.points_xy)


def test_large_members_stay_aligned(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Members over the zip64 limit get a longer local header; their data is still aligned."""
    import zipfile

    monkeypatch.setattr(zipfile, "ZIP64_LIMIT", 4096)
    path = tmp_path / "m.mtm"
    save_aerial_map(_map(), path)
    assert all(offset % 64 == 0 for offset in _data_offsets(path).values())
    assert torch.equal(load_aerial_map(path).primitives.line_descriptors, _map().primitives.line_descriptors)


@pytest.mark.parametrize("name", ["points_xy", "line_valid", "global_descriptors", "patch_bounds_xy", "header.json"])
def test_a_changed_byte_is_refused_at_open(tmp_path: Path, name: str) -> None:
    """One byte changed in place in any stored array: the map is refused before any array is returned."""
    path = tmp_path / "m.mtm"
    save_aerial_map(_map(), path)
    data = bytearray(path.read_bytes())
    offset = _data_offsets(path)[name] + (10 if name == "header.json" else 0)
    data[offset] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(MapFileError, match=rf"^{path}: .*(corrupted|header)"):
        load_aerial_map(path)


def test_failed_write_keeps_the_old_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from meridian_torch.io import npz_container

    path = tmp_path / "m.mtm"
    save_aerial_map(_map(), path)
    before = path.read_bytes()
    calls = []

    def failing_header(dtype: np.dtype, shape: tuple[int, ...]) -> bytes:
        calls.append(1)
        if len(calls) == 3:
            raise OSError("disk full")
        return header(dtype, shape)

    header = npz_container._npy_header
    monkeypatch.setattr(npz_container, "_npy_header", failing_header)
    with pytest.raises(OSError, match="disk full"):
        save_aerial_map(_map(), path)
    assert path.read_bytes() == before and not list(tmp_path.glob(".*"))


def test_corruption_is_detected(tmp_path: Path) -> None:
    path = tmp_path / "m.mtm"
    save_aerial_map(_map(), path)
    # Change one stored array without touching the header: the hash must catch it.
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["points_xy"][0, 0, 0] += 1.0
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    with pytest.raises(MapFileError, match="corrupted"):
        load_aerial_map(path)


def test_truncated_file_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "m.mtm"
    save_aerial_map(_map(), path)
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(MapFileError, match=str(path.name)):
        load_aerial_map(path)


def test_other_version_and_config_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "m.mtm"
    save_aerial_map(_map(), path)
    with pytest.raises(MapFileError, match=r"aerial_map\.patch_size_m"):
        load_aerial_map(path, expected_config={"aerial_map": {"patch_size_m": 40.0}})
    monkeypatch.setattr(map_file, "MAP_FORMAT_VERSION", 4)
    save_aerial_map(_map(), path)
    with pytest.raises(MapFileError, match="format version 4"):
        load_aerial_map(path)


def test_version_1_files_are_read_in_world_coordinates(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Version 1 maps had no local origin: their coordinates are world coordinates."""
    path = tmp_path / "m.mtm"
    monkeypatch.setattr(map_file, "MAP_FORMAT_VERSION", 1)
    monkeypatch.setattr(map_file, "_header", lambda m, header=map_file._header: {
        **header(m), "georeference": {k: v for k, v in header(m)["georeference"].items() if k != "local_origin"}})
    save_aerial_map(_map(), path)  # its local origin is not stored by version 1
    assert load_aerial_map(path).local_origin_xy == (0.0, 0.0)


def test_map_config_ignores_options_of_unused_back_ends() -> None:
    from meridian_torch.config import MeridianConfig
    from meridian_torch.mapping.aerial_map import map_config_dict

    cfg = MeridianConfig()
    base = map_config_dict(cfg.aerial_map, cfg.perception, cfg.primitives)
    seg = cfg.perception.aerial_segmenter
    changed_unused = cfg.perception.model_copy(
        update={"aerial_segmenter": seg.model_copy(update={"sam": seg.sam.model_copy(update={"points_per_side": 8})})}
    )
    assert map_config_dict(cfg.aerial_map, changed_unused, cfg.primitives) == base
    classical = seg.classical.model_copy(update={"merge_threshold": seg.classical.merge_threshold + 1})
    changed_used = cfg.perception.model_copy(update={"aerial_segmenter": seg.model_copy(update={"classical": classical})})
    assert map_config_dict(cfg.aerial_map, changed_used, cfg.primitives) != base
    switched = cfg.perception.model_copy(update={"aerial_segmenter": seg.model_copy(update={"backend": "sam"})})
    assert map_config_dict(cfg.aerial_map, switched, cfg.primitives) != base


@pytest.mark.parametrize("content", ["random bytes", "a pickled numpy array", "a zip with a pickled array"])
def test_unreadable_files_say_what_they_are_not(tmp_path: Path, content: str) -> None:
    """One line naming the file, never numpy's advice to load pickles unsafely."""
    path = tmp_path / "m.mtm"
    if content == "random bytes":
        path.write_bytes(np.random.default_rng(0).bytes(4096))
    elif content == "a pickled numpy array":
        with open(path, "wb") as fh:
            np.save(fh, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    else:
        with open(path, "wb") as fh:
            np.savez(fh, header=np.array([{"a": 1}], dtype=object))
    with pytest.raises(MapFileError) as info:
        load_aerial_map(path)
    message = str(info.value)
    assert message.startswith(f"{path}: not a") and "rebuild the map" in message
    assert "pickle" not in message and "unsafe" not in message


def test_an_open_map_survives_the_file_being_replaced(tmp_path: Path) -> None:
    """Writes replace the file by a rename: a map opened before keeps reading the old file's pages."""
    path = tmp_path / "m.mtm"
    original = _map()
    save_aerial_map(original, path)
    opened = load_aerial_map(path)
    other = _map()
    other.primitives.points_xy.add_(5.0)
    save_aerial_map(other, path)
    assert torch.equal(opened.primitives.points_xy, original.primitives.points_xy)
    assert torch.equal(load_aerial_map(path).primitives.points_xy, other.primitives.points_xy)


def _patch_reader(aerial_map: AerialMap, calls: list[int] | None = None) -> map_file.PatchReader:
    """Read one patch's unpadded arrays out of a map in memory, as a build reads its part files."""

    def read_patch(index: int, names: tuple[str, ...]) -> dict[str, np.ndarray]:
        if calls is not None:
            calls.append(index)
        unpadded = aerial_map.primitives.unbatch(index)
        arrays = {name: getattr(unpadded, name).numpy() for name in vars(unpadded)}
        arrays["global_descriptors"] = aerial_map.global_descriptors[index].numpy()
        return {name: arrays[name] for name in names}

    return read_patch


def _save_patchwise(aerial_map: AerialMap, path: Path, read_patch: map_file.PatchReader) -> str:
    fields = ("meters_per_pixel", "origin_xy", "image_size", "local_origin_xy", "crs", "config", "backends", "source")
    return map_file.save_aerial_map_patches(path, aerial_map.patches, read_patch,
                                            **{name: getattr(aerial_map, name) for name in fields})


def test_patchwise_file_is_the_in_memory_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Written patch by patch in blocks (the last one partial), the map file is byte for byte the
    in-memory writer's, and every array reads back equal."""
    monkeypatch.setattr(map_file, "_BLOCK_PATCHES", 4)
    original = _map()
    assert len(original) % 4 != 0
    digest = save_aerial_map(original, tmp_path / "memory.mtm")
    assert _save_patchwise(original, tmp_path / "patches.mtm", _patch_reader(original)) == digest
    assert (tmp_path / "patches.mtm").read_bytes() == (tmp_path / "memory.mtm").read_bytes()
    loaded = load_aerial_map(tmp_path / "patches.mtm")
    for name, array in _all_arrays(original).items():
        other = _all_arrays(loaded)[name]
        assert array.dtype == other.dtype and np.array_equal(array, other), name


def test_interrupted_patchwise_write_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "m.mtm"
    save_aerial_map(_map(), path)
    before = path.read_bytes()
    other = _map()
    other.primitives.points_xy.add_(1.0)
    calls: list[int] = []
    reader = _patch_reader(other, calls)

    def interrupted(index: int, names: tuple[str, ...]) -> dict[str, np.ndarray]:
        if len(calls) == 3 * len(other):  # within the arrays, after the counts
            raise KeyboardInterrupt
        return reader(index, names)

    with pytest.raises(KeyboardInterrupt):
        _save_patchwise(other, path, interrupted)
    assert path.read_bytes() == before and not list(tmp_path.glob(".*"))


def test_a_patch_unlike_the_others_is_refused(tmp_path: Path) -> None:
    original = _map()
    reader = _patch_reader(original)

    def wider(index: int, names: tuple[str, ...]) -> dict[str, np.ndarray]:
        arrays = reader(index, names)
        if index == 3 and "line_descriptors" in arrays:
            arrays["line_descriptors"] = np.zeros((len(arrays["line_descriptors"]), 9), np.float32)
        return arrays

    with pytest.raises(ValueError, match=r"patch 3: line_descriptors is float32 \(\d+, 9\), expected float32"):
        _save_patchwise(original, tmp_path / "m.mtm", wider)
    assert not list(tmp_path.iterdir())

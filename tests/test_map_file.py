from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from meridian_torch.io import map_file
from meridian_torch.io.map_file import MapFileError, load_aerial_map, save_aerial_map
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
    monkeypatch.setattr(map_file, "MAP_FORMAT_VERSION", 3)
    save_aerial_map(_map(), path)
    with pytest.raises(MapFileError, match="format version 3"):
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

"""One map whatever the engine and however the orthophoto is read: windowed file reading, local
worker processes and a local Ray cluster build the map of the whole-image path, array for array,
and an interrupted build resumes from its part files on any engine.

Every build here runs torch single-threaded with one patch per block, so that even the global
descriptors (batched convolutions whose summation order depends on threads and batch) must be
bitwise equal. The Ray tests skip when ray (extra 'distributed') is not installed.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from meridian_torch.cli import app
from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.io.map_file import save_aerial_map
from meridian_torch.io.ortho import Orthophoto, read_orthophoto, write_geotiff, write_orthophoto
from meridian_torch.io.ortho_source import open_orthophoto
from meridian_torch.mapping import aerial_map as aerial_map_module
from meridian_torch.mapping.aerial_map import AerialMapper, build_aerial_map, build_map_file
from meridian_torch.sim.ortho_render import render_orthophoto
from meridian_torch.sim.simulate import build_world
from meridian_torch.types import AerialMap

pytestmark = pytest.mark.usefixtures("single_thread")


def _config(*overrides: str):
    return load_config(CONFIG_DIR / "tiny.yaml", ["aerial_map.batch_size=1", *overrides])


def _mapper(*overrides: str) -> AerialMapper:
    cfg = _config(*overrides)
    return AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives)


@pytest.fixture(scope="module")
def ortho_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The tiny world's orthophoto cropped to 90 m (2 x 2 patches of 60 m), as PNG and GeoTIFF."""
    cfg = _config()
    full = render_orthophoto(build_world(cfg.sim), cfg.sim.ortho, 0)
    n = int(round(90.0 / full.meters_per_pixel))
    ortho = Orthophoto(full.image[:n, :n].copy(), full.meters_per_pixel, (458_000.0, 5_429_000.0), "EPSG:32632")
    folder = tmp_path_factory.mktemp("ortho")
    write_orthophoto(folder, ortho)
    write_geotiff(folder / "ortho.tif", ortho)
    return {"png": folder / "ortho.png", "tif": folder / "ortho.tif"}


@pytest.fixture(scope="module")
def reference_map(ortho_files: dict[str, Path]) -> AerialMap:
    """The whole-image path: read_orthophoto, then build in this process."""
    return build_aerial_map(read_orthophoto(ortho_files["tif"]), _mapper())


def assert_identical(a: AerialMap, b: AerialMap) -> None:
    """Every array of the two maps is bitwise equal."""
    for name, value in vars(a.primitives).items():
        assert torch.equal(value, getattr(b.primitives, name)), name
    assert torch.equal(a.global_descriptors, b.global_descriptors), "global_descriptors"
    for name, value in vars(a.patches).items():
        np.testing.assert_array_equal(value, getattr(b.patches, name), err_msg=name)
    assert (a.meters_per_pixel, a.origin_xy, a.local_origin_xy, a.image_size, a.crs, a.config) == (
        b.meters_per_pixel, b.origin_xy, b.local_origin_xy, b.image_size, b.crs, b.config)


def _build_file(ortho_path: Path, out: Path, *overrides: str, progress=None) -> AerialMap:
    cfg = _config(*overrides)
    return build_map_file(ortho_path, out, cfg.aerial_map, cfg.perception, cfg.primitives, progress=progress)


def _stop_after(blocks: int):
    def progress(done: int, total: int) -> None:
        if done >= blocks:
            raise KeyboardInterrupt

    return progress


def test_reference_map_is_not_empty(reference_map: AerialMap) -> None:
    assert len(reference_map) == 4 and int(reference_map.primitives.point_valid.sum()) > 0


@pytest.mark.parametrize("kind", ["tif", "png"])
def test_windowed_file_build_equals_the_whole_image(ortho_files, reference_map, tmp_path: Path, kind: str) -> None:
    built = _build_file(ortho_files[kind], tmp_path / "map.mtm")
    assert_identical(built, reference_map)
    assert not (tmp_path / "map.mtm.parts").exists() and (tmp_path / "map.mtm").is_file()


def test_map_file_is_the_in_memory_writers_file(ortho_files, reference_map, tmp_path: Path) -> None:
    """build_map_file writes the file from the part files patch by patch: byte for byte the file of
    the whole map written from memory."""
    _build_file(ortho_files["tif"], tmp_path / "map.mtm")
    in_memory = dataclasses.replace(reference_map, source={"orthophoto": str(ortho_files["tif"].resolve())})
    save_aerial_map(in_memory, tmp_path / "memory.mtm")
    assert (tmp_path / "map.mtm").read_bytes() == (tmp_path / "memory.mtm").read_bytes()


def test_interrupted_map_write_keeps_the_old_map_and_resumes(
    ortho_files, reference_map, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Interrupted while the map file is written from the parts: the old map is untouched, no
    temporary file is left, and the next run takes every patch from the parts."""
    out = tmp_path / "map.mtm"
    out.write_bytes(b"the old map")
    read_part, reads = aerial_map_module._read_part, []

    def interrupted(work_dir: Path, index: int, names: tuple[str, ...]):
        reads.append(index)
        if len(reads) == 7:  # after the counts of the 4 patches, within the arrays
            raise KeyboardInterrupt
        return read_part(work_dir, index, names)

    monkeypatch.setattr(aerial_map_module, "_read_part", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _build_file(ortho_files["tif"], out)
    assert out.read_bytes() == b"the old map" and not list(tmp_path.glob(".*"))
    monkeypatch.setattr(aerial_map_module, "_read_part", read_part)
    progress: list[int] = []
    assert_identical(_build_file(ortho_files["tif"], out, progress=lambda d, t: progress.append(d)), reference_map)
    assert progress == [4], "every patch was taken from the parts"


def test_a_part_damaged_before_the_write_is_named_and_built_again(ortho_files, reference_map, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "map.mtm"
    build_parts, damaged = aerial_map_module._build_parts, tmp_path / "map.mtm.parts" / "patch_000002.npz"

    def damage_after(*args, **kwargs) -> None:
        build_parts(*args, **kwargs)
        damaged.write_bytes(damaged.read_bytes()[:100])

    monkeypatch.setattr(aerial_map_module, "_build_parts", damage_after)
    with pytest.raises(aerial_map_module.MapFileError, match=rf"^{damaged}: damaged part file .*run build-map again"):
        _build_file(ortho_files["tif"], out)
    assert not out.exists() and not damaged.exists()
    monkeypatch.setattr(aerial_map_module, "_build_parts", build_parts)
    progress: list[int] = []
    assert_identical(_build_file(ortho_files["tif"], out, progress=lambda d, t: progress.append(d)), reference_map)
    assert progress == [3, 4], "only the damaged patch was built again"


def test_local_workers_open_the_file_themselves(ortho_files, reference_map) -> None:
    with open_orthophoto(ortho_files["tif"]) as source:
        built = build_aerial_map(source, _mapper("aerial_map.workers=2"))
        assert source._opened is None, "the parent read no pixels: the workers did"
    assert_identical(built, reference_map)


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="counts open descriptors in /proc/self/fd (Linux)")
def test_results_kept_from_local_workers_hold_no_file_descriptors(ortho_files) -> None:
    """Tensors sent back through the pool would each hold a shared-memory descriptor open while kept
    (a 4 km^2 map in memory exhausted a 20 000 limit); the kept results must hold none."""
    mapper = _mapper("aerial_map.workers=2", "aerial_map.batch_size=1")
    with open_orthophoto(ortho_files["tif"]) as source:
        grid = aerial_map_module._patch_grid(source, mapper)
        kept: dict = {}
        before = len(os.listdir("/proc/self/fd"))
        aerial_map_module._describe_missing(source, mapper, grid, set(), kept.__setitem__, None)
        after = len(os.listdir("/proc/self/fd"))
    assert len(kept) == len(grid) >= 4
    assert after - before < len(grid), f"{after - before} descriptors left open by {len(grid)} kept patches"


def test_worker_arrays_become_tensors_the_caller_can_write() -> None:
    """Ray returns a block's arrays as read-only views of its object store: those are copied (kept
    as they are, the tensors could not be written and would hold the store's memory while the
    caller keeps them); the local pool's own arrays are taken without a copy."""
    from meridian_torch.mapping.aerial_engines import _from_arrays

    rng = np.random.default_rng(0)
    patch = {"points_xy": rng.normal(size=(3, 2)), "point_descriptors": rng.normal(size=(3, 8)),
             "point_segment_ids": np.arange(3), "line_endpoints": rng.normal(size=(2, 2, 2)),
             "line_kinds": np.ones(2, dtype=np.int64), "line_descriptors": rng.normal(size=(2, 8)),
             "line_segment_ids": np.arange(2)}
    desc = rng.normal(size=16).astype(np.float32)
    for writable in (True, False):
        for a in [*patch.values(), desc]:
            a.setflags(write=writable)
        ((primitives, global_desc),) = _from_arrays([(patch, desc)])
        tensors = {**{name: getattr(primitives, name) for name in patch}, "desc": global_desc}
        for name, source in {**patch, "desc": desc}.items():
            tensor = tensors[name]
            assert torch.equal(tensor, torch.from_numpy(source.copy())), name
            assert np.shares_memory(tensor.numpy(), source) == writable, (name, writable)


def test_interrupted_file_build_resumes_with_other_workers(ortho_files, reference_map, tmp_path: Path) -> None:
    out = tmp_path / "map.mtm"
    with pytest.raises(KeyboardInterrupt):
        _build_file(ortho_files["tif"], out, "aerial_map.workers=2", progress=_stop_after(2))
    assert len(list((tmp_path / "map.mtm.parts").glob("patch_*.npz"))) == 2 and not out.exists()
    progress: list[int] = []
    assert_identical(_build_file(ortho_files["tif"], out, progress=lambda d, t: progress.append(d)), reference_map)
    assert progress[0] == 2, "the finished patches were reused"


def test_ray_engine_without_ray_names_the_extra(ortho_files, monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    from meridian_torch.errors import ConfigError

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(ConfigError, match=r"needs Ray.*pip install -e '\.\[distributed\]'"):
        build_aerial_map(read_orthophoto(ortho_files["tif"]), _mapper("aerial_map.engine=ray"))


def test_build_map_cli_backend_ray(ortho_files, reference_map, tmp_path: Path) -> None:
    """`build-map --backend ray` starts its own local cluster (2 CPUs) and stops it."""
    ray = pytest.importorskip("ray")
    assert not ray.is_initialized()
    out = tmp_path / "map.mtm"
    result = CliRunner().invoke(app, ["build-map", str(ortho_files["tif"]), "--out", str(out), "-c",
                                      str(CONFIG_DIR / "tiny.yaml"), "--set", "aerial_map.batch_size=1",
                                      "--backend", "ray", "--workers", "2"])
    assert result.exit_code == 0, result.output
    assert not ray.is_initialized(), "the cluster it started is stopped"
    from meridian_torch.io.map_file import load_aerial_map

    assert_identical(load_aerial_map(out), reference_map)


def test_address_without_ray_backend_is_refused(ortho_files, tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["build-map", str(ortho_files["tif"]), "--out", str(tmp_path / "m.mtm"),
                                      "--address", "head:6379"])
    assert result.exit_code == 2 and "an address is for the Ray engine" in result.output


@pytest.fixture(scope="module")
def ray_cluster():
    """A local Ray cluster with 2 CPUs shared by the tests below (the engine uses it as it is)."""
    ray = pytest.importorskip("ray")
    ray.init(address="local", num_cpus=2, include_dashboard=False)
    yield ray
    ray.shutdown()


def test_ray_builds_the_local_map(ray_cluster, ortho_files, reference_map, tmp_path: Path) -> None:
    progress: list[int] = []
    built = _build_file(ortho_files["tif"], tmp_path / "map.mtm", "aerial_map.engine=ray", "aerial_map.workers=2",
                        progress=lambda d, t: progress.append(d))
    assert_identical(built, reference_map)
    assert progress == [0, 1, 2, 3, 4]  # every block reported, in order
    assert ray_cluster.is_initialized(), "a cluster the caller started is left running"


def test_ray_results_come_in_block_order_from_every_actor(ray_cluster) -> None:
    """More blocks than the actors' slots, finishing out of order: every block once, in order, and
    both actors did work (they get the next block as slots free, not one block each)."""
    from meridian_torch.mapping.aerial_engines import _in_order

    class Echo:
        def describe(self, indices: np.ndarray) -> list:
            import os
            import time

            time.sleep(0.02 * (int(indices[0]) % 3))
            return [(int(indices[0]), os.getpid())]

    actors = [ray_cluster.remote(num_cpus=1)(Echo).remote() for _ in range(2)]
    try:
        results = list(_in_order(ray_cluster, actors, [np.array([i]) for i in range(11)]))
    finally:
        for actor in actors:
            ray_cluster.kill(actor)
    assert [block[0][0] for block in results] == list(range(11))
    assert len({block[0][1] for block in results}) == 2


@pytest.mark.parametrize("resume_engine", ["ray", "local"])
def test_interrupted_ray_build_resumes(ray_cluster, ortho_files, reference_map, tmp_path: Path,
                                       resume_engine: str) -> None:
    out = tmp_path / "map.mtm"
    with pytest.raises(KeyboardInterrupt):
        _build_file(ortho_files["png"], out, "aerial_map.engine=ray", "aerial_map.workers=2",
                    progress=_stop_after(1))
    assert len(list((tmp_path / "map.mtm.parts").glob("patch_*.npz"))) == 1 and not out.exists()
    progress: list[int] = []
    workers = 2 if resume_engine == "ray" else 1
    resumed = _build_file(ortho_files["png"], out, f"aerial_map.engine={resume_engine}",
                          f"aerial_map.workers={workers}", progress=lambda d, t: progress.append(d))
    assert progress[0] == 1, "the finished patch was reused"
    assert_identical(resumed, reference_map)

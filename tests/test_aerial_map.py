"""Aerial map building on a small simulated orthophoto: batching, resumption, the CLI."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from numerics import assert_close_reassociated
from typer.testing import CliRunner

from meridian_torch.cli import app
from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.io.map_file import load_aerial_map
from meridian_torch.io.ortho import Orthophoto, write_orthophoto
from meridian_torch.mapping.aerial_map import AerialMapper, _segment_pixels, build_aerial_map
from meridian_torch.perception.protocols import Segmentation
from meridian_torch.sim.ortho_render import render_orthophoto
from meridian_torch.sim.simulate import build_world

CFG = load_config(CONFIG_DIR / "tiny.yaml")


@pytest.fixture(scope="module")
def ortho() -> Orthophoto:
    world = build_world(CFG.sim)
    full = render_orthophoto(world, CFG.sim.ortho, 0)
    n = int(round(90.0 / full.meters_per_pixel))  # 90 m: a 2 x 2 grid of 60 m patches
    return Orthophoto(full.image[:n, :n].copy(), full.meters_per_pixel, full.origin_xy)


def _mapper(batch_size: int, workers: int = 1) -> AerialMapper:
    cfg = load_config(CONFIG_DIR / "tiny.yaml", [f"aerial_map.batch_size={batch_size}", f"aerial_map.workers={workers}"])
    return AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives)


def _assert_same(a, b) -> None:
    """The same map. Primitives and their descriptors are computed patch by patch: bitwise equal.
    Global descriptors pool each patch image through batched convolutions whose summation order
    depends on the batch (oneDNN), so they agree to the rounding of a reduction over the patch's
    pixels (tests/numerics.py)."""
    for name in ("points_xy", "point_valid", "point_descriptors", "line_endpoints", "line_kinds", "line_valid",
                 "line_descriptors"):
        assert torch.equal(getattr(a.primitives, name), getattr(b.primitives, name)), name
    box = b.patches.pixel_boxes
    n_pixels = int(((box[:, 2] - box[:, 0]) * (box[:, 3] - box[:, 1])).max())
    assert_close_reassociated(a.global_descriptors, b.global_descriptors, n_terms=n_pixels)


@pytest.fixture(scope="module")
def reference_map(ortho: Orthophoto):
    return build_aerial_map(ortho, _mapper(4))


def test_map_has_primitives_inside_their_patches(reference_map) -> None:
    prims = reference_map.primitives
    assert len(reference_map) == 4
    assert int(prims.point_valid.sum()) > 0 and int(prims.line_valid.sum()) > 0
    bounds = torch.from_numpy(reference_map.patches.bounds_xy).float()
    x, y = prims.points_xy[..., 0], prims.points_xy[..., 1]
    inside = (x >= bounds[:, None, 0]) & (x <= bounds[:, None, 1]) & (y >= bounds[:, None, 2]) & (y <= bounds[:, None, 3])
    assert bool(inside[prims.point_valid].all()), "points lie in their patch (world frame, not image frame)"
    norms = prims.line_descriptors[prims.line_valid].norm(dim=1)
    assert torch.allclose(norms, torch.ones_like(norms), atol=1e-4)


def test_batched_equals_one_patch_at_a_time(ortho: Orthophoto, reference_map) -> None:
    _assert_same(build_aerial_map(ortho, _mapper(1)), reference_map)


class _MasksOnly:
    """A segmenter whose results carry masks but no label image (as the neural back ends')."""

    def __init__(self, inner) -> None:
        self.inner = inner

    def segment(self, images: torch.Tensor, meters_per_pixel: float | None) -> Segmentation:
        seg = self.inner.segment(images, meters_per_pixel)
        assert seg.labels is not None  # the classical back end gives labels: both paths are run
        return dataclasses.replace(seg, labels=None)


def test_segment_pixels_from_labels_equal_those_from_masks(ortho: Orthophoto, reference_map) -> None:
    """The map built from the masks alone is the map built from the label image."""
    mapper = _mapper(4)
    _assert_same(build_aerial_map(ortho, dataclasses.replace(mapper, segmenter=_MasksOnly(mapper.segmenter))),
                 reference_map)


@pytest.mark.parametrize("n_segments", [1, 7, 300, 70000])
def test_segment_pixels_of_a_partition_are_torch_nonzeros(n_segments: int) -> None:
    """Random label images, padded masks, 8-, 16- and 32-bit labels: each segment's pixels in
    nonzero's order (segment, then row-major) and its count; labels beyond the valid masks are refused."""
    rng = np.random.default_rng(n_segments)
    h, w = (20, 30) if n_segments > 1000 else (37, 53)  # most of 70000 segments empty: masks stay small
    labels = torch.from_numpy(rng.integers(0, n_segments, (1, h, w)))
    m = n_segments + 2  # padding
    masks = labels[:, None] == torch.arange(m)[None, :, None, None]
    valid = torch.arange(m)[None] < n_segments
    seg = Segmentation(masks=masks, scores=valid.float(), valid=valid, labels=labels)
    rows, cols, counts = _segment_pixels(seg, 0)
    idx_m, rows_ref, cols_ref = torch.nonzero(masks[0][valid[0]], as_tuple=True)
    assert np.array_equal(rows, rows_ref.numpy()) and np.array_equal(cols, cols_ref.numpy())
    assert np.array_equal(counts, torch.bincount(idx_m, minlength=n_segments).numpy())
    bad = dataclasses.replace(seg, valid=torch.arange(m)[None] < int(labels.max()))  # the largest label left out
    with pytest.raises(ValueError, match="labels"):
        _segment_pixels(bad, 0)


def test_worker_processes_build_the_same_map(ortho: Orthophoto, reference_map) -> None:
    progress = []
    built = build_aerial_map(ortho, _mapper(1, workers=2), progress=lambda d, t: progress.append(d))
    _assert_same(built, reference_map)
    assert progress == [0, 1, 2, 3, 4]  # every batch reported, in order
    assert built.config == reference_map.config  # the worker count does not shape the map


@pytest.mark.parametrize("workers", [1, 2])
def test_interrupted_build_resumes(ortho: Orthophoto, reference_map, tmp_path: Path, workers: int) -> None:
    work = tmp_path / "parts"
    calls = []

    def interrupt(done: int, total: int) -> None:
        calls.append(done)
        if done >= 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_aerial_map(ortho, _mapper(1, workers), work_dir=work, progress=interrupt)
    assert len(list(work.glob("patch_*.npz"))) == 2
    progress = []
    resumed = build_aerial_map(ortho, _mapper(1), work_dir=work, progress=lambda d, t: progress.append(d))
    assert progress[0] == 2, "the two finished patches were reused"
    _assert_same(resumed, reference_map)


def test_a_damaged_part_file_is_built_again(ortho: Orthophoto, reference_map, tmp_path: Path) -> None:
    work = tmp_path / "parts"

    def interrupt(done: int, total: int) -> None:
        if done >= 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_aerial_map(ortho, _mapper(1), work_dir=work, progress=interrupt)
    parts = sorted(work.glob("patch_*.npz"))
    parts[1].write_bytes(parts[1].read_bytes()[:100])  # truncated, as by a full disk
    messages, progress = [], []
    resumed = build_aerial_map(ortho, _mapper(1), work_dir=work, progress=lambda d, t: progress.append(d),
                               on_message=messages.append)
    assert messages == [f"{parts[1]}: damaged part file, building that patch again"]
    assert progress[0] == 2, "the two intact patches were reused"
    _assert_same(resumed, reference_map)


def test_build_and_show_map_cli(ortho: Orthophoto, reference_map, tmp_path: Path) -> None:
    write_orthophoto(tmp_path / "aerial", ortho)
    out = tmp_path / "map.mtm"
    runner = CliRunner()
    result = runner.invoke(app, ["build-map", str(tmp_path / "aerial"), "--out", str(out),
                                 "-c", str(CONFIG_DIR / "tiny.yaml"), "--workers", "2"])
    assert result.exit_code == 0, result.output
    assert out.is_file() and not (tmp_path / "map.mtm.parts").exists()
    loaded = load_aerial_map(out)
    assert loaded.image_size == ortho.size_px and len(loaded) == 4
    _assert_same(loaded, reference_map)  # written and read back, from worker processes
    result = runner.invoke(app, ["show-map", str(out), "--out", str(tmp_path / "map.png")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "map.png").stat().st_size > 10_000


def test_missing_orthophoto_is_a_clear_error(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["build-map", str(tmp_path / "nothing"), "--out", str(tmp_path / "m.mtm")])
    assert result.exit_code == 1
    assert "nothing" in result.output and "Traceback" not in result.output


def test_sub_crop_segmentation_stays_in_the_patch(ortho: Orthophoto) -> None:
    cfg = load_config(CONFIG_DIR / "tiny.yaml", ["aerial_map.segmentation_crop_m=40"])
    crop_map = build_aerial_map(ortho, AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives))
    prims = crop_map.primitives
    assert int(prims.point_valid.sum()) > 0 and int(prims.line_valid.sum()) > 0
    bounds = torch.from_numpy(crop_map.patches.bounds_xy).float()
    ends = prims.line_endpoints[prims.line_valid]
    owner = torch.nonzero(prims.line_valid)[:, 0]
    lo = torch.stack([bounds[owner, 0], bounds[owner, 2]], dim=1)[:, None]
    hi = torch.stack([bounds[owner, 1], bounds[owner, 3]], dim=1)[:, None]
    assert bool(((ends >= lo - 1e-3) & (ends <= hi + 1e-3)).all())

"""ONNX export checked against eager torch, the onnxruntime ground engine, and `meridian-torch export`.

Every model is the tiny random version from configs/tiny.yaml; the five graphs are exported once
per module and shared by the parity, describer and CLI tests.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn
from typer.testing import CliRunner

from meridian_torch.config import CONFIG_DIR, MeridianConfig, load_config
from meridian_torch.core.onnx_runtime import graph_metadata, open_session, run_session
from meridian_torch.errors import ConfigError, ExportError
from meridian_torch.export import onnx as onnx_export
from meridian_torch.export.models import EXPORTABLE_MODELS, export_model
from meridian_torch.export.onnx import export_checked
from meridian_torch.perception.factory import build_ground_perception
from meridian_torch.perception.neural.onnx_backends import clear_session_cache

pytest.importorskip("onnxruntime")

TINY = CONFIG_DIR / "tiny.yaml"
# random tiny models in float32: onnxruntime only reorders sums
PARITY_ATOL = 1e-4


def _tiny(*overrides: str) -> MeridianConfig:
    return load_config(TINY, list(overrides))


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, object]]:
    folder = tmp_path_factory.mktemp("graphs")
    perception = _tiny().perception
    return {name: (folder / f"{name}.onnx", export_model(name, perception, folder / f"{name}.onnx"))
            for name in EXPORTABLE_MODELS}


@pytest.mark.parametrize("name", list(EXPORTABLE_MODELS))
def test_every_model_exports_with_parity(exported: dict, name: str) -> None:
    path, report = exported[name]
    assert path.is_file() and report.path == path
    assert len(report.checks) == 2  # the example and a second batch / image / prompt size
    assert 0 <= report.max_abs_diff <= PARITY_ATOL, report.checks
    assert all(c.within_tolerance for c in report.checks)
    meta = graph_metadata(open_session(path))
    assert meta["meridian.model"] == name
    # no stray staging folders or data files next to the graph
    assert sorted(p.name for p in path.parent.iterdir() if p.name.startswith(name) or p.name.startswith(".")) == [
        path.name
    ]


def test_dinov2_graph_keeps_batch_and_image_size_dynamic(exported: dict) -> None:
    from meridian_torch.perception.neural.dinov2 import DinoDenseFeatures
    from meridian_torch.perception.neural.runtime_cache import shared_dinov2

    path, report = exported["dinov2-dense"]
    batch, channels, height, width = report.inputs["images"]
    assert channels == 3 and not any(isinstance(d, int) for d in (batch, height, width))
    c = _tiny().perception.descriptor.dinov2
    model = DinoDenseFeatures(shared_dinov2(c.architecture, None, c.random_weights_seed, "test"))
    images = torch.rand(3, 3, 70, 98, generator=torch.Generator().manual_seed(5))  # a size never exported
    got = run_session(open_session(path), {"images": images.numpy()})[0]
    with torch.no_grad():
        expected = model(images).numpy()
    assert got.shape == expected.shape == (3, model.dim, 5, 7)
    assert np.abs(got - expected).max() <= PARITY_ATOL


class _SignBranch(nn.Module):
    """Traces only the branch of its example input: a second input of the other sign differs."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * 2 if bool(x.sum() > 0) else x * 3


class _FixedBatch(nn.Module):
    """Bakes the example batch size into the graph through a Python int."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.reshape(int(x.shape[0]), -1).sum(dim=1)


@pytest.mark.parametrize(
    ("module", "example", "check"),
    [
        (_SignBranch(), torch.ones(2, 3), torch.full((2, 3), -1.0)),
        (_FixedBatch(), torch.ones(2, 3, 4), torch.ones(3, 3, 4)),
    ],
    ids=["traced-branch", "fixed-batch"],
)
def test_failed_check_leaves_destination_untouched(
    tmp_path: Path, module: nn.Module, example: torch.Tensor, check: torch.Tensor
) -> None:
    path = tmp_path / "model.onnx"
    path.write_bytes(b"previous")
    with pytest.raises(ExportError, match=str(path)):
        export_checked(module, (example,), path, input_names=["x"], output_names=["y"],
                       dynamic_axes={"x": [0]}, check_inputs=[(check,)])
    assert path.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["model.onnx"]  # staging folder removed


def test_dynamic_axes_need_a_second_size(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="check_inputs"):
        export_checked(nn.Identity(), (torch.ones(2, 3),), tmp_path / "m.onnx", input_names=["x"],
                       output_names=["y"], dynamic_axes={"x": [0]})


@pytest.mark.slow  # the dynamo exporter takes ~10 s even for this model
def test_large_weights_go_to_one_external_data_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(onnx_export, "EXTERNAL_DATA_MIN_BYTES", 0)  # treat a small model as a huge one
    model = nn.Sequential(nn.Linear(8, 64), nn.ReLU(), nn.Linear(64, 4))  # > 1 KiB tensors are stored outside
    path = tmp_path / "big.onnx"
    report = export_checked(model, (torch.randn(2, 8),), path, input_names=["x"], output_names=["y"],
                            exporter="dynamo", metadata={"meridian.model": "test"})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.onnx", "big.onnx.data"]
    assert report.max_abs_diff <= PARITY_ATOL
    x = torch.randn(2, 8)
    session = open_session(path)
    assert graph_metadata(session)["meridian.model"] == "test"
    with torch.no_grad():
        np.testing.assert_allclose(run_session(session, {"x": x.numpy()})[0], model(x).numpy(), atol=PARITY_ATOL)


def _onnx_config(exported: dict, *overrides: str) -> MeridianConfig:
    paths = {name: path for name, (path, _) in exported.items()}
    return _tiny(
        "perception.ground_engine=onnx",
        "perception.descriptor.backend=dinov2",
        f"perception.onnx.dinov2_dense_path={paths['dinov2-dense']}",
        f"perception.onnx.anyloc_facet_path={paths['anyloc-facet']}",
        f"perception.onnx.vlad_head_path={paths['vlad-head']}",
        *overrides,
    )


def _blob_masks(b: int, m: int, h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(b, m, 2, generator=g) * torch.tensor([h, w])
    radii = 4 + torch.rand(b, m, generator=g) * 20
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    d2 = (yy - centres[..., 0, None, None]) ** 2 + (xx - centres[..., 1, None, None]) ** 2
    masks = d2 < radii[..., None, None] ** 2
    valid = torch.ones(b, m, dtype=torch.bool)
    valid[1, -2:] = False  # padding rows
    return masks & valid[..., None, None], valid


@pytest.mark.parametrize("global_backend", ["anyloc", "gem"])
def test_onnx_engine_matches_torch_without_running_torch_models(
    exported: dict, global_backend: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    clear_session_cache()
    onnx_cfg = _onnx_config(exported, f"perception.global_descriptor.backend={global_backend}")
    torch_perception = onnx_cfg.perception.model_copy(update={"ground_engine": "torch"})
    _, torch_describer, torch_global = build_ground_perception(torch_perception)
    _, onnx_describer, onnx_global = build_ground_perception(onnx_cfg.perception)
    images = torch.rand(2, 3, 72, 128, generator=torch.Generator().manual_seed(1))
    masks, valid = _blob_masks(2, 6, 72, 128, seed=2)
    expected_segments = torch_describer.describe(images, masks, valid)
    expected_global = torch_global.describe(images)

    def no_torch_models(self: nn.Module, *args: object, **kwargs: object) -> None:
        raise AssertionError(f"torch module {type(self).__name__} ran on the onnx engine")

    monkeypatch.setattr(nn.Module, "__call__", no_torch_models)
    segments = onnx_describer.describe(images, masks, valid)
    global_desc = onnx_global.describe(images)
    monkeypatch.undo()

    assert onnx_describer.dim == torch_describer.dim and onnx_global.dim == torch_global.dim
    assert segments.shape == expected_segments.shape == (2, 6, torch_describer.dim)
    assert torch.all(segments[~valid] == 0)
    assert (segments - expected_segments).abs().max() <= PARITY_ATOL
    assert global_desc.shape == expected_global.shape == (2, torch_global.dim)
    assert (global_desc - expected_global).abs().max() <= PARITY_ATOL


def test_onnx_engine_rejects_mismatched_or_missing_graphs(exported: dict) -> None:
    clear_session_cache()
    # graphs were exported from block 2; the config asks for block 1
    cfg = _onnx_config(exported, "perception.global_descriptor.backend=anyloc",
                       "perception.global_descriptor.anyloc.layer=1")
    with pytest.raises(ConfigError, match="layer '2'.*'1'"):
        build_ground_perception(cfg.perception)
    cfg = _onnx_config(exported, "perception.onnx.dinov2_dense_path=null")
    with pytest.raises(ConfigError, match="perception.onnx.dinov2_dense_path"):
        build_ground_perception(cfg.perception)
    cfg = _onnx_config(exported, "perception.ground_segmenter.backend=sam")
    with pytest.raises(ConfigError, match="ground_segmenter.backend: 'sam'"):
        build_ground_perception(cfg.perception)


def test_cli_export_prints_parity(tmp_path: Path) -> None:
    from meridian_torch.cli import app

    runner = CliRunner()
    out = tmp_path / "vlad.onnx"
    result = runner.invoke(app, ["export", "vlad-head", "--out", str(out), "-c", str(TINY)])
    assert result.exit_code == 0, result.output
    assert out.is_file() and "max abs difference" in result.output
    result = runner.invoke(app, ["export", "dinov3", "--out", str(out), "-c", str(TINY)])
    assert result.exit_code == 2 and "dinov2-dense" in result.output


@pytest.mark.slow  # renders the tiny world and maps it twice
def test_torch_and_onnx_engines_give_the_same_ground_primitives(exported: dict, tmp_path: Path) -> None:
    from meridian_torch.io.sequence import SequenceReader
    from meridian_torch.mapping.ground_map import GroundMapper
    from meridian_torch.runtime import resolve_runtime
    from meridian_torch.sim.simulate import simulate_sequence

    clear_session_cache()
    onnx_cfg = _onnx_config(exported, "perception.global_descriptor.backend=anyloc")
    simulate_sequence(onnx_cfg.sim, tmp_path / "seq")
    reader = SequenceReader(tmp_path / "seq")
    runtime = resolve_runtime(onnx_cfg.runtime)

    def run(engine: str) -> list:
        perception = onnx_cfg.perception.model_copy(update={"ground_engine": engine})
        mapper = GroundMapper(onnx_cfg.ground_map, onnx_cfg.primitives, reader.camera,
                              *build_ground_perception(perception), runtime)
        submaps = []
        for start in range(0, len(reader), 8):
            submaps += mapper.add_frames([reader[i] for i in range(start, min(start + 8, len(reader)))])
        return submaps + mapper.finish()

    by_torch, by_onnx = run("torch"), run("onnx")
    assert len(by_torch) == len(by_onnx) >= 1
    assert sum(len(s.primitives.points_xy) + len(s.primitives.line_endpoints) for s in by_torch) > 0
    for a, b in zip(by_torch, by_onnx):
        pa, pb = a.primitives, b.primitives
        assert torch.equal(pa.point_segment_ids, pb.point_segment_ids)
        assert torch.equal(pa.line_kinds, pb.line_kinds)
        torch.testing.assert_close(pa.points_xy, pb.points_xy, atol=1e-5, rtol=0)
        torch.testing.assert_close(pa.line_endpoints, pb.line_endpoints, atol=1e-5, rtol=0)
        torch.testing.assert_close(pa.point_descriptors, pb.point_descriptors, atol=PARITY_ATOL, rtol=0)
        torch.testing.assert_close(pa.line_descriptors, pb.line_descriptors, atol=PARITY_ATOL, rtol=0)
        torch.testing.assert_close(a.frame_descriptors, b.frame_descriptors, atol=PARITY_ATOL, rtol=0)

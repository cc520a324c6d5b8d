"""AnyLoc: VLAD and GeM against loop references, the facet extractor, vocabularies and fit-vocabulary."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image
from typer.testing import CliRunner

from meridian_torch.cli import app
from meridian_torch.config.perception import GlobalDescriptorConfig
from meridian_torch.errors import ModelWeightsError
from meridian_torch.perception.factory import build_global_describer
from meridian_torch.perception.neural.anyloc import (
    AnyLocFacet,
    Vocabulary,
    fit_vocabulary,
    gem,
    load_vocabulary,
    save_vocabulary,
    vlad,
)
from meridian_torch.perception.neural.dinov2 import build_dinov2
from meridian_torch.perception.neural.weights import initialize_weights


def vlad_loop(tokens: torch.Tensor, centers: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """One image and one token at a time, as AnyLoc's VLAD.generate describes it."""
    unit_centers = F.normalize(centers, dim=1)
    out = []
    for b in range(tokens.shape[0]):
        residuals = torch.zeros_like(centers)
        for n in range(tokens.shape[1]):
            if valid[b, n]:
                k = int(torch.argmax(unit_centers @ tokens[b, n]))
                residuals[k] += tokens[b, n] - centers[k]
        for k in range(centers.shape[0]):
            if residuals[k].norm() > 0:
                residuals[k] /= residuals[k].norm()
        flat = residuals.flatten()
        out.append(flat / flat.norm())
    return torch.stack(out)


def test_vlad_equals_loop_reference() -> None:
    g = torch.Generator().manual_seed(0)
    tokens = F.normalize(torch.randn(3, 40, 8, generator=g, dtype=torch.float64), dim=-1)
    centers = torch.randn(6, 8, generator=g, dtype=torch.float64) * 0.7  # raw, not unit, as k-means means are
    valid = torch.rand(3, 40, generator=g) > 0.3
    got = vlad(tokens, centers, valid)
    assert got.shape == (3, 48)
    torch.testing.assert_close(got, vlad_loop(tokens, centers, valid))
    torch.testing.assert_close(vlad(tokens, centers), vlad_loop(tokens, centers, torch.ones_like(valid)))


def test_vlad_empty_clusters_are_zero() -> None:
    centers = torch.eye(4)
    tokens = F.normalize(torch.tensor([[[1.0, 0.1, 0, 0], [0.9, 0, 0.2, 0]]]), dim=-1)  # all near centre 0
    out = vlad(tokens, centers).view(4, 4)
    assert out[0].norm() == pytest.approx(1.0)
    assert torch.all(out[1:] == 0)


def test_gem_equals_formula() -> None:
    g = torch.Generator().manual_seed(1)
    tokens = torch.randn(2, 30, 5, generator=g, dtype=torch.float64)
    valid = torch.rand(2, 30, generator=g) > 0.5
    for b in range(2):
        x = tokens[b, valid[b]]
        m = (x**3).mean(dim=0)
        expected = F.normalize(m.sign() * m.abs() ** (1 / 3), dim=0)
        torch.testing.assert_close(gem(tokens, 3.0, valid)[b], expected)
    # p = 1 is the normalized mean
    torch.testing.assert_close(gem(tokens, 1.0), F.normalize(tokens.mean(dim=1), dim=-1))


def _tiny_facet(layer: int, facet: str = "value", seed: int = 0) -> AnyLocFacet:
    return AnyLocFacet(initialize_weights(build_dinov2("tiny_reg"), None, seed, "test"), layer, facet).eval()


def test_facet_tokens_are_unit_and_skip_later_blocks() -> None:
    model = _tiny_facet(layer=1)
    x = torch.rand(2, 3, 42, 56)
    with torch.no_grad():
        tokens = model(x)
        assert tokens.shape == (2, 12, 48)  # 3 x 4 patches, CLS and registers dropped
        torch.testing.assert_close(tokens.norm(dim=-1), torch.ones(2, 12))
        with torch.no_grad():
            for p in model.backbone.blocks[2].parameters():
                p.fill_(float("nan"))  # block 2 must not run
        torch.testing.assert_close(model(x), tokens)


def test_vocabulary_files(tmp_path: Path) -> None:
    centers = torch.randn(4, 48)
    anyloc_file = tmp_path / "c_centers.pt"
    torch.save(centers, anyloc_file)  # AnyLoc publishes a bare (K, D) tensor
    loaded = load_vocabulary(anyloc_file)
    assert torch.equal(loaded.centers, centers) and loaded.layer is None
    loaded.check_fits(anyloc_file, dim=48, architecture="tiny", layer=1, facet="value")

    ours = tmp_path / "vocab.pt"
    save_vocabulary(ours, Vocabulary(centers, architecture="tiny", layer=1, facet="value"))
    again = load_vocabulary(ours)
    assert torch.equal(again.centers, centers) and (again.architecture, again.layer, again.facet) == ("tiny", 1, "value")
    with pytest.raises(ModelWeightsError, match="layer 1 \\(configured: 2\\)"):
        again.check_fits(ours, dim=48, architecture="tiny", layer=2, facet="value")
    with pytest.raises(ModelWeightsError, match="dimension 48"):
        again.check_fits(ours, dim=64, architecture="tiny", layer=1, facet="value")
    with pytest.raises(ModelWeightsError, match="vocabulary file not found") as info:
        load_vocabulary(tmp_path / "absent.pt")
    assert str(tmp_path / "absent.pt") in str(info.value)
    torch.save(torch.randn(48), tmp_path / "flat.pt")
    with pytest.raises(ModelWeightsError, match="\\(K, D\\)"):
        load_vocabulary(tmp_path / "flat.pt")


def test_fit_vocabulary_is_seeded() -> None:
    model = _tiny_facet(layer=2)
    images = [torch.rand(1, 3, 60 + 14 * i, 70) for i in range(3)]
    kwargs = dict(num_clusters=5, resize_short_side_px=None, tokens_per_image=10)
    a = fit_vocabulary(model, images, seed=3, **kwargs)
    b = fit_vocabulary(model, images, seed=3, **kwargs)
    c = fit_vocabulary(model, images, seed=4, **kwargs)
    assert a.shape == (5, 48)
    assert torch.equal(a, b) and not torch.equal(a, c)
    torch.testing.assert_close(a.norm(dim=1), torch.ones(5))


def _tiny_anyloc_overrides(extra: list[str]) -> list[str]:
    base = [
        "perception.global_descriptor.backend=anyloc",
        "perception.global_descriptor.anyloc.architecture=tiny",
        "perception.global_descriptor.anyloc.random_weights_seed=0",
        "perception.global_descriptor.anyloc.layer=2",
        "perception.global_descriptor.anyloc.num_clusters=3",
    ]
    return [arg for item in base + extra for arg in ("--set", item)]


def test_fit_vocabulary_command_feeds_the_describer(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    paths = []
    for i in range(2):
        paths.append(tmp_path / f"img{i}.png")
        Image.fromarray(rng.integers(0, 255, (50, 64, 3), dtype=np.uint8)).save(paths[-1])
    out = tmp_path / "vocab.pt"
    result = CliRunner().invoke(
        app, ["fit-vocabulary", *map(str, paths), "--out", str(out), "--seed", "1", *_tiny_anyloc_overrides([])]
    )
    assert result.exit_code == 0, result.output
    assert load_vocabulary(out).centers.shape == (3, 48)

    cfg = GlobalDescriptorConfig.model_validate(
        {"backend": "anyloc", "anyloc": {"architecture": "tiny", "random_weights_seed": 0, "layer": 2,
                                         "num_clusters": 3, "vocabulary_path": str(out)}}
    )
    describer = build_global_describer(cfg)
    desc = describer.describe(torch.rand(2, 3, 50, 64))
    assert describer.dim == 3 * 48 and desc.shape == (2, 144)
    torch.testing.assert_close(desc.norm(dim=1), torch.ones(2))

    # the vocabulary remembers its layer: using it with another layer is an error naming the file
    bad = cfg.model_copy(update={"anyloc": cfg.anyloc.model_copy(update={"layer": 1})})
    with pytest.raises(ModelWeightsError, match=str(out)):
        build_global_describer(bad)


def test_fit_vocabulary_command_reports_unreadable_images(tmp_path: Path) -> None:
    bad = tmp_path / "not_an_image.png"
    bad.write_text("hello")
    result = CliRunner().invoke(app, ["fit-vocabulary", str(bad), "--out", str(tmp_path / "v.pt"), *_tiny_anyloc_overrides([])])
    assert result.exit_code == 1
    assert "not a readable image" in result.output and not (tmp_path / "v.pt").exists()

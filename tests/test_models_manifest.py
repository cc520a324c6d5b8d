"""models/manifest.yaml: the shipped entries, hash verification statuses, recording, and the CLI."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from meridian_torch.cli import app
from meridian_torch.core.paths import MODELS_ENV, models_dir, shipped_dir
from meridian_torch.errors import ConfigError
from meridian_torch.export.manifest import load_manifest, verify_models

runner = CliRunner()


def test_shipped_manifest_lists_every_model_family() -> None:
    m = load_manifest()
    names = {e.name for e in m.entries}
    expected = {"sam_vit_b", "sam_vit_l", "sam_vit_h", "fastsam_x", "fastsam_s", "anyloc_urban_vocabulary"}
    expected |= {f"dinov2_vit{s}14{r}" for s in "sblg" for r in ("", "_reg")}
    assert expected <= names
    assert len({e.file for e in m.entries}) == len(m.entries)
    assert all(e.source.startswith("http") and e.license for e in m.entries)
    assert m.folder == models_dir() and (shipped_dir("models") / "README.md").is_file()


@pytest.fixture
def manifest_copy(tmp_path: Path) -> Path:
    path = tmp_path / "manifest.yaml"
    shutil.copy(shipped_dir("models") / "manifest.yaml", path)
    return path


def test_verify_tells_ok_mismatch_missing_and_unrecorded_apart(manifest_copy: Path) -> None:
    folder = manifest_copy.parent
    good, bad = b"sam weights", b"dinov2 weights"
    text = manifest_copy.read_text()
    # record hashes by hand for two entries: one file matches, the other was changed since
    for name, content in (("sam_vit_b", good), ("dinov2_vits14", b"original")):
        entry_start = text.index(f"name: {name}\n")
        null_at = text.index("sha256: null", entry_start)
        text = text[:null_at] + f"sha256: {hashlib.sha256(content).hexdigest()}" + text[null_at + len("sha256: null"):]
    manifest_copy.write_text(text)
    m = load_manifest(manifest_copy)
    (folder / m.entry("sam_vit_b").file).write_bytes(good)
    (folder / m.entry("dinov2_vits14").file).write_bytes(bad)
    (folder / m.entry("fastsam_x").file).write_bytes(b"my export")
    status = {r.entry.name: r for r in verify_models(m)}
    assert status["sam_vit_b"].status == "ok" and not status["sam_vit_b"].failed
    assert status["dinov2_vits14"].status == "mismatch" and status["dinov2_vits14"].failed
    assert status["fastsam_x"].status == "no hash recorded" and not status["fastsam_x"].failed
    assert status["sam_vit_h"].status == "missing" and status["sam_vit_h"].failed
    assert status["dinov2_vits14"].sha256 == hashlib.sha256(bad).hexdigest()


def test_record_fills_only_missing_hashes_and_keeps_comments(manifest_copy: Path) -> None:
    folder = manifest_copy.parent
    m = load_manifest(manifest_copy)
    (folder / m.entry("fastsam_s").file).write_bytes(b"export s")
    (folder / m.entry("sam_vit_l").file).write_bytes(b"sam l")
    results = {r.entry.name: r.status for r in verify_models(m, record=True)}
    assert results["fastsam_s"] == results["sam_vit_l"] == "recorded"
    reloaded = load_manifest(manifest_copy)
    assert reloaded.entry("fastsam_s").sha256 == hashlib.sha256(b"export s").hexdigest()
    assert reloaded.entry("sam_vit_l").sha256 == hashlib.sha256(b"sam l").hexdigest()
    assert reloaded.entry("fastsam_x").sha256 is None and reloaded.entry("sam_vit_b").sha256 is None
    assert manifest_copy.read_text().startswith("# Model files meridian-torch can use")
    # a changed file is a mismatch, and --record does not overwrite the recorded hash
    (folder / m.entry("fastsam_s").file).write_bytes(b"export s, changed")
    assert verify_models(reloaded, ["fastsam_s"], record=True)[0].status == "mismatch"
    assert load_manifest(manifest_copy).entry("fastsam_s").sha256 == hashlib.sha256(b"export s").hexdigest()


def test_invalid_manifest_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "manifest.yaml"
    entry = "{name: x, file: x.pt, sha256: nothex, architecture: a, source: s, license: l}"
    path.write_text(f"version: 1\nmodels:\n  - {entry}\n")
    with pytest.raises(ConfigError, match=r"manifest.yaml: models\.0\.sha256"):
        load_manifest(path)
    path.write_text("version: 1\nmodels:\n  - {name: x, file: x.pt, architecture: a, source: s, license: l, url: u}\n")
    with pytest.raises(ConfigError, match="url"):
        load_manifest(path)


def test_cli_list_and_verify(manifest_copy: Path) -> None:
    result = runner.invoke(app, ["models", "list", "--manifest", str(manifest_copy)])
    assert result.exit_code == 0 and "sam_vit_l" in result.output and "missing" in result.output
    result = runner.invoke(app, ["models", "verify", "--manifest", str(manifest_copy)])
    assert result.exit_code == 0 and "no model files" in result.output
    result = runner.invoke(app, ["models", "verify", "sam_vit_h", "--manifest", str(manifest_copy)])
    assert result.exit_code == 1 and "missing" in result.output
    result = runner.invoke(app, ["models", "verify", "nope", "--manifest", str(manifest_copy)])
    assert result.exit_code == 1 and "no model named 'nope'" in result.output

    file = manifest_copy.parent / load_manifest(manifest_copy).entry("fastsam_x").file
    file.write_bytes(b"v1")
    result = runner.invoke(app, ["models", "verify", "--record", "--manifest", str(manifest_copy)])
    assert result.exit_code == 0 and "recorded" in result.output
    file.write_bytes(b"v2")
    result = runner.invoke(app, ["models", "verify", "--manifest", str(manifest_copy)])
    assert result.exit_code == 1 and "mismatch" in result.output


def test_a_models_folder_without_a_manifest_records_into_its_own_copy(tmp_path: Path, monkeypatch) -> None:
    """As after `pip install .`: the shipped manifest is read, files and records live in the models folder."""
    folder = tmp_path / "my-models"
    monkeypatch.setenv(MODELS_ENV, str(folder))
    shipped = shipped_dir("models") / "manifest.yaml"
    before = shipped.read_text()
    m = load_manifest()
    assert m.path == shipped and m.folder == folder
    folder.mkdir()
    (folder / m.entry("fastsam_s").file).write_bytes(b"export s")
    assert {r.entry.name: r.status for r in verify_models(m, record=True)}["fastsam_s"] == "recorded"
    assert shipped.read_text() == before, "the shipped manifest is never written"
    own = load_manifest()
    assert own.path == folder / "manifest.yaml" and own.folder == folder
    assert own.entry("fastsam_s").sha256 == hashlib.sha256(b"export s").hexdigest()

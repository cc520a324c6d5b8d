"""The local model manifest (`models/manifest.yaml`): which files exist, where users get them, their hashes.

The manifest in use is the one in the user's models folder (`core.paths.models_dir`) when it has
one, else the one shipped with the package; model files are looked up in the models folder.
Nothing is downloaded. `verify_models` hashes the files present and tells apart: ok, missing,
mismatch (the file differs from the recorded sha256) and "no hash recorded" (the manifest has
null, as shipped, since the official files cannot be hashed offline). With `record=True` the
hashes of present files without one are written into the manifest (recorded hashes are never
overwritten: a mismatch stays an error until the user edits the manifest); an installed package's
shipped manifest is first copied into the models folder, which then holds the user's record.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import yaml
from pydantic import Field, ValidationError

from meridian_torch.config.base import StrictModel
from meridian_torch.core.paths import models_dir, shipped_dir
from meridian_torch.errors import ConfigError, ModelWeightsError
from meridian_torch.io.atomic import write_text_atomic

__all__ = [
    "ModelEntry",
    "Manifest",
    "VerifyResult",
    "default_manifest_path",
    "load_manifest",
    "sha256_file",
    "verify_models",
]

Status = Literal["ok", "missing", "mismatch", "no hash recorded", "recorded"]
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


class ModelEntry(StrictModel):
    """One model file: what it is and where users obtain it."""

    name: str = Field(pattern=r"^[a-z0-9_]+$")
    file: str = Field(description="file name inside the models folder")
    sha256: str | None = Field(default=None, pattern=r"^[0-9a-f]{64}$")
    architecture: str
    source: str = Field(description="where to fetch it by hand (never downloaded by the package)")
    license: str


class _ManifestFile(StrictModel):
    version: Literal[1]
    models: list[ModelEntry]


@dataclass(frozen=True)
class Manifest:
    path: Path  # the manifest file
    entries: tuple[ModelEntry, ...]
    folder: Path  # where the model files are

    def entry(self, name: str) -> ModelEntry:
        for e in self.entries:
            if e.name == name:
                return e
        known = ", ".join(e.name for e in self.entries)
        raise ModelWeightsError(f"{self.path}: no model named {name!r}; known: {known}")


@dataclass(frozen=True)
class VerifyResult:
    entry: ModelEntry
    path: Path
    status: Status
    sha256: str | None  # of the file, when it exists

    @property
    def failed(self) -> bool:
        return self.status in ("missing", "mismatch")


def default_manifest_path() -> Path:
    """The models folder's manifest when it has one, else the shipped manifest."""
    own = models_dir() / "manifest.yaml"
    return own if own.is_file() else shipped_dir("models") / "manifest.yaml"


def load_manifest(path: str | os.PathLike[str] | None = None) -> Manifest:
    """Read and validate a manifest: `path` (its files beside it), or the default (files in the
    models folder, see the module docstring)."""
    folder = Path(path).parent if path is not None else models_dir()
    path = Path(path) if path is not None else default_manifest_path()
    if not path.is_file():
        raise ConfigError(f"model manifest not found: {path}")
    try:
        data = _ManifestFile.model_validate(yaml.safe_load(path.read_text()))
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise ConfigError(f"{path}: {problems}") from None
    names = [e.name for e in data.models]
    if duplicates := sorted({n for n in names if names.count(n) > 1}):
        raise ConfigError(f"{path}: duplicate model names {duplicates}")
    return Manifest(path, tuple(data.models), folder)


def sha256_file(path: str | os.PathLike[str], progress: Callable[[int, int], None] | None = None) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks; `progress(bytes_done, bytes_total)`."""
    digest = hashlib.sha256()
    total, done = os.path.getsize(path), 0
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
            done += len(chunk)
            if progress is not None:
                progress(done, total)
    return digest.hexdigest()


def _record(manifest: Manifest, hashes: dict[str, str]) -> None:
    """Replace `sha256: null` of the named entries in the manifest text (keeps its comments); a
    manifest outside the models folder (the shipped one) is copied there first."""
    text = manifest.path.read_text()
    if manifest.path.parent.resolve() != manifest.folder.resolve():
        manifest.folder.mkdir(parents=True, exist_ok=True)
        manifest = Manifest(manifest.folder / "manifest.yaml", manifest.entries, manifest.folder)
        if manifest.path.exists():
            raise ConfigError(f"{manifest.path} exists and is not the manifest in use; pass it with --manifest")
    for name, digest in hashes.items():
        pattern = re.compile(rf"(-\s+name:\s*{re.escape(name)}\s*\n(?:[ \t]+(?!-)[^\n]*\n)*?[ \t]+sha256:\s*)null\b")
        text, count = pattern.subn(rf"\g<1>{digest}", text, count=1)
        if count != 1:
            raise ConfigError(f"{manifest.path}: cannot find 'sha256: null' of {name!r} to record its hash")
    write_text_atomic(manifest.path, text)


def verify_models(
    manifest: Manifest,
    names: Sequence[str] = (),
    record: bool = False,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[VerifyResult]:
    """Hash the manifest's files (or the `names` given) and compare with the recorded sha256.

    `progress(name, bytes_done, bytes_total)` reports hashing. With `record`, files present
    without a recorded hash get theirs written into the manifest (status "recorded").
    """
    entries = [manifest.entry(n) for n in names] if names else list(manifest.entries)
    results, new_hashes = [], {}
    for entry in entries:
        path = manifest.folder / entry.file
        if not path.is_file():
            results.append(VerifyResult(entry, path, "missing", None))
            continue
        report = (lambda done, total, n=entry.name: progress(n, done, total)) if progress else None
        digest = sha256_file(path, report)
        if entry.sha256 is None:
            status: Status = "recorded" if record else "no hash recorded"
            if record:
                new_hashes[entry.name] = digest
        else:
            status = "ok" if digest == entry.sha256 else "mismatch"
        results.append(VerifyResult(entry, path, status, digest))
    if new_hashes:
        _record(manifest, new_hashes)
    return results

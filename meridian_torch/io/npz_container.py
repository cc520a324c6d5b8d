"""The container shared by our binary files (aerial maps, ground submaps): an `.npz` zip of
named arrays plus `header.json` (a uint8 array) carrying `format`, `format_version`,
`package_version` and a `content_hash` (sha256 over the rest of the header and every array).
Written atomically; reading checks the format, its version and the hash."""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from meridian_torch import __version__
from meridian_torch.errors import MeridianError
from meridian_torch.io.atomic import atomic_path

__all__ = ["content_hash", "write_container", "read_container"]


def content_hash(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> str:
    """sha256 over the header (without its own hash) and every array's name, dtype, shape and bytes."""
    h = hashlib.sha256(json.dumps({k: v for k, v in header.items() if k != "content_hash"}, sort_keys=True).encode())
    for name in sorted(arrays):
        a = arrays[name]
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def write_container(path: Path, fmt: str, version: int, header: dict[str, Any], arrays: dict[str, np.ndarray]) -> str:
    """Write `arrays` and `header` (format fields and hash added) to `path` atomically; returns the hash."""
    header = {"format": fmt, "format_version": version, "package_version": __version__, **header}
    header["content_hash"] = content_hash(header, arrays)
    stored = dict(arrays)
    stored["header.json"] = np.frombuffer(json.dumps(header, indent=1).encode(), dtype=np.uint8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **stored)
    return header["content_hash"]


def read_container(
    path: Path, fmt: str, version: int | tuple[int, ...], error: type[MeridianError], what: str, redo: str
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(header, arrays) of a verified file; problems raise `error` naming `path`.

    `version` is the format version this package reads, or a tuple of the versions it reads.

    `what` names the file kind in messages ("aerial map file"), `redo` what the user should do
    about an old or corrupted file ("rebuild the map").
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: {what} not found")
    if not zipfile.is_zipfile(path):  # numpy would guess a pickle and advise loading it unsafely
        raise error(f"{path}: not a meridian-torch {what} (not a zip archive); {redo}")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        detail = "it holds Python objects" if "pickle" in str(exc) else str(exc)
        raise error(f"{path}: not a readable {what} ({detail}); {redo}") from None
    try:
        header = json.loads(arrays.pop("header.json").tobytes().decode())
    except (KeyError, UnicodeDecodeError, json.JSONDecodeError):
        raise error(f"{path}: missing or unreadable header.json") from None
    if header.get("format") != fmt:
        raise error(f"{path}: not a meridian-torch {what} (format {header.get('format')!r})")
    readable = version if isinstance(version, tuple) else (version,)
    if header.get("format_version") not in readable:
        raise error(
            f"{path}: {what} format version {header.get('format_version')} (written by meridian-torch "
            f"{header.get('package_version')}), this version reads {' or '.join(map(str, readable))}; {redo}"
        )
    if content_hash(header, arrays) != header.get("content_hash"):
        raise error(f"{path}: content hash mismatch, the file is corrupted; {redo}")
    return header, arrays

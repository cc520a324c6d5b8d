"""The container shared by our binary files (aerial maps, ground submaps): a zip (numpy `.npz`
layout) of named arrays plus `header.json` (a uint8 array) carrying `format`, `format_version`,
`package_version` and a `content_hash` (sha256 over the rest of the header and every array).

Arrays are written compressed (`np.savez_compressed`, read whole) or stored: uncompressed, each
array's data at a 64-byte aligned file offset, and read as copy-on-write memory maps of the file,
so that opening costs the hash, not a copy (the hash is computed by reading the file in chunks,
which does not keep it in memory). A stored array may be given as a `StreamedArray`, written block
by block, so that writing a file larger than memory holds one block at a time; the hash of a stored
file is computed from the written file, before `header.json` (the last member) is added. Written
atomically; reading checks the format, its version and the hash before any array is returned."""

from __future__ import annotations

import hashlib
import json
import struct
import zipfile
from collections.abc import Callable, Iterable
from io import BytesIO
from pathlib import Path
from typing import IO, Any, NamedTuple

import numpy as np

from meridian_torch import __version__
from meridian_torch.errors import MeridianError
from meridian_torch.io.atomic import atomic_path

__all__ = ["StreamedArray", "content_hash", "write_container", "read_container"]

_ALIGN = 64  # bytes: array data starts at a multiple (numpy pads .npy headers to it as well)
_PAD_EXTRA_ID = 0xD935  # the zip extra field that zipalign pads with
_LOCAL_HEADER = struct.Struct("<4s2B4HL2L2H")  # zip local file header, 30 bytes
_ZIP64_EXTRA = 20  # bytes zipfile adds to a local header for a member over ZIP64_LIMIT
_CHUNK = 1 << 24  # bytes read at once while hashing a stored array


class _Stored(NamedTuple):
    """Where one stored array's data lies in the file."""

    dtype: np.dtype
    shape: tuple[int, ...]
    offset: int


class StreamedArray(NamedTuple):
    """A stored array written block by block: `blocks()` yields C-ordered arrays of `dtype` whose
    concatenation along the first axis is the array of `shape`."""

    dtype: np.dtype
    shape: tuple[int, ...]
    blocks: Callable[[], Iterable[np.ndarray]]


def _hash_start(header: dict[str, Any]) -> Any:
    return hashlib.sha256(json.dumps({k: v for k, v in header.items() if k != "content_hash"}, sort_keys=True).encode())


def _array_tag(name: str, dtype: np.dtype, shape: tuple[int, ...]) -> bytes:
    return f"{name}:{dtype.str}:{shape}".encode()


def content_hash(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> str:
    """sha256 over the header (without its own hash) and every array's name, dtype, shape and bytes."""
    h = _hash_start(header)
    for name in sorted(arrays):
        a = arrays[name]
        h.update(_array_tag(name, a.dtype, a.shape))
        h.update(a.tobytes())
    return h.hexdigest()


def _stored_content_hash(header: dict[str, Any], fh: IO[bytes], stored: dict[str, _Stored]) -> str:
    """`content_hash` of stored arrays, read from the open file `fh` in chunks."""
    h = _hash_start(header)
    for name in sorted(stored):
        dtype, shape, offset = stored[name]
        h.update(_array_tag(name, dtype, shape))
        fh.seek(offset)
        left = int(np.prod(shape)) * dtype.itemsize
        while left:
            chunk = fh.read(min(left, _CHUNK))
            if not chunk:
                raise EOFError(f"array {name} is truncated")
            h.update(chunk)
            left -= len(chunk)
    return h.hexdigest()


def _write_stored(fh: IO[bytes], arrays: dict[str, np.ndarray | StreamedArray], header: dict[str, Any]) -> str:
    """Arrays, then `header.json` with the content hash, as uncompressed `.npy` zip members whose
    data start at multiples of `_ALIGN`; `fh` is open for reading and writing. Returns the hash."""
    with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED) as zf:
        stored = {name: _write_member(zf, fh, name, array) for name, array in arrays.items()}
        end = fh.tell()
        digest = _stored_content_hash(header, fh, stored)
        fh.seek(end)
        header = {**header, "content_hash": digest}
        _write_member(zf, fh, "header.json", np.frombuffer(json.dumps(header, indent=1).encode(), dtype=np.uint8))
    return digest


def _write_member(zf: zipfile.ZipFile, fh: IO[bytes], name: str, array: np.ndarray | StreamedArray) -> _Stored:
    """One array as a stored `.npy` member at the end of `fh`; where its data lies."""
    if isinstance(array, np.ndarray):
        whole = np.ascontiguousarray(array)
        array = StreamedArray(whole.dtype, whole.shape, lambda: (whole,))
    dtype, shape = np.dtype(array.dtype), tuple(array.shape)
    npy_header = _npy_header(dtype, shape)
    info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
    info.file_size = len(npy_header) + int(np.prod(shape)) * dtype.itemsize
    zip64 = info.file_size * 1.05 > zipfile.ZIP64_LIMIT  # zipfile's own rule
    start = fh.tell() + _LOCAL_HEADER.size + len(info.filename.encode()) + 4 + _ZIP64_EXTRA * zip64
    info.extra = struct.pack("<HH", _PAD_EXTRA_ID, -start % _ALIGN) + bytes(-start % _ALIGN)
    rows = 0
    with zf.open(info, "w", force_zip64=zip64) as member:
        member.write(npy_header)
        for block in array.blocks():
            if block.dtype != dtype or tuple(block.shape[1:]) != shape[1:]:
                raise ValueError(f"array {name}: a block of {block.dtype} {block.shape} in an array of {dtype} {shape}")
            member.write(np.ascontiguousarray(block).reshape(-1).view(np.uint8))
            rows += block.shape[0]
    if rows != shape[0]:
        raise ValueError(f"array {name}: its blocks hold {rows} rows, its shape {shape} has {shape[0]}")
    return _Stored(dtype, shape, start + -start % _ALIGN + len(npy_header))


def _npy_header(dtype: np.dtype, shape: tuple[int, ...]) -> bytes:
    """The `.npy` (version 1.0) header of a C-ordered array."""
    buffer = BytesIO()
    header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(buffer, header)
    return buffer.getvalue()


def write_container(
    path: Path, fmt: str, version: int, header: dict[str, Any], arrays: dict[str, np.ndarray | StreamedArray], *,
    compressed: bool = True,
) -> str:
    """Write `arrays` and `header` (format fields and hash added) to `path` atomically; returns the hash.

    `compressed=False` stores the arrays uncompressed and aligned, for `read_container` to map;
    only stored arrays may be `StreamedArray`s.
    """
    header = {"format": fmt, "format_version": version, "package_version": __version__, **header}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not compressed:
        with atomic_path(path) as tmp, open(tmp, "w+b") as fh:
            return _write_stored(fh, arrays, header)
    streamed = [name for name, array in arrays.items() if isinstance(array, StreamedArray)]
    if streamed:
        raise ValueError(f"arrays {streamed} are streamed: a compressed container needs them in memory")
    header["content_hash"] = content_hash(header, arrays)
    stored = {**arrays, "header.json": np.frombuffer(json.dumps(header, indent=1).encode(), dtype=np.uint8)}
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **stored)
    return header["content_hash"]


def _stored_arrays(fh: IO[bytes], members: list[zipfile.ZipInfo]) -> dict[str, _Stored]:
    """Where each uncompressed `.npy` member's array lies (from the local headers and .npy headers)."""
    stored = {}
    for info in members:
        fh.seek(info.header_offset)
        fields = _LOCAL_HEADER.unpack(fh.read(_LOCAL_HEADER.size))
        if fields[0] != b"PK\x03\x04":
            raise zipfile.BadZipFile(f"bad local header of {info.filename}")
        start = info.header_offset + _LOCAL_HEADER.size + fields[-2] + fields[-1]
        fh.seek(start)
        major, _ = np.lib.format.read_magic(fh)
        read_header = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
        shape, fortran_order, dtype = read_header(fh)
        if fortran_order or dtype.hasobject:
            raise ValueError(f"{info.filename} is not a C-ordered array of numbers")
        offset = fh.tell()
        if offset + int(np.prod(shape)) * dtype.itemsize > start + info.file_size:
            raise EOFError(f"{info.filename} is truncated")
        stored[info.filename.removesuffix(".npy")] = _Stored(dtype, shape, offset)
    return stored


def _mapped(path: Path, stored: _Stored) -> np.ndarray:
    """A copy-on-write memory map of one stored array (writes stay in this process, the file is
    never changed; writable, so torch.from_numpy takes it as it is)."""
    if int(np.prod(stored.shape)) == 0:  # mmap cannot map zero bytes
        return np.empty(stored.shape, stored.dtype)
    return np.memmap(path, stored.dtype, "c", stored.offset, stored.shape).view(np.ndarray)


def _read_arrays(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any], str]:
    """(arrays without the header, the header, the content hash of what was read)."""
    with zipfile.ZipFile(path) as zf:
        members = zf.infolist()
        if any(info.compress_type != zipfile.ZIP_STORED for info in members):
            with np.load(path, allow_pickle=False) as npz:
                arrays = {name: npz[name] for name in npz.files}
            header = _header(arrays.pop("header.json", None))
            return arrays, header, content_hash(header, arrays)
    with open(path, "rb") as fh:
        stored = _stored_arrays(fh, members)
        if "header.json" not in stored:
            return {}, _header(None), ""
        header_part = stored.pop("header.json")
        fh.seek(header_part.offset)
        header = _header(np.frombuffer(fh.read(int(np.prod(header_part.shape))), np.uint8))
        digest = _stored_content_hash(header, fh, stored)
    return {name: _mapped(path, part) for name, part in stored.items()}, header, digest


def _header(array: np.ndarray | None) -> dict[str, Any]:
    """header.json's dict, {} when it is missing or unreadable."""
    try:
        header = json.loads(array.tobytes().decode())
    except (AttributeError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return header if isinstance(header, dict) else {}


def read_container(
    path: Path, fmt: str, version: int | tuple[int, ...], error: type[MeridianError], what: str, redo: str
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(header, arrays) of a verified file; problems raise `error` naming `path`.

    `version` is the format version this package reads, or a tuple of the versions it reads.
    Stored (uncompressed) files give memory-mapped arrays, compressed ones arrays in memory.

    `what` names the file kind in messages ("aerial map file"), `redo` what the user should do
    about an old or corrupted file ("rebuild the map").
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: {what} not found")
    if not zipfile.is_zipfile(path):  # numpy would guess a pickle and advise loading it unsafely
        raise error(f"{path}: not a meridian-torch {what} (not a zip archive); {redo}")
    try:
        arrays, header, digest = _read_arrays(path)
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        detail = "it holds Python objects" if "pickle" in str(exc) else str(exc)
        raise error(f"{path}: not a readable {what} ({detail}); {redo}") from None
    if not header:
        raise error(f"{path}: missing or unreadable header.json")
    if header.get("format") != fmt:
        raise error(f"{path}: not a meridian-torch {what} (format {header.get('format')!r})")
    readable = version if isinstance(version, tuple) else (version,)
    if header.get("format_version") not in readable:
        raise error(
            f"{path}: {what} format version {header.get('format_version')} (written by meridian-torch "
            f"{header.get('package_version')}), this version reads {' or '.join(map(str, readable))}; {redo}"
        )
    if digest != header.get("content_hash"):
        raise error(f"{path}: content hash mismatch, the file is corrupted; {redo}")
    return header, arrays

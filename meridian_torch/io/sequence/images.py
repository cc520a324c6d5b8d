"""Frame images: colour (8-bit PNG or JPEG) and depth (16-bit PNG) checked against the format and
camera.json, and loaded as arrays."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from meridian_torch.errors import SequenceFormatError
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.sequence.problems import raise_first

__all__ = ["check_depth", "check_rgb", "decode_image", "load_frame_images", "open_image"]

_RGB_MODES = ("RGB", "RGBA")  # alpha, if any, is dropped
_DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I")  # how Pillow opens 16-bit greyscale PNGs


def open_image(path: Path, line: int, problems: list[str]) -> Image.Image | None:
    """Open (header only) an image listed on `line` of frames.csv."""
    try:
        return Image.open(path)
    except FileNotFoundError:
        problems.append(f"{path}: file not found (listed in frames.csv line {line})")
    except (UnidentifiedImageError, OSError) as e:
        problems.append(f"{path}: not a readable image ({e})")
    return None


def decode_image(img: Image.Image, path: Path, problems: list[str]) -> None:
    """Decode the whole image: truncated or corrupt data shows only here, not in the header."""
    try:
        img.load()
    except (OSError, SyntaxError, ValueError) as e:
        problems.append(f"{path}: image data cannot be decoded ({e})")


def _check_size(img: Image.Image, path: Path, camera: CameraModel | None, problems: list[str]) -> None:
    if camera is not None and img.size != (camera.width, camera.height):
        problems.append(
            f"{path}: image is {img.size[0]}x{img.size[1]} but camera.json says "
            f"{camera.width}x{camera.height}"
        )


def check_rgb(img: Image.Image, path: Path, camera: CameraModel | None, problems: list[str]) -> None:
    if img.format not in ("PNG", "JPEG"):
        problems.append(f"{path}: {img.format} image; RGB frames must be PNG or JPEG")
    elif img.mode not in _RGB_MODES:
        problems.append(f"{path}: image mode {img.mode}; RGB frames must be 8-bit RGB")
    _check_size(img, path, camera, problems)


def check_depth(img: Image.Image, path: Path, camera: CameraModel | None, problems: list[str]) -> None:
    if img.format != "PNG":
        problems.append(f"{path}: {img.format} image; depth must be a 16-bit PNG")
    elif img.mode in ("L", "P", "1"):
        problems.append(
            f"{path}: 8-bit depth image; depth must be a 16-bit greyscale PNG (value = metres * depth_scale)"
        )
    elif img.mode not in _DEPTH_MODES:
        problems.append(f"{path}: image mode {img.mode}; depth must be a 16-bit greyscale PNG")
    _check_size(img, path, camera, problems)


def load_frame_images(
    rgb_path: Path, depth_path: Path, line: int, camera: CameraModel
) -> tuple[np.ndarray, np.ndarray]:
    problems: list[str] = []
    rgb_img = open_image(rgb_path, line, problems)
    raise_first(problems)
    assert rgb_img is not None
    with rgb_img:
        check_rgb(rgb_img, rgb_path, camera, problems)
        raise_first(problems)
        try:
            rgb = np.array(rgb_img.convert("RGB"))  # a writable copy
        except OSError as e:
            raise SequenceFormatError(f"{rgb_path}: cannot decode image ({e})") from e
    depth_img = open_image(depth_path, line, problems)
    raise_first(problems)
    assert depth_img is not None
    with depth_img:
        check_depth(depth_img, depth_path, camera, problems)
        raise_first(problems)
        try:
            raw = np.asarray(depth_img)
        except OSError as e:
            raise SequenceFormatError(f"{depth_path}: cannot decode image ({e})") from e
    depth = (raw.astype(np.float64) / camera.depth_scale).astype(np.float32)
    return rgb, depth

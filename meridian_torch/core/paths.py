"""Where the package finds the files it ships (configs, the model manifest) and the user's model files.

In a source checkout (an editable install) the shipped files are the repository's top-level
`configs/` and `models/`. A wheel carries copies in `meridian_torch/_bundled/` (setup.py copies
them at build time), so an installed package finds them from any working folder.

Model files (checkpoints, ONNX graphs) are the user's: they live in `$MERIDIAN_TORCH_MODELS` when
set, else in the checkout's `models/`, else in `$XDG_DATA_HOME/meridian-torch/models`
(~/.local/share/meridian-torch/models).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

__all__ = ["shipped_dir", "models_dir", "MODELS_ENV"]

MODELS_ENV = "MERIDIAN_TORCH_MODELS"
_PACKAGE = Path(__file__).resolve().parents[1]


def shipped_dir(name: Literal["configs", "models"]) -> Path:
    """The folder of shipped files `name`: the wheel's bundled copy, else the checkout's."""
    bundled = _PACKAGE / "_bundled" / name
    return bundled if bundled.is_dir() else _PACKAGE.parent / name


def models_dir() -> Path:
    """The folder holding the user's model files (see the module docstring)."""
    if os.environ.get(MODELS_ENV):
        return Path(os.environ[MODELS_ENV]).expanduser()
    if not (_PACKAGE / "_bundled").is_dir():  # a source checkout
        return _PACKAGE.parent / "models"
    data_home = Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")
    return data_home / "meridian-torch" / "models"

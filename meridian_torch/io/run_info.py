"""Provenance of a run: every output folder gets the resolved config and the package version."""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path

from meridian_torch import __version__
from meridian_torch.config import MeridianConfig, dump_config
from meridian_torch.io.atomic import write_text_atomic

__all__ = ["write_run_info", "CONFIG_FILE", "RUN_FILE"]

CONFIG_FILE = "config.yaml"
RUN_FILE = "run.json"


def write_run_info(out_dir: Path, config: MeridianConfig, command: str) -> None:
    """Write `config.yaml` (resolved config) and `run.json` (version, command, time) into out_dir."""
    import torch

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out_dir / CONFIG_FILE, dump_config(config))
    info = {
        "meridian_torch_version": __version__,
        "command": command,
        "argv": sys.argv,
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "python": platform.python_version(),
        "torch": torch.__version__,
    }
    write_text_atomic(out_dir / RUN_FILE, json.dumps(info, indent=2) + "\n")

from __future__ import annotations

import subprocess
import sys

HEAVY = ("gtsam", "onnx", "onnxruntime", "matplotlib", "rasterio", "typer")


def test_import_is_cheap_and_side_effect_free() -> None:
    code = (
        "import sys, meridian_torch, meridian_torch.config, meridian_torch.errors; "
        f"print([m for m in {HEAVY!r} if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    assert out.stderr == ""

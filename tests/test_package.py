from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

HEAVY = ("gtsam", "onnx", "onnxruntime", "matplotlib", "rasterio", "typer")


def test_import_is_cheap_and_side_effect_free() -> None:
    code = (
        "import sys, meridian_torch, meridian_torch.config, meridian_torch.errors; "
        f"print([m for m in {HEAVY!r} if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    assert out.stderr == ""


@pytest.mark.slow
def test_a_built_wheel_runs_from_any_folder(tmp_path: Path) -> None:
    """`pip install .` (not editable): configs and the model manifest ship inside the package, so
    `config show`, `models list` and `demo` work from a folder far from any checkout."""
    wheels, venv, elsewhere = tmp_path / "wheels", tmp_path / "venv", tmp_path / "elsewhere"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(wheels), str(REPO)], check=True,
                   capture_output=True)
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    # the dependencies come from this interpreter's site-packages (a .pth path, so its editable
    # install of meridian_torch is not picked up); the package itself only from the wheel
    site = venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([*pip, "--python", str(venv / "bin" / "python"), "install", "--no-deps",
                    str(next(wheels.glob("meridian_torch-*.whl")))], check=True, capture_output=True)
    elsewhere.mkdir()

    def run(*args: str) -> str:
        out = subprocess.run([str(venv / "bin" / "meridian-torch"), *args], cwd=elsewhere, capture_output=True,
                             text=True, env={**os.environ, "MERIDIAN_TORCH_MODELS": str(tmp_path / "models")})
        assert out.returncode == 0, out.stdout + out.stderr
        return out.stdout

    located = subprocess.run([str(venv / "bin" / "python"), "-c", "import meridian_torch; print(meridian_torch.__file__)"],
                             capture_output=True, text=True, check=True, cwd=elsewhere).stdout
    assert str(site) in located, "the wheel's package is the one imported"
    assert "patch_size_m: 60.0" in run("config", "show")
    assert "sam_vit_l" in run("models", "list")
    tiny = site / "meridian_torch" / "_bundled" / "configs" / "tiny.yaml"
    out = run("demo", "--out", "demo", "--cache-dir", "cache", "-c", str(tiny))
    assert "demo finished" in out and (elsewhere / "demo" / "report.md").is_file()

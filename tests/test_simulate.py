"""The simulator end to end on the tiny world: CLI, determinism, and conformance to the sequence
folder format checked by an independent reader written here from the format text (not our io
module)."""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from meridian_torch.cli import app
from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.io.poses import read_tum
from meridian_torch.io.sequence import check_sequence
from meridian_torch.sim.simulate import simulate_sequence

TINY = CONFIG_DIR / "tiny.yaml"


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "seq"
    result = CliRunner().invoke(app, ["simulate", "--out", str(out), "-c", str(TINY)])
    assert result.exit_code == 0, result.output
    return out


def _read_tum(path: Path) -> np.ndarray:
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    assert all(len(r) == 8 for r in rows), f"{path}: TUM lines have 8 fields"
    return np.array(rows, dtype=np.float64)


def test_sequence_conforms_to_format(tiny_sequence: Path) -> None:
    seq = tiny_sequence
    ortho = json.loads((seq / "aerial" / "ortho.json").read_text())
    assert ortho["meters_per_pixel"] > 0 and len(ortho["origin"]) == 2
    with Image.open(seq / "aerial" / "ortho.png") as im:
        assert im.mode == "RGB"

    cam = json.loads((seq / "ground" / "camera.json").read_text())
    for key in ("width", "height", "fx", "fy", "cx", "cy", "depth_scale", "T_base_camera"):
        assert key in cam
    T_base_camera = np.array(cam["T_base_camera"])
    assert T_base_camera.shape == (4, 4)
    assert np.allclose(T_base_camera[:3, :3] @ T_base_camera[:3, :3].T, np.eye(3), atol=1e-6)

    with open(seq / "ground" / "frames.csv", newline="") as fh:
        reader = csv.reader(fh)
        assert next(reader) == ["timestamp", "rgb", "depth"]
        rows = list(reader)
    stamps = np.array([float(r[0]) for r in rows])
    assert len(rows) > 5 and np.all(np.diff(stamps) > 0)
    for _, rgb, depth in rows[:: max(1, len(rows) // 5)]:
        with Image.open(seq / "ground" / rgb) as im:
            assert im.size == (cam["width"], cam["height"]) and im.mode == "RGB"
        with Image.open(seq / "ground" / depth) as im:
            assert im.size == (cam["width"], cam["height"]) and im.mode.startswith("I;16")
            d = np.asarray(im).astype(np.float64) / cam["depth_scale"]
        assert (d > 0).mean() > 0.3, "most pixels see ground or objects within range"

    for name in ("ground/odometry.tum", "groundtruth.tum"):
        tum = _read_tum(seq / name)
        assert np.all(np.diff(tum[:, 0]) > 0)
        assert np.allclose(np.linalg.norm(tum[:, 4:8], axis=1), 1.0, atol=1e-6)
        if name.startswith("ground"):
            assert tum[0, 0] <= stamps[0] and tum[-1, 0] >= stamps[-1], "odometry covers the frames"

    assert check_sequence(seq) == []
    for extra in ("preview.png", "config.yaml", "run.json", "sim/objects.json", "sim/borders.json"):
        assert (seq / extra).is_file(), extra


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file() and p.name not in ("run.json", "preview.png")):
        h.update(path.relative_to(folder).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def test_same_seed_gives_identical_files(tmp_path: Path) -> None:
    cfg = load_config(TINY, ["sim.trajectory.max_frames=6"]).sim
    simulate_sequence(cfg, tmp_path / "a")
    simulate_sequence(cfg, tmp_path / "b")
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b")
    other = load_config(TINY, ["sim.trajectory.max_frames=6", "sim.seed=2"]).sim
    simulate_sequence(other, tmp_path / "c")
    assert _digest(tmp_path / "a") != _digest(tmp_path / "c")


def test_existing_output_is_refused_before_rendering(tiny_sequence: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def must_not_build(*_args: object) -> None:
        raise AssertionError("the world was built before the existing output was refused")

    monkeypatch.setattr("meridian_torch.sim.simulate.build_world", must_not_build)
    before = _digest(tiny_sequence)
    result = CliRunner().invoke(app, ["simulate", "--out", str(tiny_sequence), "-c", str(TINY)])
    assert result.exit_code == 1, result.output
    assert "already exists" in result.output
    assert str(tiny_sequence) in result.output
    assert _digest(tiny_sequence) == before


def test_check_cli_on_simulated_sequence(tiny_sequence: Path) -> None:
    result = CliRunner().invoke(app, ["check", str(tiny_sequence)])
    assert result.exit_code == 0, result.output
    assert "OK" in result.output


@pytest.mark.slow
def test_demo_runs_end_to_end_with_the_same_trajectory_on_1_and_2_threads(tmp_path: Path) -> None:
    """The demo as a user runs it; a seeded run gives the same trajectories whatever the thread
    count (sums may be reassociated across threads, so to 1 mm rather than bitwise)."""
    cache = tmp_path / "cache"
    runs = {}
    for threads in (2, 1):
        out = tmp_path / f"out-{threads}"
        result = CliRunner().invoke(app, ["demo", "--out", str(out), "--cache-dir", str(cache),
                                          "--set", f"runtime.num_threads={threads}"])
        assert result.exit_code == 0, result.output
        runs[threads] = out
    out = runs[2]
    for name in ("preview.png", "config.yaml", "aerial_map.png", "report.md", "metrics.json", "submaps.csv"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_submaps"] >= 10 and metrics["n_frames"] > 300
    assert "ATE final" in result.output and "demo finished" in result.output
    for name in ("trajectory.tum", "trajectory_incremental.tum"):
        two, one = read_tum(runs[2] / name), read_tum(runs[1] / name)
        assert np.array_equal(two.timestamps, one.timestamps), name
        assert np.abs(two.poses[:, :3, 3] - one.poses[:, :3, 3]).max() < 1e-3, name

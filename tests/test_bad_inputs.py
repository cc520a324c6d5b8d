"""The bad-input battery (issue 22): each broken input gives one line naming the problem, exit 1,
before any frame is processed, and leaves the output folder as it was."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from meridian_torch.cli import app
from meridian_torch.config import CONFIG_DIR

CONFIG = str(CONFIG_DIR / "tiny.yaml")


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A tiny rendered sequence and its aerial map."""
    root = tmp_path_factory.mktemp("bad-inputs")
    runner = CliRunner()
    result = runner.invoke(app, ["simulate", "-o", str(root / "seq"), "-c", CONFIG])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["build-map", str(root / "seq"), "--out", str(root / "map.mtm"), "-c", CONFIG])
    assert result.exit_code == 0, result.output
    return root / "seq", root / "map.mtm"


def _edit_json(path: Path, edit: Callable[[dict], None]) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def shifted_orthophoto(seq: Path, mtm: Path, tmp: Path) -> list[str]:
    """The orthophoto moved 500 m east after the map was built: the map no longer belongs to it."""
    _edit_json(seq / "aerial" / "ortho.json", lambda d: d.update(origin=[d["origin"][0] + 500.0, d["origin"][1]]))
    return ["--map", str(mtm)]


def missing_pixel_size(seq: Path, mtm: Path, tmp: Path) -> list[str]:
    _edit_json(seq / "aerial" / "ortho.json", lambda d: d.pop("meters_per_pixel"))
    return ["--map", str(mtm)]


def geographic_crs(seq: Path, mtm: Path, tmp: Path) -> list[str]:
    _edit_json(seq / "aerial" / "ortho.json", lambda d: d.update(crs="EPSG:4326"))
    return ["--map", str(mtm)]


def odometry_gap(seq: Path, mtm: Path, tmp: Path) -> list[str]:
    tum = seq / "ground" / "odometry.tum"
    rows = [r for r in tum.read_text().splitlines() if r and not r.startswith("#")]
    t = np.array([float(r.split()[0]) for r in rows])
    middle = (t > t[0] + 0.4 * (t[-1] - t[0])) & (t < t[0] + 0.6 * (t[-1] - t[0]))
    tum.write_text("\n".join(r for r, drop in zip(rows, middle) if not drop) + "\n")
    return ["--map", str(mtm)]


def infinite_config_value(seq: Path, mtm: Path, tmp: Path) -> list[str]:
    return ["--map", str(mtm), "--set", "backend.sigma_t_m=inf"]


def random_bytes_map(seq: Path, mtm: Path, tmp: Path) -> list[str]:
    bad = tmp / "random.mtm"
    bad.write_bytes(np.random.default_rng(0).bytes(4096))
    return ["--map", str(bad)]


def map_of_another_config(seq: Path, mtm: Path, tmp: Path) -> list[str]:
    return ["--map", str(mtm), "--set", "aerial_map.patch_size_m=41.0"]


def truncated_frame(seq: Path, mtm: Path, tmp: Path) -> list[str]:
    png = sorted((seq / "ground" / "rgb").iterdir())[3]
    png.write_bytes(png.read_bytes()[:200])
    return ["--map", str(mtm)]


CASES = {
    shifted_orthophoto: "built from another orthophoto",
    missing_pixel_size: "meters_per_pixel",
    geographic_crs: "EPSG:4326",
    odometry_gap: "no pose between",
    infinite_config_value: "backend.sigma_t_m",
    random_bytes_map: "random.mtm",
    map_of_another_config: "built with another config",
    truncated_frame: "000003.png",
}


@pytest.mark.parametrize("case", list(CASES), ids=[c.__name__ for c in CASES])
def test_a_broken_input_is_refused_before_the_run_and_the_output_is_untouched(
    world: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, case: Callable[..., list[str]]
) -> None:
    from meridian_torch import pipeline

    seq = tmp_path / "seq"
    shutil.copytree(world[0], seq)
    args = case(seq, world[1], tmp_path)
    out = tmp_path / "run"
    out.mkdir()
    (out / "trajectory.tum").write_text("# an earlier run\n")
    # a refusal must come before the first frame: the run itself may not start
    monkeypatch.setattr(pipeline.LiveLocalizer, "add_frames", lambda *a, **k: pytest.fail("frames were processed"))
    check_first = case is truncated_frame  # only decoding finds it: `check` does, up front
    command = ["check", str(seq)] if check_first else ["localize", str(seq), "-o", str(out), "--overwrite", "-c", CONFIG,
                                                        *args]
    result = CliRunner().invoke(app, command)
    assert result.exit_code == 1, result.output
    assert CASES[case] in result.output
    assert "Traceback" not in result.output and "pickle" not in result.output
    assert [p.name for p in out.iterdir()] == ["trajectory.tum"]
    assert (out / "trajectory.tum").read_text() == "# an earlier run\n"


def test_an_output_path_in_the_way_is_one_line(world: tuple[Path, Path], tmp_path: Path) -> None:
    """A file where the output folder's parent should be: the OS error is one line, exit 1."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    result = CliRunner().invoke(app, ["localize", str(world[0]), "--map", str(world[1]), "-o", str(blocker / "run"),
                                      "-c", CONFIG])
    assert result.exit_code == 1, result.output
    assert str(blocker) in result.output and "Traceback" not in result.output
    assert blocker.read_text() == "not a folder"


@pytest.mark.parametrize("command", ["map-ground", "demo", "localize"])
def test_a_folder_of_someone_elses_files_is_refused_without_overwrite(world: tuple[Path, Path], tmp_path: Path,
                                                                        command: str) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    args = {"map-ground": ["map-ground", str(world[0])], "demo": ["demo", "--cache-dir", str(tmp_path / "cache")],
            "localize": ["localize", str(world[0]), "--map", str(world[1])]}[command]
    result = CliRunner().invoke(app, [*args, "-o", str(out), "-c", CONFIG])
    assert result.exit_code == 1 and "already exists and holds files; pass --overwrite" in result.output
    assert [p.name for p in out.iterdir()] == ["notes.txt"] and (out / "notes.txt").read_text() == "mine"
    assert not (tmp_path / "cache").exists(), "refused before any work"


def test_the_demo_replaces_its_own_earlier_output(tmp_path: Path) -> None:
    from meridian_torch.errors import OutputExistsError
    from meridian_torch.pipeline.prepare import refuse_foreign_folder

    out = tmp_path / "demo"
    out.mkdir()
    (out / "run.json").write_text(json.dumps({"command": "demo"}))
    refuse_foreign_folder(out, overwrite=False, command="demo")  # an earlier demo: fine
    with pytest.raises(OutputExistsError):
        refuse_foreign_folder(out, overwrite=False, command="localize")
    (out / "run.json").write_text(json.dumps({"command": "localize"}))
    with pytest.raises(OutputExistsError):
        refuse_foreign_folder(out, overwrite=False, command="demo")


def test_map_ground_writes_its_folder_whole(world: tuple[Path, Path], tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """Interrupted during mapping: no output folder, no temporary folder; completed: submaps and run info."""
    from meridian_torch.mapping.ground_map import GroundMapper

    out = tmp_path / "ground"
    real = GroundMapper.map_sequence

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(GroundMapper, "map_sequence", interrupt)
    result = CliRunner().invoke(app, ["map-ground", str(world[0]), "-o", str(out), "-c", CONFIG, "--no-plots"])
    assert result.exit_code == 130 and "interrupted" in result.output
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(GroundMapper, "map_sequence", real)
    result = CliRunner().invoke(app, ["map-ground", str(world[0]), "-o", str(out), "-c", CONFIG, "--no-plots"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == ["config.yaml", "run.json", "submaps.mts"]


def test_sigterm_during_localize_leaves_the_folder_as_it_was(world: tuple[Path, Path], tmp_path: Path) -> None:
    """A scheduler's SIGTERM unwinds like Ctrl-C: exit 130, OUT untouched, no temporary folder left."""
    import os
    import signal
    import subprocess
    import sys

    out = tmp_path / "run"
    out.mkdir()
    (out / "trajectory.tum").write_text("# an earlier run\n")
    command = [sys.executable, "-c", "from meridian_torch.cli import app; app()", "localize", str(world[0]),
               "--map", str(world[1]), "-o", str(out), "--overwrite", "-c", CONFIG]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    seen = []
    for line in proc.stdout:  # wait until the run is under way (the map is loaded)
        seen.append(line)
        if "using the aerial map" in line:
            break
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=120)
    output = "".join(seen) + rest
    assert proc.returncode == 130, output
    assert "interrupted: nothing was written" in output and "Traceback" not in output
    assert [p.name for p in out.iterdir()] == ["trajectory.tum"]
    assert (out / "trajectory.tum").read_text() == "# an earlier run\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"], "no temporary folder left"

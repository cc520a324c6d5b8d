from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from meridian_torch.cli import app
from meridian_torch.config import CONFIG_DIR, load_config

runner = CliRunner()


def test_help_lists_commands() -> None:
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ("demo", "simulate", "check", "config"):
        assert command in result.output


def test_config_show_resolves_overrides() -> None:
    result = runner.invoke(app, ["config", "show", "-c", str(CONFIG_DIR / "tiny.yaml"), "--set", "matching.associations.k_prim=7"])
    assert result.exit_code == 0, result.output
    shown = yaml.safe_load(result.output)
    assert shown["matching"]["associations"]["k_prim"] == 7
    assert shown["sim"]["name"] == load_config(CONFIG_DIR / "tiny.yaml").sim.name


def test_config_error_is_one_line_and_exit_1() -> None:
    result = runner.invoke(app, ["config", "show", "--set", "sim.wrld.size_m=3"])
    assert result.exit_code == 1
    assert "unknown key 'sim.wrld'" in result.output
    assert "Traceback" not in result.output


def test_check_reports_missing_folder(tmp_path: Path) -> None:
    result = runner.invoke(app, ["check", str(tmp_path / "nope")])
    assert result.exit_code == 1
    assert "nope" in result.output


def test_localize_refuses_a_folder_with_files_and_leaves_it_untouched(tmp_path: Path) -> None:
    out = tmp_path / "results"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    result = CliRunner().invoke(app, ["localize", str(tmp_path / "no-sequence"), "--map", str(tmp_path / "m.mtm"),
                                      "--out", str(out)])
    assert result.exit_code == 1
    assert f"{out}: already exists and holds files; pass --overwrite" in result.output
    assert [p.name for p in out.iterdir()] == ["notes.txt"] and (out / "notes.txt").read_text() == "mine"


def _interrupt() -> None:
    raise KeyboardInterrupt


def _interrupt_inside_an_extension() -> None:
    """What CPython makes of a SIGTERM/Ctrl-C that lands while numba's dispatcher runs Python code."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as exc:
        raise SystemError("CPUDispatcher(<function f>) returned a result with an exception set") from exc


@pytest.mark.parametrize("interrupt", [_interrupt, _interrupt_inside_an_extension])
def test_a_failed_or_interrupted_localize_leaves_the_folder_as_it_was(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                       interrupt) -> None:
    from meridian_torch.cli import runs
    from meridian_torch.pipeline import prepare

    out = tmp_path / "results"
    out.mkdir()
    (out / "trajectory.tum").write_text("# an earlier run\n")
    args = ["localize", str(tmp_path / "seq"), "--map", str(tmp_path / "m.mtm"), "--out", str(out), "--overwrite"]
    failed = CliRunner().invoke(app, args)  # the sequence does not exist: fails after the folder check
    assert failed.exit_code == 1 and "seq" in failed.output
    assert sorted(p.name for p in out.iterdir()) == ["trajectory.tum"], "a failed run touched the folder"

    monkeypatch.setattr(prepare, "open_sequence", lambda cfg, sequence: (None, None))  # a sequence that checks out
    monkeypatch.setattr(runs, "_load_or_build_map", lambda *args, **kwargs: interrupt())
    interrupted = CliRunner().invoke(app, args)
    assert interrupted.exit_code == 130 and "interrupted: nothing was written" in interrupted.output
    assert "Traceback" not in interrupted.output and "SystemError" not in interrupted.output
    assert sorted(p.name for p in out.iterdir()) == ["trajectory.tum"]
    assert (out / "trajectory.tum").read_text() == "# an earlier run\n"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".results")], "no temporary folder left"


def test_a_bug_is_not_mistaken_for_an_interrupt(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An extension's SystemError that no interrupt caused is a bug: it keeps its traceback."""
    from meridian_torch.cli import runs
    from meridian_torch.pipeline import prepare

    def bug(*args, **kwargs):
        try:
            raise ValueError("inside the extension")
        except ValueError as exc:
            raise SystemError("returned a result with an exception set") from exc

    monkeypatch.setattr(prepare, "open_sequence", lambda cfg, sequence: (None, None))
    monkeypatch.setattr(runs, "_load_or_build_map", bug)
    result = CliRunner().invoke(app, ["localize", str(tmp_path / "seq"), "--map", str(tmp_path / "m.mtm"),
                                      "--out", str(tmp_path / "out")])
    assert result.exit_code == 1 and isinstance(result.exception, SystemError), result.output
    assert "interrupted" not in result.output


def test_an_explicit_exit_while_handling_an_interrupt_keeps_its_code() -> None:
    import typer

    from meridian_torch.cli.common import error_boundary

    @error_boundary
    def command() -> None:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise typer.Exit(1)  # noqa: B904 (the command's own decision, with the interrupt as context)

    with pytest.raises(typer.Exit) as stopped:
        command()
    assert stopped.value.exit_code == 1

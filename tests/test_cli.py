from __future__ import annotations

from pathlib import Path

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

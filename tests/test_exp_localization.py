"""The table of scripts/exp_localization.py: every issue-19 column from a run's metrics, '-' where absent."""

from __future__ import annotations

import sys

from conftest import REPO

sys.path.insert(0, str(REPO / "scripts"))
import exp_localization as exp  # noqa: E402


def _row(metrics: dict) -> dict:
    return {
        "sequence": "kitti09",
        "variant": "default",
        "frames": 477,
        "submaps": 30,
        "metrics": metrics,
        "real_time_factor": 0.41,
    }


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip("|").split("|")]


def test_table_gives_every_column_per_world() -> None:
    metrics = {
        "final": {"ate_rmse_m": 0.84, "ate_max_m": 2.0},
        "incremental": {"ate_rmse_m": 2.21, "ate_max_m": 6.73},
        "fraction_localized": 0.803,
        "distance_to_first_fix_m": 338.4,
        "final_covariance_consistency": {
            "n": 477,
            "position_nees_mean": 5.126,
            "position_within_2sigma": 0.612,
        },
        "incremental_covariance_consistency": {
            "n": 380,
            "position_nees_mean": 2.304,
            "position_within_2sigma": 0.847,
        },
    }
    header, rule, line = exp.table([_row(metrics)]).splitlines()
    cells = dict(zip(_cells(header), _cells(line)))
    assert len(_cells(header)) == len(_cells(line)) == rule.count("---")
    assert cells["ATE final (m)"] == "0.8" and cells["ATE incremental (m)"] == "2.2"
    assert cells["worst incremental (m)"] == "6.7" and cells["localized online"] == "80 %"
    assert cells["first fix (m)"] == "338.4" and cells["position NEES final / online (2)"] == "5.13 / 2.30"
    assert cells["inside 2 sigma final / online (86 %)"] == "61 % / 85 %"
    assert cells["paper inc. / final (m)"] == "2.4 / 2.1"
    assert cells["RTF"] == "0.41"


def test_table_without_the_online_covariance() -> None:
    """A run folder without covariance_incremental.csv (written before it existed) keeps the final
    columns and shows '-' for the online ones."""
    metrics = {
        "final": {"ate_rmse_m": 0.84, "ate_max_m": 2.0},
        "incremental": {"ate_rmse_m": 2.21, "ate_max_m": 6.73},
        "fraction_localized": 0.803,
        "distance_to_first_fix_m": 338.4,
        "final_covariance_consistency": {"n": 477, "position_nees_mean": 1.9, "position_within_2sigma": 0.9},
    }
    header, _, line = exp.table([_row(metrics)]).splitlines()
    cells = dict(zip(_cells(header), _cells(line)))
    assert cells["position NEES final / online (2)"] == "1.90 / -"
    assert cells["inside 2 sigma final / online (86 %)"] == "90 % / -"


def test_table_of_a_run_that_never_localized() -> None:
    metrics = {
        "final": None,
        "incremental": None,
        "fraction_localized": 0.0,
        "distance_to_first_fix_m": None,
        "final_covariance_consistency": None,
        "incremental_covariance_consistency": None,
    }
    header, _, line = exp.table([_row(metrics)]).splitlines()
    cells = dict(zip(_cells(header), _cells(line)))
    for column in (
        "ATE final (m)",
        "ATE incremental (m)",
        "worst incremental (m)",
        "first fix (m)",
    ):
        assert cells[column] == "-"
    for column in ("position NEES final / online (2)", "inside 2 sigma final / online (86 %)"):
        assert cells[column] == "- / -"
    assert cells["localized online"] == "0 %"

"""Evaluation logic of scripts/exp_registration.py (truth, success at top-L, patch choice)."""

from __future__ import annotations

import math
import sys

import numpy as np
from conftest import REPO
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(REPO / "scripts"))
import exp_registration as exp  # noqa: E402


def se3(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = [x, y, z]
    return T


def se2(x: float, y: float, yaw: float) -> np.ndarray:
    return np.array([[math.cos(yaw), -math.sin(yaw), x], [math.sin(yaw), math.cos(yaw), y], [0.0, 0.0, 1.0]])


coord = st.floats(-500, 500)
angle = st.floats(-math.pi, math.pi)


@settings(max_examples=40, deadline=None)
@given(coord, coord, angle, coord, coord, angle)
def test_true_T_world_odom_composes_back(x, y, yaw, ox, oy, oyaw) -> None:
    T_world_odom = se3(x, y, yaw)
    T_odom_base = se3(ox, oy, oyaw, z=1.3)
    T_true = exp.true_T_world_odom(T_world_odom @ T_odom_base, T_odom_base)
    np.testing.assert_allclose(T_true, se2(x, y, yaw), atol=1e-6)


def test_top_l_counts_valid_ranks_and_thresholds() -> None:
    truth = se2(10.0, -4.0, 0.3)
    hyps = np.stack([
        se2(0.0, 0.0, 0.3),  # far away
        se2(10.5, -4.0, 0.3),  # correct but invalid (padding) -> never counts
        se2(50.0, 50.0, 1.0),
        se2(13.0, -4.0, 0.3 + math.radians(7.0)),  # 3 m, 7 deg: only a 10 deg success
        se2(10.0, -3.0, 0.3 - 2 * math.pi),  # correct (yaw wraps), valid rank 3
        se2(10.0, -4.0, 0.3),
    ])
    valid = np.array([True, False, True, True, True, False])
    five = exp.top_l_success(hyps, valid, truth, 5.0, 5.0, (1, 3, 4, 25))
    assert five == {1: False, 3: False, 4: True, 25: True}
    ten = exp.top_l_success(hyps, valid, truth, 5.0, 10.0, (1, 3, 4))
    assert ten == {1: False, 3: True, 4: True}
    assert not any(exp.top_l_success(hyps, np.zeros(6, dtype=bool), truth, 5.0, 5.0).values())


def test_containing_patch_prefers_nearest_centre() -> None:
    bounds = np.array([[0, 60, 0, 60], [30, 90, 0, 60], [60, 120, 0, 60]], dtype=float)
    centres = np.stack([(bounds[:, 0] + bounds[:, 1]) / 2, (bounds[:, 2] + bounds[:, 3]) / 2], 1)
    assert exp.containing_patch(centres, bounds, np.array([50.0, 30.0])) == 1
    assert exp.containing_patch(centres, bounds, np.array([5.0, 5.0])) == 0
    assert exp.containing_patch(centres, bounds, np.array([500.0, 5.0])) is None


def test_table_reports_percentages() -> None:
    tally = exp.Tally(n=4)
    for k in range(4):
        tally.add("Meridian", "known", (5.0, 5.0), {1: k == 0, 5: k < 2, 10: k < 3, 25: True})
    text = exp.format_table("x", tally, (5.0, 5.0), exp.PAPER_KITTI00)
    row = next(line for line in text.splitlines() if line.startswith("Meridian "))
    assert [float(v) for v in row.split()[1:5]] == [25.0, 50.0, 75.0, 100.0]
    assert "38.3" in text


def test_line_agreement_under_the_true_transform() -> None:
    T = se2(100.0, 50.0, 0.7)
    ground = np.array([[[0.0, 0.0], [10.0, 0.0]], [[0.0, 5.0], [0.0, 15.0]]])
    mapped = ground @ T[:2, :2].T + T[:2, 2]
    # Aerial: line 0 is the first ground line extended along itself, line 1 is the second shifted by 4 m.
    d = mapped[0, 1] - mapped[0, 0]
    normal = np.array([-(mapped[1, 1] - mapped[1, 0])[1], (mapped[1, 1] - mapped[1, 0])[0]]) / 10.0
    aerial = np.stack([mapped[0] + 0.5 * d, mapped[1] + 4.0 * normal])
    ok = exp.line_agreement(ground, aerial, T, 3.0, 10.0)
    assert ok.tolist() == [[True, False], [False, False]]
    assert exp.line_agreement(ground, aerial, T, 5.0, 10.0)[1, 1]

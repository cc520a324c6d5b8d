"""Hand-built cases for meridian_torch.evaluation.primitive_metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from meridian_torch.evaluation.primitive_metrics import (
    dedup_points,
    line_metrics,
    point_metrics,
    polygon_ring,
)


def _rot(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


GT_PTS = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [20.0, 20.0]])


def test_points_perfect_and_shifted() -> None:
    m = point_metrics(GT_PTS, GT_PTS)
    assert (m["precision"], m["recall"], m["n_pred"], m["n_gt"]) == (1.0, 1.0, 4, 4)
    m = point_metrics(GT_PTS + [3.0, 0.0], GT_PTS, radius=2.0)
    assert m["precision"] == 0.0 and m["recall"] == 0.0


def test_points_one_to_one_and_duplicates() -> None:
    # Two predictions near one GT point: only one may match (after de-duplication they are one).
    pred = np.array([[0.2, 0.0], [1.5, 0.0]])
    m = point_metrics(pred, GT_PTS[:1], merge_m=None)
    assert m["precision"] == 0.5 and m["recall"] == 1.0
    # Overlapping patches repeat a point (within 0.5 m): merged before matching.
    m = point_metrics(np.array([[0.0, 0.0], [0.1, 0.1], [0.0, 0.2]]), GT_PTS[:1])
    assert m["n_pred"] == 1 and m["precision"] == 1.0
    # Optimal assignment: the greedy nearest pair (p0-g1) would leave g0 unmatched.
    gt = np.array([[0.0, 0.0], [1.8, 0.0]])
    pred = np.array([[1.0, 0.0], [3.5, 0.0]])
    m = point_metrics(pred, gt, radius=2.0, merge_m=None)
    assert m["precision"] == 1.0 and m["recall"] == 1.0


def test_points_region() -> None:
    region = (-5.0, 15.0, -5.0, 15.0)  # excludes (20, 20)
    m = point_metrics(GT_PTS[:3], GT_PTS, region=region)
    assert m["n_gt"] == 3 and m["recall"] == 1.0
    # A GT point just inside the region matched by a prediction just outside counts.
    m = point_metrics(np.array([[15.5, 0.0]]), np.array([[14.5, 0.0]]), region=region)
    assert m["recall"] == 1.0 and m["n_pred"] == 0 and math.isnan(m["precision"])
    assert dedup_points(np.zeros((5, 2))).shape == (1, 2)


SQUARE = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])


def _edges(poly: np.ndarray) -> np.ndarray:
    ring = polygon_ring(poly)
    return np.stack([ring[:-1], ring[1:]], axis=1)


def test_lines_perfect_and_shifted() -> None:
    m = line_metrics(_edges(SQUARE), [polygon_ring(SQUARE)])
    assert m["precision"] == pytest.approx(1.0) and m["recall"] == pytest.approx(1.0)
    assert m["pred_length"] == pytest.approx(40.0) and m["gt_length"] == pytest.approx(40.0)
    # Shifting a single horizontal line 3 m north: nothing within 1 m.
    gt = [np.array([[0.0, 0.0], [10.0, 0.0]])]
    m = line_metrics(np.array([[[0.0, 3.0], [10.0, 3.0]]]), gt)
    assert m["precision"] == 0.0 and m["recall"] == 0.0


def test_lines_half_coverage_and_union() -> None:
    gt = [np.array([[0.0, 0.0], [10.0, 0.0]])]
    m = line_metrics(np.array([[[0.0, 0.3], [5.0, 0.3]]]), gt)
    assert m["precision"] == pytest.approx(1.0) and m["recall"] == pytest.approx(0.5)
    # A prediction twice as long as the GT: half of its length is wrong.
    m = line_metrics(np.array([[[0.0, 0.0], [20.0, 0.0]]]), gt)
    assert m["precision"] == pytest.approx(0.5) and m["recall"] == pytest.approx(1.0)
    # Duplicates from overlapping patches count once (union): a correct copy and a wrong line.
    pred = np.array([[[0.0, 0.0], [10.0, 0.0]], [[0.0, 0.1], [10.0, 0.1]], [[0.0, 5.0], [10.0, 5.0]]])
    m = line_metrics(pred, gt)
    assert m["pred_length"] == pytest.approx(20.0) and m["precision"] == pytest.approx(0.5)
    m = line_metrics(pred, gt, merge_m=None)
    assert m["pred_length"] == pytest.approx(30.0)


def test_lines_angle() -> None:
    gt = [np.array([[-10.0, 0.0], [10.0, 0.0]])]
    seg = np.array([[[-0.5, 0.0], [0.5, 0.0]]])
    for deg, expected in ((20.0, 0.0), (5.0, 1.0), (180.0 - 5.0, 1.0)):  # direction is undirected
        m = line_metrics(seg @ _rot(deg).T, gt)
        assert m["precision"] == pytest.approx(expected), deg
    # A whole rotated copy of the square: precision/recall zero.
    m = line_metrics(_edges(SQUARE - 5.0) @ _rot(20.0).T, [polygon_ring(SQUARE - 5.0)], dist=0.2)
    assert m["precision"] == 0.0 and m["recall"] == 0.0


def test_lines_region_and_empty() -> None:
    gt = [np.array([[-10.0, 0.0], [10.0, 0.0]])]
    m = line_metrics(np.array([[[0.0, 0.0], [10.0, 0.0]]]), gt, region=(-20.0, 20.0, -20.0, 20.0), margin=10.0)
    assert m["gt_length"] == pytest.approx(20.0) and m["recall"] == pytest.approx(0.5)
    m = line_metrics(np.zeros((0, 2, 2)), gt)
    assert math.isnan(m["precision"]) and m["recall"] == 0.0

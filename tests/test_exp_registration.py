"""Evaluation logic of scripts/exp_registration.py (truth, success at top-L, patch choice)."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
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


def primitive_set(n_points: int, n_lines: int, seed: int = 0):
    import torch

    from meridian_torch.types import PrimitiveSet

    g = torch.Generator().manual_seed(seed)
    desc = torch.nn.functional.normalize(torch.randn(n_points + n_lines, 8, generator=g), dim=1)
    start = torch.rand(n_lines, 2, generator=g) * 50
    return PrimitiveSet(
        points_xy=torch.rand(n_points, 2, generator=g) * 40 - 10,
        point_descriptors=desc[:n_points],
        point_segment_ids=torch.arange(n_points),
        line_endpoints=torch.stack([start, start + torch.rand(n_lines, 2, generator=g) * 10 + 1], 1),
        line_kinds=torch.randint(0, 3, (n_lines,), generator=g),
        line_descriptors=desc[n_points:],
        line_segment_ids=torch.arange(n_points, n_points + n_lines),
    )


def rows_of(x, table) -> np.ndarray:
    """For each row of x (n, ...) the index of an equal row of table, -1 if none."""
    x, table = np.asarray(x), np.asarray(table)
    width = int(np.prod(x.shape[1:]))
    x, table = x.reshape(len(x), width), table.reshape(len(table), width)
    if len(table) == 0:
        return np.full(len(x), -1)
    equal = (x[:, None] == table[None]).all(-1)
    return np.where(equal.any(1), equal.argmax(1), -1)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 40), st.integers(0, 30), st.floats(0, 1), st.floats(0, 0.6), st.integers(0, 10**6))
def test_perturbation_respects_fractions_and_keeps_copies(n_points, n_lines, missing, spurious, seed) -> None:
    from meridian_torch.evaluation.perturbation import Perturbation, perturb_primitives

    p = primitive_set(n_points, n_lines, seed % 97)
    out = perturb_primitives(p, Perturbation(missing, spurious, 0.0), seed)
    for n, xy, kept_xy, desc, kept_desc in (
        (n_points, out.points_xy, p.points_xy, out.point_descriptors, p.point_descriptors),
        (n_lines, out.line_endpoints, p.line_endpoints, out.line_descriptors, p.line_descriptors),
    ):
        n_kept, n_spurious = n - round(missing * n), round(spurious * n)
        assert len(xy) == len(desc) == n_kept + n_spurious
        # Without noise the kept primitives are originals (distinct, in order); every descriptor is a copy.
        kept = rows_of(xy[:n_kept], kept_xy)
        assert (kept >= 0).all() and (np.diff(kept) > 0).all()
        assert (rows_of(desc, kept_desc) >= 0).all()
    corners = np.concatenate([p.points_xy.numpy(), p.line_endpoints.numpy().reshape(-1, 2)])
    if len(corners):
        n_kept = n_points - round(missing * n_points)
        spurious_xy = out.points_xy[n_kept:].numpy()
        assert (spurious_xy >= corners.min(0) - 1e-4).all() and (spurious_xy <= corners.max(0) + 1e-4).all()
        n_kept = n_lines - round(missing * n_lines)
        mid = out.line_endpoints[n_kept:].mean(1).numpy()
        assert (mid >= corners.min(0) - 1e-4).all() and (mid <= corners.max(0) + 1e-4).all()
        length = (out.line_endpoints[:, 1] - out.line_endpoints[:, 0]).norm(dim=-1).numpy()
        original = (p.line_endpoints[:, 1] - p.line_endpoints[:, 0]).norm(dim=-1).numpy()
        if n_lines:
            assert (np.abs(length[:, None] - original[None]).min(1) < 1e-3).all()
    ids = np.concatenate([out.point_segment_ids.numpy(), out.line_segment_ids.numpy()])
    assert len(np.unique(ids)) == len(ids)


def test_perturbation_is_seeded_and_zero_is_identity() -> None:
    from meridian_torch.evaluation.perturbation import Perturbation, parse_perturbation, perturb_primitives

    p = primitive_set(30, 20)
    heavy = parse_perturbation("missing=0.4, spurious=0.2,noise_m=1.0")
    assert heavy == Perturbation(0.4, 0.2, 1.0)
    a, b, c = (perturb_primitives(p, heavy, s) for s in (3, 3, 4))
    for name in ("points_xy", "point_descriptors", "line_endpoints", "line_kinds", "line_descriptors"):
        assert torch_equal(getattr(a, name), getattr(b, name))
    assert not torch_equal(a.points_xy, c.points_xy)
    assert perturb_primitives(p, parse_perturbation(""), 3) is p
    for bad in ("missing=1.5", "outliers=0.2", "noise_m=x", "missing"):
        try:
            parse_perturbation(bad)
        except ValueError:
            continue
        raise AssertionError(f"{bad!r} accepted")


def torch_equal(a, b) -> bool:
    return a.shape == b.shape and bool((a == b).all())


def test_perturbation_noise_has_the_asked_spread() -> None:
    from meridian_torch.evaluation.perturbation import Perturbation, perturb_primitives

    p = primitive_set(2000, 1000)
    out = perturb_primitives(p, Perturbation(noise_m=0.7), 0)
    point_noise = (out.points_xy - p.points_xy).numpy().ravel()
    line_noise = (out.line_endpoints - p.line_endpoints).numpy().ravel()
    for noise in (point_noise, line_noise):  # 4000 samples: the sample std is within ~2 % of 0.7
        assert abs(noise.std() - 0.7) < 0.05 and abs(noise.mean()) < 0.05


def test_across_patch_success_ranks_all_patches_by_probability() -> None:
    truth = se2(10.0, -4.0, 0.3)
    wrong = se2(200.0, 0.0, 0.3)
    T = np.stack([np.stack([truth, wrong]), np.stack([wrong, truth])])  # (2 patches, 2, 3, 3)
    valid = np.ones((2, 2), bool)
    # Patch 1's wrong pose is the most probable overall, patch 0's truth second.
    prob = np.array([[0.5, 0.1], [0.6, 0.05]])
    assert exp.across_patch_success(T, prob, valid, truth, 5.0, 5.0, (1, 2)) == {1: False, 2: True}
    # An invalid hypothesis never ranks; a tie with a wrong one is not a success.
    assert exp.across_patch_success(T, prob, np.array([[True, True], [False, True]]), truth, 5.0, 5.0, (1,)) == {1: True}
    tie = np.array([[0.5, 0.1], [0.5, 0.05]])
    assert exp.across_patch_success(T, tie, valid, truth, 5.0, 5.0, (1, 2)) == {1: False, 2: True}


def test_decoy_patches_do_not_overlap_the_true_one() -> None:
    x0, y0 = np.meshgrid(np.arange(0, 300, 30.0), np.arange(0, 300, 30.0))
    bounds = np.stack([x0.ravel(), x0.ravel() + 60, y0.ravel(), y0.ravel() + 60], 1)
    true = 44
    a = exp.decoy_patches(bounds, true, 24, np.random.default_rng(1))
    b = exp.decoy_patches(bounds, true, 24, np.random.default_rng(1))
    assert (a == b).all() and len(np.unique(a)) == 24 and true not in a
    t = bounds[true]
    overlap_x = (bounds[a, 0] < t[1]) & (bounds[a, 1] > t[0])
    overlap_y = (bounds[a, 2] < t[3]) & (bounds[a, 3] > t[2])
    assert not (overlap_x & overlap_y).any()
    try:
        exp.decoy_patches(bounds, true, 100, np.random.default_rng(1))
    except ValueError:
        pass
    else:
        raise AssertionError("more decoys than patches apart were returned")


def test_across_table_reports_per_patch_and_across() -> None:
    tally = exp.Tally(n=2)
    for k in range(2):
        tally.add("Meridian", "unknown", (5.0, 5.0), {1: True, 5: True, 10: True, 25: True})
        tally.add("Meridian", "unknown across", (5.0, 5.0), {1: k == 0, 5: True})
    text = exp.format_across_table("x", tally, (5.0, 5.0), 24)
    row = next(line for line in text.splitlines() if line.startswith("Meridian "))
    assert [float(v) for v in row.split()[1:]] == [0.0, 0.0, 0.0, 100.0, 50.0, 100.0]


def test_seeds_must_be_positive(capsys: pytest.CaptureFixture[str]) -> None:
    # --seeds 0 would report tables of zero cases: refused before any work.
    with pytest.raises(SystemExit):
        exp.main(["--sequence", "missing-sequence", "--map", "missing.mtm", "--seeds", "0"])
    assert "--seeds must be at least 1, got 0" in capsys.readouterr().err

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize_scalar

from meridian_torch.config.matching import RegistrationConfig
from meridian_torch.geometry.se2 import rotation_matrix, se2_apply, wrap_angle
from meridian_torch.matching.registration import RegistrationResult, register_se2

DT = torch.float64
seeds = st.integers(0, 2**31 - 1)
fast = settings(max_examples=40, deadline=None)


@dataclass
class Scene:
    """One association set with its ground truth T_dst_src; tensors carry a batch dimension of 1."""

    theta: float
    t: torch.Tensor  # (2,)
    src_points: torch.Tensor  # (1, m, 2)
    dst_points: torch.Tensor
    point_weights: torch.Tensor  # (1, m)
    src_lines: torch.Tensor  # (1, k, 2, 2)
    dst_lines: torch.Tensor
    line_weights: torch.Tensor  # (1, k)

    def register(self, **kwargs: object) -> RegistrationResult:
        return register_se2(
            self.src_points, self.dst_points, self.point_weights,
            self.src_lines, self.dst_lines, self.line_weights, **kwargs,
        )


def _uniform(g: torch.Generator, shape: tuple[int, ...], lo: float, hi: float) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(shape, generator=g, dtype=DT)


def _scene(seed: int, n_points: int, n_lines: int, *, spread: float = 20.0, offset: float = 0.0) -> Scene:
    """Random SE(2), random source primitives and their exact images in the destination.

    Destination lines are re-sampled along the mapped infinite line (endpoints do not correspond,
    as between an aerial segment and a ground ray) and their direction is flipped at random.
    """
    g = torch.Generator().manual_seed(seed)
    theta = float(_uniform(g, (), -math.pi, math.pi))
    t = _uniform(g, (2,), -100.0, 100.0) + offset
    R = rotation_matrix(torch.tensor(theta, dtype=DT))
    src_points = _uniform(g, (n_points, 2), -spread, spread)
    dst_points = src_points @ R.T + t

    anchor = _uniform(g, (n_lines, 2), -spread, spread)
    angle = _uniform(g, (n_lines,), 0.0, math.pi)
    direction = torch.stack([torch.cos(angle), torch.sin(angle)], -1)
    along = torch.stack([_uniform(g, (n_lines,), -10.0, -1.0), _uniform(g, (n_lines,), 1.0, 10.0)], -1)
    src_lines = anchor[:, None] + along[..., None] * direction[:, None]
    dst_anchor, dst_direction = anchor @ R.T + t, direction @ R.T
    dst_along = torch.stack([_uniform(g, (n_lines,), -15.0, -2.0), _uniform(g, (n_lines,), 2.0, 15.0)], -1)
    flip = torch.rand(n_lines, generator=g) < 0.5
    dst_along = torch.where(flip[:, None], dst_along.flip(-1), dst_along)
    dst_lines = dst_anchor[:, None] + dst_along[..., None] * dst_direction[:, None]
    return Scene(
        theta, t, src_points[None], dst_points[None], torch.ones(1, n_points, dtype=DT),
        src_lines[None], dst_lines[None], torch.ones(1, n_lines, dtype=DT),
    )


def _assert_recovers(scene: Scene, result: RegistrationResult, tol: float = 1e-5) -> None:
    assert bool(result.valid[0])
    assert abs(float(wrap_angle(result.theta[0] - scene.theta))) < tol
    assert torch.allclose(result.t[0], scene.t, atol=tol, rtol=0)
    assert math.isclose(float(torch.linalg.det(result.R[0])), 1.0, abs_tol=1e-12)
    assert float(result.point_residual[0]) < tol and float(result.line_residual[0]) < tol


def _line_normals_offsets(lines: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    d = lines[:, 1] - lines[:, 0]
    n = torch.stack([-d[:, 1], d[:, 0]], -1) / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    return n, (n * lines[:, 0]).sum(-1)


def _concurrency_residual(lines: torch.Tensor) -> float:
    """RMS distance of the lines from the point closest to all of them (0 = all through one point)."""
    n, o = _line_normals_offsets(lines)
    c = torch.linalg.lstsq(n, o[:, None]).solution[:, 0]
    return float(((n @ c - o) ** 2).mean().sqrt())


# ----------------------------------------------------------------------------------------- recovery


@fast
@given(seeds, st.integers(2, 12))
def test_points_recover_exact_transform(seed: int, n_points: int) -> None:
    scene = _scene(seed, n_points, 0)
    assume(float(torch.pdist(scene.src_points[0]).max()) > 2.0)
    _assert_recovers(scene, scene.register())


@fast
@given(seeds, st.integers(3, 8))
def test_lines_only_recover_exact_transform(seed: int, n_lines: int) -> None:
    # Two lines alone are ambiguous (a half turn about their intersection maps them onto
    # themselves), so lines-only sets need >= 3 lines that are not all concurrent.
    scene = _scene(seed, 0, n_lines)
    n, _ = _line_normals_offsets(scene.src_lines[0])
    assume(float(torch.linalg.eigvalsh(n.T @ n)[0]) > 0.3)
    assume(_concurrency_residual(scene.src_lines[0]) > 1.0)
    _assert_recovers(scene, scene.register())


@fast
@given(seeds, st.sampled_from([(1, 1), (1, 2), (1, 4), (2, 1), (3, 3), (6, 2)]))
def test_points_and_lines_recover_exact_transform(seed: int, counts: tuple[int, int]) -> None:
    n_points, n_lines = counts
    scene = _scene(seed, n_points, n_lines)
    if n_points == 1:
        # A point on a line adds nothing to that line's half-turn ambiguity: put it beside the first
        # line, next to the line's midpoint (where the offset constraint is evaluated).
        n, _ = _line_normals_offsets(scene.src_lines[0])
        side = 2.0 + 3.0 * (seed % 1000) / 1000.0
        scene.src_points[0, 0] = scene.src_lines[0, 0].mean(0) + side * n[0]
        R = rotation_matrix(torch.tensor(scene.theta, dtype=DT))
        scene.dst_points[0] = scene.src_points[0] @ R.T + scene.t
    else:
        assume(float(torch.pdist(scene.src_points[0]).max()) > 2.0)
    _assert_recovers(scene, scene.register())


@fast
@given(seeds)
def test_large_world_coordinates_in_float32(seed: int) -> None:
    # UTM-sized destination coordinates: centring keeps float32 usable. float32 itself rounds
    # such coordinates to ~3 cm, i.e. ~1e-3 rad over the 40 m extent of the scene.
    scene = _scene(seed, 5, 3, offset=5e5)
    assume(float(torch.pdist(scene.src_points[0]).max()) > 2.0)
    args = [x.float() for x in (scene.src_points, scene.dst_points, scene.point_weights,
                                scene.src_lines, scene.dst_lines, scene.line_weights)]
    result = register_se2(*args)
    assert result.t.dtype == torch.float32 and bool(result.valid[0])
    assert abs(float(wrap_angle(result.theta[0].double() - scene.theta))) < 5e-3
    assert torch.allclose(result.t[0].double(), scene.t, atol=0.3, rtol=0)


def test_transform_maps_source_into_destination() -> None:
    scene = _scene(7, 4, 2)
    result = scene.register()
    assert result.T_dst_src.shape == (1, 3, 3)
    assert torch.allclose(se2_apply(result.T_dst_src, scene.src_points), scene.dst_points, atol=1e-9)


# -------------------------------------------------------------------------------- no reflections


@fast
@given(seeds, st.integers(3, 10), st.integers(0, 4))
def test_mirrored_data_gives_poor_fit_not_reflection(seed: int, n_points: int, n_lines: int) -> None:
    scene = _scene(seed, n_points, n_lines)
    src = scene.src_points[0]
    # Collinear points are mirror-symmetric, so their mirror image is reachable by a rotation.
    minor_std = float(torch.linalg.eigvalsh(torch.cov(src.T))[0].sqrt())
    assume(minor_std > 1.0)
    mirror = torch.tensor([1.0, -1.0], dtype=DT)
    result = register_se2(
        scene.src_points, scene.dst_points * mirror, scene.point_weights,
        scene.src_lines, scene.dst_lines * mirror, scene.line_weights,
    )
    assert math.isclose(float(torch.linalg.det(result.R[0])), 1.0, abs_tol=1e-12)
    assert float(result.point_residual[0]) > 0.5 * minor_std


# ------------------------------------------------------------------------------------ degeneracy


def _batch(*scenes: Scene) -> list[torch.Tensor]:
    """Stack scenes with equal counts into one batch."""
    names = ("src_points", "dst_points", "point_weights", "src_lines", "dst_lines", "line_weights")
    return [torch.cat([getattr(s, name) for s in scenes]) for name in names]


def test_degenerate_sets_are_flagged() -> None:
    g = torch.Generator().manual_seed(3)
    one_point = _scene(1, 1, 0)
    coincident = _scene(2, 2, 0)
    coincident.src_points[0, 1] = coincident.src_points[0, 0]
    coincident.dst_points[0, 1] = coincident.dst_points[0, 0]
    two_lines = _scene(3, 0, 2)
    one_line = _scene(4, 0, 1)
    empty = _scene(5, 0, 0)

    # Parallel lines only: translation along the lines is free.
    parallel = _scene(6, 0, 4)
    d = parallel.src_lines[0, 0, 1] - parallel.src_lines[0, 0, 0]
    start = _uniform(g, (4, 2), -20.0, 20.0)
    parallel.src_lines[0] = torch.stack([start, start + d * _uniform(g, (4, 1), 0.5, 2.0)], 1)
    R = rotation_matrix(torch.tensor(parallel.theta, dtype=DT))
    parallel.dst_lines[0] = parallel.src_lines[0] @ R.T + parallel.t

    # Three lines through one point: the half turn about it fits as well as the truth.
    concurrent = _scene(7, 0, 3)
    centre = _uniform(g, (2,), -5.0, 5.0)
    angles = torch.tensor([0.3, 1.4, 2.5], dtype=DT)
    dirs = torch.stack([torch.cos(angles), torch.sin(angles)], -1)
    concurrent.src_lines[0] = torch.stack([centre - 3 * dirs, centre + 5 * dirs], 1)
    R = rotation_matrix(torch.tensor(concurrent.theta, dtype=DT))
    concurrent.dst_lines[0] = concurrent.src_lines[0] @ R.T + concurrent.t

    for scene in (one_point, coincident, two_lines, one_line, empty, parallel, concurrent):
        result = scene.register()
        assert not bool(result.valid[0])
        assert math.isclose(float(torch.linalg.det(result.R[0])), 1.0, abs_tol=1e-12)
        assert torch.isfinite(result.t).all() and torch.isfinite(result.theta).all()
    assert float(parallel.register().condition[0]) < 1e-9
    assert float(one_point.register().condition[0]) < 1e-9
    assert float(two_lines.register().ambiguity_gap[0]) < 1e-6
    assert float(concurrent.register().ambiguity_gap[0]) < 1e-6


# --------------------------------------------------------------------------------------- padding


@fast
@given(seeds, st.integers(0, 5), st.integers(0, 5))
def test_padding_is_ignored(seed: int, pad_points: int, pad_lines: int) -> None:
    scene = _scene(seed, 3, 2)
    g = torch.Generator().manual_seed(seed + 1)
    filler = [float("nan"), 0.0, 1e6]

    def pad(x: torch.Tensor, n: int) -> torch.Tensor:
        garbage = _uniform(g, (1, n) + tuple(x.shape[2:]), -50.0, 50.0)
        garbage.view(-1)[: len(filler)] = torch.tensor(filler[: garbage.numel()], dtype=DT)
        return torch.cat([x, garbage], 1)

    result = scene.register()
    padded = register_se2(
        pad(scene.src_points, pad_points), pad(scene.dst_points, pad_points),
        torch.cat([scene.point_weights, torch.zeros(1, pad_points, dtype=DT)], 1),
        pad(scene.src_lines, pad_lines), pad(scene.dst_lines, pad_lines),
        torch.cat([scene.line_weights, torch.zeros(1, pad_lines, dtype=DT)], 1),
    )
    for name in ("theta", "t", "valid", "condition", "point_residual", "line_residual"):
        assert torch.allclose(getattr(padded, name).double(), getattr(result, name).double(), atol=1e-9), name


# ------------------------------------------------------------------------ batched vs slow reference


def _reference_register(
    src_points: np.ndarray, dst_points: np.ndarray, w: np.ndarray,
    src_lines: np.ndarray, dst_lines: np.ndarray, v: np.ndarray, direction_weight: float,
) -> tuple[float, np.ndarray]:
    """One set, independently of the batched derivation: dense angle search + bounded 1D refinement.

    For each angle the translation is the weighted linear least-squares solution of the point
    residuals R p + t - q and the point-to-line residuals n·(R a + t - b) (a, b = line midpoints,
    n = destination normal); the direction residual n·R d does not depend on t.
    """
    src_mid, dst_mid = src_lines.mean(1), dst_lines.mean(1)
    d_src = src_lines[:, 1] - src_lines[:, 0]
    d_src /= np.linalg.norm(d_src, axis=1, keepdims=True)
    d_dst = dst_lines[:, 1] - dst_lines[:, 0]
    n_dst = np.stack([-d_dst[:, 1], d_dst[:, 0]], 1) / np.linalg.norm(d_dst, axis=1, keepdims=True)

    def solve(theta: float) -> tuple[float, np.ndarray]:
        R = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
        sw, sv = np.sqrt(w), np.sqrt(v)
        # Rows: (A t - y) scaled by sqrt(weight).
        A = np.concatenate([np.repeat(np.eye(2)[None], len(w), 0).reshape(-1, 2) * np.repeat(sw, 2)[:, None],
                            n_dst * sv[:, None]])
        y = np.concatenate([((dst_points - src_points @ R.T) * sw[:, None]).reshape(-1),
                            ((n_dst * (dst_mid - src_mid @ R.T)).sum(1)) * sv])
        t = np.linalg.lstsq(A, y, rcond=None)[0]
        direction = (n_dst * (d_src @ R.T)).sum(1)
        return float(((A @ t - y) ** 2).sum() + direction_weight * (v * direction**2).sum()), t

    grid = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    start = grid[np.argmin([solve(th)[0] for th in grid])]
    step = grid[1] - grid[0]
    best = minimize_scalar(lambda th: solve(th)[0], bounds=(start - step, start + step), method="bounded",
                           options={"xatol": 1e-12}).x
    return float(best), solve(best)[1]


def test_batched_equals_per_set_loop() -> None:
    g = torch.Generator().manual_seed(11)
    compositions = [(2, 0), (5, 0), (0, 3), (0, 6), (1, 1), (1, 3), (3, 2), (8, 5), (1, 0), (0, 2)]
    scenes = []
    for i, (n_p, n_l) in enumerate(compositions):
        s = _scene(100 + i, n_p, n_l)
        s.dst_points += 0.05 * torch.randn(s.dst_points.shape, generator=g, dtype=DT)
        s.dst_lines += 0.05 * torch.randn(s.dst_lines.shape, generator=g, dtype=DT)
        levels = torch.tensor([0.5, 1.0, 2.0], dtype=DT)
        s.point_weights = levels[torch.randint(0, 3, s.point_weights.shape, generator=g)]
        s.line_weights = levels[torch.randint(0, 3, s.line_weights.shape, generator=g)]
        scenes.append(s)
    m, k = max(c[0] for c in compositions), max(c[1] for c in compositions)

    def pad(x: torch.Tensor, n: int) -> torch.Tensor:
        return torch.cat([x, x.new_zeros((1, n - x.shape[1]) + tuple(x.shape[2:]))], 1)

    batch = register_se2(
        torch.cat([pad(s.src_points, m) for s in scenes]), torch.cat([pad(s.dst_points, m) for s in scenes]),
        torch.cat([pad(s.point_weights, m) for s in scenes]),
        torch.cat([pad(s.src_lines, k) for s in scenes]), torch.cat([pad(s.dst_lines, k) for s in scenes]),
        torch.cat([pad(s.line_weights, k) for s in scenes]),
    )
    assert batch.valid.tolist() == [True] * 8 + [False, False]
    config = RegistrationConfig()
    for i, s in enumerate(scenes):
        single = s.register()
        for name in ("theta", "t", "valid", "condition", "ambiguity_gap", "point_residual", "line_residual"):
            assert torch.allclose(getattr(batch, name)[i], getattr(single, name)[0], atol=1e-9), (i, name)
        if not bool(batch.valid[i]):
            continue
        theta_ref, t_ref = _reference_register(
            *(x[0].numpy() for x in (s.src_points, s.dst_points, s.point_weights,
                                     s.src_lines, s.dst_lines, s.line_weights)),
            config.line_direction_weight,
        )
        assert abs(float(wrap_angle(batch.theta[i] - theta_ref))) < 1e-7, i
        assert np.allclose(batch.t[i].numpy(), t_ref, atol=1e-5), i


# ------------------------------------------------------------------------------- known rotation


@fast
@given(seeds, st.sampled_from([(1, 0), (0, 2), (3, 1), (0, 5)]))
def test_known_rotation_recovers_translation(seed: int, counts: tuple[int, int]) -> None:
    scene = _scene(seed, *counts)
    if counts == (0, 2):
        n, _ = _line_normals_offsets(scene.src_lines[0])
        assume(abs(float(n[0, 0] * n[1, 1] - n[0, 1] * n[1, 0])) > 0.5)
    prior = torch.tensor([scene.theta], dtype=DT)
    result = scene.register(rotation_prior=prior)
    # A single point or two lines are enough once the rotation is known.
    _assert_recovers(scene, result)
    assert float(result.theta[0]) == pytest.approx(float(wrap_angle(prior[0])), abs=1e-15)


def test_known_rotation_with_parallel_lines_is_degenerate() -> None:
    scene = _scene(5, 0, 1)
    result = scene.register(rotation_prior=torch.tensor([scene.theta], dtype=DT))
    assert not bool(result.valid[0]) and float(result.condition[0]) < 1e-9


# -------------------------------------------------------------------------------------- noise


@settings(max_examples=20, deadline=None)
@given(seeds)
def test_noisy_inputs_give_residuals_of_noise_size(seed: int) -> None:
    sigma = 0.1
    scene = _scene(seed, 40, 10)
    g = torch.Generator().manual_seed(seed)
    scene.dst_points += sigma * torch.randn(scene.dst_points.shape, generator=g, dtype=DT)
    # Noise across the destination line only (noise along it does not move the line).
    n, _ = _line_normals_offsets(scene.dst_lines[0])
    scene.dst_lines += sigma * torch.randn((1, 10, 1, 1), generator=g, dtype=DT) * n[None, :, None]
    result = scene.register()
    assert bool(result.valid[0])
    # RMS of a 2D residual of per-axis noise sigma is ~ sqrt(2) sigma (less the 3 fitted dof).
    assert 0.7 * sigma * math.sqrt(2) < float(result.point_residual[0]) < 1.3 * sigma * math.sqrt(2)
    assert 0.3 * sigma < float(result.line_residual[0]) < 2.0 * sigma
    assert abs(float(wrap_angle(result.theta[0] - scene.theta))) < 0.01
    assert torch.allclose(result.t[0], scene.t, atol=0.2, rtol=0)


def test_shape_errors_are_reported() -> None:
    scene = _scene(0, 3, 2)
    with pytest.raises(ValueError, match="point_weights"):
        register_se2(scene.src_points, scene.dst_points, scene.point_weights[:, :2],
                     scene.src_lines, scene.dst_lines, scene.line_weights)
    with pytest.raises(ValueError, match="rotation_prior"):
        scene.register(rotation_prior=torch.zeros(2, dtype=DT))

"""`registration._minimise_angle` against its plain definition: f and its derivatives each take
their own sines and cosines, of every set's copy of the grid; the sharing must not change a bit."""

from __future__ import annotations

import math

import pytest
import torch

from meridian_torch.config.matching import RegistrationConfig
from meridian_torch.geometry.se2 import wrap_angle
from meridian_torch.matching.registration import _minimise_angle


def _plain_cost(coef: torch.Tensor, theta: torch.Tensor, order: int) -> torch.Tensor:
    a_c, a_s, b_c, b_s = (coef[:, i, None] for i in range(4))
    c1, s1, c2, s2 = torch.cos(theta), torch.sin(theta), torch.cos(2 * theta), torch.sin(2 * theta)
    if order == 0:
        return a_c * c2 + a_s * s2 + b_c * c1 + b_s * s1
    if order == 1:
        return 2 * (a_s * c2 - a_c * s2) + b_s * c1 - b_c * s1
    return -4 * (a_c * c2 + a_s * s2) - b_c * c1 - b_s * s1


def _plain_minimise_angle(M: torch.Tensor, g_red: torch.Tensor, cfg: RegistrationConfig) -> tuple[torch.Tensor, ...]:
    B, dtype = M.shape[0], M.dtype
    a_c, a_s = 0.5 * (M[:, 0, 0] - M[:, 1, 1]), 0.5 * (M[:, 0, 1] + M[:, 1, 0])
    coef = torch.stack([a_c, a_s, -2 * g_red[:, 0], -2 * g_red[:, 1]], -1)
    n = cfg.n_angle_samples
    step = 2 * math.pi / n
    grid = -math.pi + step * torch.arange(n, dtype=dtype)
    f_grid = _plain_cost(coef, grid.expand(B, n), 0)
    is_min = (f_grid < f_grid.roll(1, -1)) & (f_grid <= f_grid.roll(-1, -1))
    ranked = torch.where(is_min, f_grid, torch.full_like(f_grid, math.inf)).topk(2, dim=-1, largest=False)
    has_second = torch.isfinite(ranked.values[:, 1])
    start = grid[ranked.indices]
    lo, hi = start - step, start + step
    theta = start
    for _ in range(cfg.newton_iterations):
        d1 = _plain_cost(coef, theta, 1)
        d2 = _plain_cost(coef, theta, 2)
        newton = -d1 / d2.clamp_min(torch.finfo(dtype).tiny)
        theta = torch.clamp(theta + torch.where(d2 > 0, newton, -torch.sign(d1) * step), lo, hi)
    f_ref = _plain_cost(coef, theta, 0)
    first_best = (f_ref[:, 0] <= f_ref[:, 1]) | ~has_second
    best = torch.where(first_best, theta[:, 0], theta[:, 1])
    distinct = has_second & (wrap_angle(theta[:, 0] - theta[:, 1]).abs() > 2 * step)
    gap = torch.where(distinct, (f_ref[:, 0] - f_ref[:, 1]).abs(), torch.full_like(best, math.inf))
    return wrap_angle(best), gap


def _same_bits(x: torch.Tensor, y: torch.Tensor) -> bool:
    return x.dtype == y.dtype and torch.equal(x.view(-1).view(torch.uint8), y.view(-1).view(torch.uint8))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(("n_angle_samples", "newton_iterations"), [(32, 10), (8, 1), (37, 4), (100, 3)])
def test_minimise_angle_is_bitwise_its_plain_definition(
    dtype: torch.dtype, n_angle_samples: int, newton_iterations: int
) -> None:
    gen = torch.Generator().manual_seed(n_angle_samples)
    B = 3001  # not a multiple of the vector width
    A = torch.randn(B, 2, 2, generator=gen, dtype=torch.float64) * 10.0 ** torch.randint(-3, 4, (B, 1, 1), generator=gen)
    M = (A @ A.transpose(1, 2)).to(dtype)  # positive semi-definite, as a Schur complement is
    g_red = (torch.randn(B, 2, generator=gen, dtype=torch.float64) * 10.0 ** torch.randint(-3, 4, (B, 1), generator=gen)).to(dtype)
    M[:10], g_red[:10] = 0.0, 0.0  # padding: f flat, no grid minimum
    g_red[10:20] = 0.0  # lines through one point: two equal minima pi apart
    M[20:30] = torch.eye(2, dtype=dtype)  # rotation-free quadratic part
    M[30], g_red[31] = math.nan, math.inf  # non-finite sums
    g_red[32:40] = -0.0
    cfg = RegistrationConfig(n_angle_samples=n_angle_samples, newton_iterations=newton_iterations)
    theta, gap = _minimise_angle(M, g_red, cfg)
    plain_theta, plain_gap = _plain_minimise_angle(M, g_red, cfg)
    assert _same_bits(theta, plain_theta) and _same_bits(gap, plain_gap)
    assert bool(torch.isfinite(gap).any()) and bool(torch.isinf(gap).any())  # both kinds of set occur
    empty = _minimise_angle(M[:0], g_red[:0], cfg)
    assert empty[0].shape == (0,) and empty[1].shape == (0,)

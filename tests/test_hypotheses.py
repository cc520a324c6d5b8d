"""Greedy clustering of inlier sets: the compiled walk over the poses, torch's fixed-point sweeps
over all pairs and the plain definition pick the same representatives and weights."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from meridian_torch.geometry.se2 import wrap_angle
from meridian_torch.matching.hypotheses import _greedy_representatives, _representatives


@pytest.mark.parametrize("seed", range(4))
def test_greedy_representatives_sweeps_equal_the_definition(seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    n_patches, n_sets = 5, 40
    close = torch.rand(n_patches, n_sets, n_sets, generator=gen) < 0.15
    close = close | close.transpose(1, 2) | torch.eye(n_sets, dtype=torch.bool)  # symmetric, reflexive
    valid = torch.rand(n_patches, n_sets, generator=gen) < 0.8
    valid[0] = False  # a patch without sets
    expected = torch.zeros_like(valid)
    for p in range(n_patches):  # the definition: in order, unless close to an earlier representative
        for s in range(n_sets):
            expected[p, s] = bool(valid[p, s]) and not any(
                bool(expected[p, r] and close[p, s, r]) for r in range(s)
            )
    assert torch.equal(_greedy_representatives(close, valid), expected)
    assert expected.any() and (valid & ~expected).any()  # both outcomes occur


def random_poses(seed: int, n_patches: int, n_sets: int, dtype: torch.dtype) -> tuple[SimpleNamespace, torch.Tensor]:
    """Registrations clumped so that clusters form, many pairs right at the limits (1 m, 5 deg,
    yaw differences near +-pi), some NaN poses among the valid ones, and particle counts."""
    gen = torch.Generator().manual_seed(seed)
    centre = torch.randint(0, 4, (n_patches, n_sets, 2), generator=gen).to(dtype)
    t = centre + torch.randn(n_patches, n_sets, 2, generator=gen, dtype=dtype) * 0.6
    t[:, ::7, 0] = t[:, :1, 0] + 1.0  # exactly the translation limit from set 0
    t[:, ::7, 1] = t[:, :1, 1]
    theta = wrap_angle(torch.randint(-1, 2, (n_patches, n_sets), generator=gen).to(dtype) * math.pi
                       + torch.randn(n_patches, n_sets, generator=gen, dtype=dtype) * 0.08)
    theta[:, 3::9] = wrap_angle(theta[:, :1] + math.radians(5.0))  # at the rotation limit
    theta[:, 5::11] = -math.pi
    valid = torch.rand(n_patches, n_sets, generator=gen) < 0.85
    valid[0] = False  # a patch without valid registrations
    t[1, 2] = float("nan")  # a valid set whose pose is close to nothing, not even itself
    theta[2, 0] = float("nan")
    counts = torch.randint(0, 30, (n_patches, n_sets), generator=gen)
    return SimpleNamespace(t=t, theta=theta, valid=valid), counts


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", range(3))
def test_compiled_clustering_equals_the_torch_sweeps(dtype: torch.dtype, seed: int) -> None:
    # CPU tensors cluster with a compiled walk comparing only the pairs it needs, other devices
    # with torch's pairwise tensors and sweeps: the same representatives and weights.
    reg, counts = random_poses(seed, 6, 120, dtype)
    for translation_m, rotation_deg in [(1.0, 5.0), (0.3, 1.0), (100.0, 360.0)]:
        compiled = _representatives(reg, counts, translation_m, rotation_deg, compiled=True)
        reference = _representatives(reg, counts, translation_m, rotation_deg, compiled=False)
        for got, want in zip(compiled, reference):
            assert got.dtype == want.dtype and torch.equal(got, want)
        rep, weight = reference
        assert (reg.valid & ~rep).any()  # sets join clusters
        assert int(weight.sum()) == int(torch.where(reg.valid, counts, 0).sum())  # no count is lost
        assert int(weight[~rep].abs().sum()) == 0
        if rotation_deg < 360.0:
            assert rep.sum() > 2 * len(rep)  # several clusters per patch


def test_compiled_clustering_without_sets() -> None:
    for n_patches, n_sets in [(0, 4), (2, 1)]:  # InlierSets always have a set column
        reg = SimpleNamespace(t=torch.zeros(n_patches, n_sets, 2), theta=torch.zeros(n_patches, n_sets),
                              valid=torch.ones(n_patches, n_sets, dtype=torch.bool))
        counts = torch.ones(n_patches, n_sets, dtype=torch.int64)
        for compiled in (True, False):
            rep, weight = _representatives(reg, counts, 1.0, 5.0, compiled=compiled)
            assert rep.shape == weight.shape == (n_patches, n_sets)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_clustering_at_the_limits(dtype: torch.dtype) -> None:
    # Poses a few ulps either side of the limits from set 0 at the origin: the walk compares in
    # the poses' dtype, with the limits rounded to it, as torch does.
    n_sets, translation_m, rotation_deg = 64, 0.3, 1.0
    step = torch.arange(-8, 8, dtype=dtype)
    t = torch.zeros(2, n_sets, 2, dtype=dtype)
    theta = torch.zeros(2, n_sets, dtype=dtype)
    limit = torch.tensor(translation_m, dtype=dtype)
    t[0, 1:17, 0] = limit + step * torch.finfo(dtype).eps * limit  # along x
    t[0, 17:33, 1] = -limit + step * torch.finfo(dtype).eps * limit  # along -y
    angle = torch.tensor(math.radians(rotation_deg), dtype=dtype)
    theta[1, 1:17] = angle + step * torch.finfo(dtype).eps * angle
    theta[1, 17:33] = wrap_angle(torch.tensor(math.pi, dtype=dtype)) - angle + step * torch.finfo(dtype).eps * 4
    reg = SimpleNamespace(t=t, theta=theta, valid=torch.ones(2, n_sets, dtype=torch.bool))
    counts = torch.arange(2 * n_sets).reshape(2, n_sets)
    compiled = _representatives(reg, counts, translation_m, rotation_deg, compiled=True)
    reference = _representatives(reg, counts, translation_m, rotation_deg, compiled=False)
    for got, want in zip(compiled, reference):
        assert torch.equal(got, want)
    assert compiled[0][:, 1:17].any() and not compiled[0][:, 1:17].all()  # both sides of the limits

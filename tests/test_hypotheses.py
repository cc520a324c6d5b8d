"""From inlier sets to hypotheses: the compiled registration of every set follows torch's batched
registration; for the greedy clustering, the compiled walk over the poses, torch's fixed-point
sweeps over all pairs and the plain definition pick the same representatives and weights."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from meridian_torch.config.matching import RegistrationConfig
from meridian_torch.geometry.se2 import wrap_angle
from meridian_torch.matching.associations import Associations
from meridian_torch.matching.hypotheses import _greedy_representatives, _representatives, register_sets
from meridian_torch.types import PrimitiveSet, stack_primitive_sets


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


def _registration_scene(seed: int, dtype: torch.dtype) -> tuple:
    """P patches that each see the ground submap moved by their own SE(2) (with noise and a few
    extra primitives), associations by index with a few wrong and padded ones, and sets of every
    kind: random members, empty, one point, lines through one point (nearly ambiguous), parallel
    lines and a point, a zero-length line."""
    gen = torch.Generator().manual_seed(seed)
    n_points, n_lines, n_patches, n_sets = 9, 11, 3, 40
    points = torch.rand(n_points, 2, generator=gen, dtype=torch.float64) * 60 - 30
    lines = torch.rand(n_lines, 2, 2, generator=gen, dtype=torch.float64) * 60 - 30
    lines[0] = torch.tensor([[0.0, 0.0], [10.0, 0.0]])  # 0-2: through the origin
    lines[1] = torch.tensor([[0.0, 0.0], [0.0, 7.0]])
    lines[2] = torch.tensor([[-3.0, -3.0], [4.0, 4.0]])
    lines[3] = torch.tensor([[0.0, 5.0], [10.0, 5.0]])  # parallel to line 0
    lines[4] = torch.tensor([[2.0, 2.0], [2.0, 2.0]])  # zero length
    patches = []
    for p in range(n_patches):
        theta = float(torch.rand((), generator=gen)) * 2 * math.pi - math.pi
        R = torch.tensor([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]], dtype=torch.float64)
        t = torch.rand(2, generator=gen, dtype=torch.float64) * 400 - 200
        a_pts = points @ R.T + t + 0.2 * torch.randn(n_points, 2, generator=gen, dtype=torch.float64)
        a_lns = lines @ R.T + t + 0.2 * torch.randn(n_lines, 2, 2, generator=gen, dtype=torch.float64)
        a_lns[4] = a_lns[4, :1]  # its image has zero length too
        extra = p + 1  # patches of different sizes: padding in the batch
        a_pts = torch.cat([a_pts, torch.rand(extra, 2, generator=gen, dtype=torch.float64) * 100 + t])
        a_lns = torch.cat([a_lns, torch.rand(extra, 2, 2, generator=gen, dtype=torch.float64) * 100 + t])
        patches.append(PrimitiveSet(a_pts.to(dtype), torch.zeros(len(a_pts), 4), torch.arange(len(a_pts)),
                                    a_lns.to(dtype), torch.zeros(len(a_lns), dtype=torch.int64),
                                    torch.zeros(len(a_lns), 4), torch.arange(len(a_lns))))
    ground = PrimitiveSet(points.to(dtype), torch.zeros(n_points, 4), torch.arange(n_points), lines.to(dtype),
                          torch.zeros(n_lines, dtype=torch.int64), torch.zeros(n_lines, 4), torch.arange(n_lines))
    aerial = stack_primitive_sets(patches)
    n_aerial_points = aerial.points_xy.shape[1]
    k, m = n_points + 2, n_points + 2 + n_lines + 2  # two padded columns per block
    pairs = torch.full((n_patches, m, 2), -1, dtype=torch.int64)
    valid = torch.zeros(n_patches, m, dtype=torch.bool)
    pairs[:, :n_points] = torch.arange(n_points)[:, None]
    pairs[:, k:k + n_lines, 0] = n_points + torch.arange(n_lines)
    pairs[:, k:k + n_lines, 1] = n_aerial_points + torch.arange(n_lines)
    valid[:, :n_points] = valid[:, k:k + n_lines] = True
    pairs[:, 1, 1] = n_points  # a wrong association: an extra aerial point
    pairs[:, k + 5, 1] = n_aerial_points + n_lines  # and an extra aerial line
    is_line = torch.arange(m) >= k
    assoc = Associations(pairs=pairs, is_line=is_line.expand(n_patches, m).clone(), valid=valid,
                         cosine=valid.float(), n_point_assoc=k, n_ground_points=n_points,
                         n_aerial_points=n_aerial_points)
    density = torch.rand(n_patches, n_sets, 1, generator=gen)
    masks = torch.rand(n_patches, n_sets, m, generator=gen) < density
    masks[:, 0] = False  # empty
    masks[:, 1] = False
    masks[:, 1, 2] = True  # one point
    masks[:, 2] = False
    masks[:, 2, [k, k + 1, k + 2]] = True  # lines through one point only
    masks[:, 3] = False
    masks[:, 3, [k, k + 3, 0]] = True  # two parallel lines and a point
    masks[:, 4] = masks[:, 5]
    masks[:, 4, k + 4] = True  # a zero-length line among others
    masks[:, 6] = True  # padded columns too (invalid associations are not members)
    sets = SimpleNamespace(masks=masks, valid=torch.rand(n_patches, n_sets, generator=gen) < 0.9)
    return sets, assoc, ground, aerial


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", range(4))
def test_compiled_registration_of_sets_follows_the_torch_path(dtype: torch.dtype, seed: int) -> None:
    # On the CPU every set is registered in one compiled pass over its mask (float64 inside),
    # elsewhere by torch's batched ops in the inputs' dtype: the same poses and decisions to rounding.
    sets, assoc, ground, aerial = _registration_scene(seed, dtype)
    compiled = register_sets(sets, assoc, ground, aerial, compiled=True)
    reference = register_sets(sets, assoc, ground, aerial, compiled=False)
    rel = 1e-9 if dtype == torch.float64 else 2e-4
    eps = RegistrationConfig()
    # A decision can differ only for a value within rounding of its threshold.
    clear = ((reference.condition - eps.information_eps).abs() > rel * (1 + reference.condition.abs())) & (
        (reference.ambiguity_gap - eps.ambiguity_eps).abs() > rel * (1 + reference.ambiguity_gap.abs()))
    assert torch.equal(compiled.valid[clear], reference.valid[clear])
    ok = reference.valid & compiled.valid
    assert ok.sum() > 20 and (~reference.valid & sets.valid).any()
    assert not compiled.valid[:, :2].any() and not compiled.valid[~sets.valid].any()  # empty, one point: degenerate
    # Poses: well conditioned sets within rounding of the coordinates (~200 m).
    assert torch.allclose(compiled.theta[ok], reference.theta[ok], rtol=0, atol=300 * rel)
    assert torch.allclose(compiled.t[ok], reference.t[ok], rtol=0, atol=300 * rel * 200)
    assert torch.allclose(compiled.R[ok], reference.R[ok], rtol=0, atol=300 * rel)
    for name in ("condition", "point_residual", "line_residual"):
        a, b = getattr(compiled, name)[sets.valid], getattr(reference, name)[sets.valid]
        assert torch.allclose(a, b, rtol=300 * rel, atol=300 * rel), name
    finite = torch.isfinite(reference.ambiguity_gap) & ok
    assert torch.equal(torch.isfinite(compiled.ambiguity_gap[ok]), torch.isfinite(reference.ambiguity_gap[ok]))
    assert torch.allclose(compiled.ambiguity_gap[finite], reference.ambiguity_gap[finite], rtol=300 * rel, atol=300 * rel)
    assert compiled.theta.dtype == compiled.t.dtype == dtype

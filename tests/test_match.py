"""End to end: match_submap recovers a planted SE(2) transform among unrelated patches."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from meridian_torch.matching.config import AssociationConfig, MatchConfig, ParticleConfig
from meridian_torch.matching.match import match_arrays, match_submap
from meridian_torch.types import PrimitiveSet, stack_primitive_sets

YAW, T = 2.1, (512.0, -307.0)


def _lines(gen: torch.Generator, n: int, half: float) -> torch.Tensor:
    e0 = (torch.rand(n, 2, generator=gen) - 0.5) * 2 * half
    ang = torch.rand(n, generator=gen) * math.pi
    length = 4 + 10 * torch.rand(n, generator=gen)
    return torch.stack([e0, e0 + length[:, None] * torch.stack([ang.cos(), ang.sin()], 1)], 1)


def _desc(gen: torch.Generator, n: int, centres: torch.Tensor) -> torch.Tensor:
    cls = torch.randint(0, centres.shape[0], (n,), generator=gen)
    return F.normalize(centres[cls] + F.normalize(torch.randn(n, centres.shape[1], generator=gen), dim=1), dim=1)


def scene(seed: int = 0) -> tuple[PrimitiveSet, list[PrimitiveSet], int, int]:
    """Ground (14 points, 10 lines); patch 0 = 10 points + 8 lines of it moved by (YAW, T) with
    0.2 m noise plus 8 + 6 outliers; patches 1, 2 unrelated. Returns ground, patches, kp, kl."""
    gen = torch.Generator().manual_seed(seed)
    centres = F.normalize(torch.randn(5, 16, generator=gen), dim=1)
    gp, gl = (torch.rand(14, 2, generator=gen) - 0.5) * 50, _lines(gen, 10, 25)
    ground = PrimitiveSet(gp, _desc(gen, 14, centres), torch.arange(14), gl, torch.randint(0, 3, (10,), generator=gen),
                          _desc(gen, 10, centres), torch.arange(10))
    R = torch.tensor([[math.cos(YAW), -math.sin(YAW)], [math.sin(YAW), math.cos(YAW)]])
    t = torch.tensor(T)
    kp, kl = 10, 8

    def patch(true: bool) -> PrimitiveSet:
        n_p, n_l = (8, 6) if true else (18, 14)
        pts, lns = t + (torch.rand(n_p, 2, generator=gen) - 0.5) * 60, t + _lines(gen, n_l, 30)
        pd, ld, kinds = _desc(gen, n_p, centres), _desc(gen, n_l, centres), torch.randint(0, 3, (n_l,), generator=gen)
        if true:
            mix = lambda d: F.normalize(d + 0.5 * F.normalize(torch.randn(d.shape, generator=gen), dim=1), dim=1)  # noqa: E731
            pts = torch.cat([gp[:kp] @ R.T + t + 0.2 * torch.randn(kp, 2, generator=gen), pts])
            lns = torch.cat([gl[:kl] @ R.T + t + 0.2 * torch.randn(kl, 2, 2, generator=gen), lns])
            pd, ld = torch.cat([mix(ground.point_descriptors[:kp]), pd]), torch.cat([mix(ground.line_descriptors[:kl]), ld])
            kinds = torch.cat([ground.line_kinds[:kl], kinds])
        return PrimitiveSet(pts, pd, torch.arange(len(pts)), lns, kinds, ld, torch.arange(len(lns)))

    return ground, [patch(True), patch(False), patch(False)], kp, kl


CFG = MatchConfig(associations=AssociationConfig(k_prim=5), particles=ParticleConfig(n_particles=64, n_iterations=200))


def check_top(hyp, n_aerial_points: int, kp: int, kl: int, n_ground_points: int = 14) -> None:
    assert hyp.valid[0, 0]
    assert abs(math.remainder(float(hyp.theta[0, 0]) - YAW, 2 * math.pi)) < math.radians(1.0)
    assert float((hyp.t[0, 0] - torch.tensor(T)).norm()) < 0.5
    torch.testing.assert_close(hyp.T_world_odom[0, 0, :2, 2], hyp.t[0, 0])
    assert (hyp.probability.sum(1) <= 1 + 1e-6).all() and (hyp.probability >= 0).all()
    chosen = hyp.pairs[0][hyp.association_mask[0, 0]]
    true = {(i, i) for i in range(kp)} | {(n_ground_points + i, n_aerial_points + i) for i in range(kl)}
    correct = sum(tuple(p) in true for p in chosen.tolist())
    assert correct >= 0.8 * chosen.shape[0] and correct >= 6


@pytest.mark.parametrize("prior", [None, YAW + 0.1])
def test_match_submap_recovers_transform(prior: float | None) -> None:
    torch.set_num_threads(1)
    ground, patches, kp, kl = scene()
    batch = stack_primitive_sets(patches)
    hyp = match_submap(ground, batch, rotation_prior=prior, config=CFG, generator=torch.Generator().manual_seed(0))
    assert hyp.T_world_odom.shape == (3, 25, 3, 3) and hyp.valid.shape == (3, 25)
    check_top(hyp, batch.points_xy.shape[1], kp, kl)
    again = match_submap(ground, batch, rotation_prior=prior, config=CFG, generator=torch.Generator().manual_seed(0))
    assert torch.equal(hyp.T_world_odom, again.T_world_odom) and torch.equal(hyp.probability, again.probability)


def test_clipper_solver_and_match_arrays() -> None:
    ground, patches, kp, kl = scene()
    cfg = CFG.model_copy(update={"solver": "clipper"})
    hyp = match_arrays(
        ground.points_xy.numpy(), ground.point_descriptors.numpy(), ground.line_endpoints.numpy(),
        ground.line_kinds.numpy(), ground.line_descriptors.numpy(),
        [p.points_xy.numpy() for p in patches], [p.point_descriptors.numpy() for p in patches],
        [p.line_endpoints.numpy() for p in patches], [p.line_kinds.numpy() for p in patches],
        [p.line_descriptors.numpy() for p in patches], config=cfg,
    )
    check_top(hyp, max(len(p.points_xy) for p in patches), kp, kl)
    assert float(hyp.probability[0, 0]) == 1.0 and int(hyp.valid[0].sum()) == 1

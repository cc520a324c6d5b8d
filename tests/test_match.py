"""End to end: match_submap recovers a planted SE(2) transform among unrelated patches."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from meridian_torch.config.matching import AssociationConfig, MatchConfig, ParticleConfig
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
    # Verified probabilities: each in [0, 1], most probable first, and they compare across patches:
    # the true patch's best beats every decoy's.
    assert ((hyp.probability >= 0) & (hyp.probability <= 1)).all()
    assert (hyp.probability[:, :-1] >= hyp.probability[:, 1:]).all()
    assert float(hyp.probability[0, 0]) == float(hyp.probability.max()) > 0
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


def test_particles_start_by_rotation_mode(monkeypatch: pytest.MonkeyPatch) -> None:
    # The sampler starts at `start_scale` with a rotation prior and `start_scale_free_rotation`
    # without one, in every patch group; the other particle settings are the config's.
    import meridian_torch.matching.match as match_module

    seen = []
    original = match_module.sample_problem

    def spy(problem, cfg, seeds):
        seen.append(cfg)
        return original(problem, cfg, seeds)

    monkeypatch.setattr(match_module, "sample_problem", spy)
    ground, patches, _, _ = scene()
    particles = CFG.particles.model_copy(update={"start_scale": 0.5, "start_scale_free_rotation": 3.0})
    cfg = CFG.model_copy(update={"particles": particles, "patch_chunk": 2})
    for prior, want in ((YAW, 0.5), (None, 3.0)):
        seen.clear()
        match_submap(ground, stack_primitive_sets(patches), rotation_prior=prior, config=cfg)
        assert len(seen) == 2 and all(c.start_scale == want for c in seen)
        assert all(c.model_dump(exclude={"start_scale"}) == particles.model_dump(exclude={"start_scale"}) for c in seen)


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
    check_top(hyp, len(patches[0].points_xy), kp, kl)  # aerial lines count from patch 0's own points
    assert int(hyp.valid[0].sum()) == 1  # one CLIPPER set per patch


def _arrays(ps: PrimitiveSet) -> tuple:
    return (ps.points_xy.numpy(), ps.point_descriptors.numpy(), ps.line_endpoints.numpy(), ps.line_kinds.numpy(),
            ps.line_descriptors.numpy())


SMALL = MatchConfig(associations=AssociationConfig(k_prim=3), particles=ParticleConfig(n_particles=8, n_iterations=20))


def test_match_arrays_numpy_equals_torch_and_empty_inputs() -> None:
    torch.set_num_threads(1)
    ground, patches, _, _ = scene()
    g = _arrays(ground)
    aerial = [list(x) for x in zip(*[_arrays(p) for p in patches[:2]])]
    a = match_arrays(*g, *aerial, config=SMALL, generator=torch.Generator().manual_seed(0))
    b = match_arrays(*[torch.as_tensor(x) for x in g], *[[torch.as_tensor(x) for x in f] for f in aerial],
                     config=SMALL, generator=torch.Generator().manual_seed(0))
    assert torch.equal(a.T_world_odom, b.T_world_odom) and torch.equal(a.probability, b.probability)
    empty = ([], [], [], [], [])
    D = g[1].shape[1]
    no_lines = (*g[:2], [], [], [])
    no_points = (np.zeros((0, 2)), np.zeros((0, D)), *g[2:])
    cases = [
        (no_lines, aerial),
        (no_points, aerial),
        (empty, aerial),
        (g, [list(x) + [y] for x, y in zip(aerial, empty)]),  # a third, empty patch
        (empty, [[y] for y in empty]),
    ]
    for ground_arrays, patches_arrays in cases:
        hyp = match_arrays(*ground_arrays, *patches_arrays, config=SMALL)
        P = len(patches_arrays[0])
        assert hyp.T_world_odom.shape == (P, 25, 3, 3) and hyp.probability.shape == (P, 25)
        assert torch.isfinite(hyp.T_world_odom[hyp.valid]).all()
        assert ((hyp.probability >= 0) & (hyp.probability <= 1)).all()
    # An empty patch, and a ground without primitives, never yield hypotheses.
    assert not match_arrays(*g, *[list(x) + [y] for x, y in zip(aerial, empty)], config=SMALL).valid[2].any()
    assert not match_arrays(*empty, *aerial, config=SMALL).valid.any()


@pytest.mark.parametrize(
    "position, value, message",
    [
        (0, np.zeros((3, 3)), "ground_points"),
        (1, np.zeros((14, 16, 1)), "ground_point_desc"),
        (2, np.zeros((10, 2)), "ground_lines"),
        (3, np.full(10, 7), "ground_line_kinds"),
        (3, np.zeros(4, dtype=np.int64), "ground_line_kinds"),
        (4, np.zeros((9, 16)), "ground_line_desc"),
        (5, [np.zeros((3, 2))], "aerial"),  # one patch where the other sequences have two
        (0, np.full((14, 2), np.nan), "ground_points"),
        (3, np.full(10, 0.5), "ground_line_kinds"),  # kinds are integers
        (6, [np.zeros((18, 8)), np.zeros((18, 16))], r"aerial_point_desc\[0\]"),  # D differs
    ],
)
def test_match_arrays_errors_name_the_argument(position: int, value: object, message: str) -> None:
    ground, patches, _, _ = scene()
    args = list(_arrays(ground)) + [list(x) for x in zip(*[_arrays(p) for p in patches[:2]])]
    args[position] = value
    with pytest.raises(ValueError, match=message):
        match_arrays(*args, config=SMALL)


def test_match_arrays_rejects_bad_patch_and_prior() -> None:
    ground, patches, _, _ = scene()
    g = _arrays(ground)
    aerial = [list(x) for x in zip(*[_arrays(p) for p in patches[:2]])]
    aerial[0][1] = np.zeros((5, 5))
    with pytest.raises(ValueError, match=r"aerial_points\[1\]"):
        match_arrays(*g, *aerial, config=SMALL)
    aerial = [list(x) for x in zip(*[_arrays(p) for p in patches[:2]])]
    with pytest.raises(ValueError, match="rotation_prior"):
        match_arrays(*g, *aerial, rotation_prior=[0.1, 0.2, 0.3], config=SMALL)
    with pytest.raises(ValueError, match="at least one aerial patch"):
        match_arrays(*g, [], [], [], [], [], config=SMALL)


def test_match_arrays_line_indices_count_from_each_patchs_own_points() -> None:
    # The true patch comes second and has fewer points than the first: its aerial line indices
    # in `pairs` must start at its own point count, not at the largest one in the batch.
    torch.set_num_threads(1)
    ground, patches, kp, kl = scene()
    crowded = patches[1]
    crowded = PrimitiveSet(torch.cat([crowded.points_xy] * 3), torch.cat([crowded.point_descriptors] * 3),
                           torch.arange(3 * len(crowded.points_xy)), crowded.line_endpoints, crowded.line_kinds,
                           crowded.line_descriptors, crowded.line_segment_ids)
    order = [crowded, patches[0]]
    hyp = match_arrays(*_arrays(ground), *[list(x) for x in zip(*[_arrays(p) for p in order])], config=CFG,
                       generator=torch.Generator().manual_seed(0))
    chosen = hyp.pairs[1][hyp.association_mask[1, 0]]
    n_points = len(patches[0].points_xy)
    lines = chosen[chosen[:, 0] >= 14]
    assert len(lines) >= 4 and bool((lines[:, 1] < n_points + len(patches[0].line_endpoints)).all())
    assert sum(int(a) - n_points == int(g) - 14 for g, a in lines.tolist()) >= 0.8 * len(lines)


def test_match_arrays_several_empty_patches() -> None:
    # patches without associations settle together in the sampler (this once crashed)
    ground, patches, _, _ = scene()
    empty = ([], [], [], [], [])
    hyp = match_arrays(*_arrays(ground), *[[x] * 9 for x in empty], config=SMALL)
    assert hyp.valid.shape == (9, 25) and not hyp.valid.any()


def _sized(ps: PrimitiveSet, n_points: int, n_lines: int) -> PrimitiveSet:
    return PrimitiveSet(ps.points_xy[:n_points], ps.point_descriptors[:n_points], torch.arange(n_points),
                        ps.line_endpoints[:n_lines], ps.line_kinds[:n_lines], ps.line_descriptors[:n_lines],
                        torch.arange(n_lines))


@pytest.mark.parametrize("prior", [None, YAW])
def test_patch_chunking_keeps_each_patchs_results(prior: float | None) -> None:
    # Chunks take patches by size and drop the padding none of their patches uses, so the
    # patches here differ in size, and some have no points or no lines. This checks the chunks'
    # bookkeeping: on real maps a patch's line-pair entries can round an ulp apart between
    # groups (README, Reproducibility), which this scene's values happen not to.
    torch.set_num_threads(1)
    ground, patches, _, _ = scene()
    batch = stack_primitive_sets([_sized(patches[1], 5, 0), patches[0], _sized(patches[2], 0, 3), patches[2],
                                  _sized(patches[1], 12, 9)])
    cfg = CFG.model_copy(update={"particles": ParticleConfig(n_particles=16, n_iterations=60, max_associations=24)})
    runs = [match_submap(ground, batch, rotation_prior=prior, config=cfg.model_copy(update={"patch_chunk": chunk}),
                         generator=torch.Generator().manual_seed(4)) for chunk in (1, 2, 8)]
    assert runs[0].valid[1].any() and not runs[0].valid.all()
    for other in runs[1:]:
        assert torch.equal(runs[0].valid, other.valid) and torch.equal(runs[0].association_mask, other.association_mask)
        assert torch.equal(runs[0].T_world_odom, other.T_world_odom)
        assert torch.equal(runs[0].probability, other.probability)
        assert torch.equal(runs[0].objective, other.objective)


@pytest.mark.parametrize("prior", [None, YAW])
def test_patch_groups_in_threads_give_the_results_of_one_thread(prior: float | None) -> None:
    # On the CPU the patch groups run side by side, one torch thread each; the thread count must
    # decide only where a group runs, never what it computes.
    ground, patches, _, _ = scene()
    _, other_patches, _, _ = scene(seed=3)
    batch = stack_primitive_sets(patches + other_patches + [_sized(patches[0], 6, 4)])
    cfg = CFG.model_copy(update={"particles": ParticleConfig(n_particles=16, n_iterations=60), "patch_chunk": 2})
    threads = torch.get_num_threads()
    try:
        runs = []
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            runs.append(match_submap(ground, batch, rotation_prior=prior, config=cfg,
                                     generator=torch.Generator().manual_seed(6)))
    finally:
        torch.set_num_threads(threads)
    assert runs[0].valid.any(dim=1).sum() >= 2
    for other in runs[1:]:
        for field in dataclasses.fields(other):
            assert torch.equal(getattr(runs[0], field.name), getattr(other, field.name)), field.name


def test_sub_stages_are_timed_when_recorded() -> None:
    from meridian_torch.core.timing import record_stages

    ground, patches, _, _ = scene()
    cfg = CFG.model_copy(update={"particles": ParticleConfig(n_particles=8, n_iterations=10), "patch_chunk": 2})
    with record_stages() as times:
        match_submap(ground, stack_primitive_sets(patches), config=cfg, generator=torch.Generator().manual_seed(0))
    assert set(times.seconds) == {"associations", "affinity", "pruning", "particles", "particles/langevin",
                                  "registration", "clustering", "verification"}
    groups = -(-len(patches) // 2)
    assert times.calls["affinity"] == times.calls["pruning"] == times.calls["particles"] == groups  # one per group
    # the Langevin loop is timed inside the sampler, once per group
    assert times.calls["particles/langevin"] == groups
    assert 0 < times.seconds["particles/langevin"] <= times.seconds["particles"]

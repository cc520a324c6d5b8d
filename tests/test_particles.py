"""Langevin inlier-set sampler: batched == per-patch loop, seeded reproducibility, planted set."""

from __future__ import annotations

import pytest
import torch

from meridian_torch.config.matching import ParticleConfig
from meridian_torch.matching.particle_problem import support_pruning
from meridian_torch.matching.particles import patch_seeds, sample_inlier_sets

CFG = ParticleConfig(n_particles=24, n_iterations=60)


def planted_problem(seed: int, m: int, n_in: int, weight: float = 0.9) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random weak affinities plus a planted clique of strongly consistent associations.

    Returns M (m, m), valid (m,), pairs (m, 2), planted (m,) bool. Association i pairs ground
    i // 3 with a random aerial index; the planted ones use distinct ground and aerial indices.
    """
    gen = torch.Generator().manual_seed(seed)
    upper = (torch.rand(m, m, generator=gen) < 0.15) * (0.2 + 0.3 * torch.rand(m, m, generator=gen))
    M = torch.triu(upper.double(), 1)
    planted = torch.zeros(m, dtype=torch.bool)
    planted[torch.randperm(m, generator=gen)[:n_in]] = True
    block = planted[:, None] & planted[None, :]
    M = torch.where(block, weight, M)
    M = torch.triu(M, 1)
    M = M + M.T
    M.fill_diagonal_(1.0)
    pairs = torch.stack([torch.arange(m) // 3, torch.randint(0, m, (m,), generator=gen)], -1)
    pairs[planted] = torch.stack([1000 + torch.arange(n_in), 1000 + torch.arange(n_in)], -1)
    # One-to-one conflicts are zero in an affinity.
    share = (pairs[:, None, 0] == pairs[None, :, 0]) | (pairs[:, None, 1] == pairs[None, :, 1])
    M = M.masked_fill(share & ~torch.eye(m, dtype=torch.bool), 0.0)
    return M, torch.ones(m, dtype=torch.bool), pairs, planted


def batch(problems: list[tuple[torch.Tensor, ...]]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    m = max(p[0].shape[0] for p in problems)
    M = torch.zeros(len(problems), m, m, dtype=torch.float64)
    valid = torch.zeros(len(problems), m, dtype=torch.bool)
    pairs = torch.full((len(problems), m, 2), -1, dtype=torch.int64)
    for k, (Mk, vk, pk, _) in enumerate(problems):
        n = Mk.shape[0]
        M[k, :n, :n], valid[k, :n], pairs[k, :n] = Mk, vk, pk
    return M, valid, pairs


def test_batched_equals_per_patch_loop() -> None:
    torch.set_num_threads(1)
    M, valid, pairs = batch([planted_problem(0, 60, 8), planted_problem(1, 45, 6), planted_problem(2, 70, 10)])
    seeds = patch_seeds(3, torch.Generator().manual_seed(7))
    batched = sample_inlier_sets(M, valid, pairs, CFG, seeds=seeds)
    same_gen = sample_inlier_sets(M, valid, pairs, CFG, torch.Generator().manual_seed(7))
    assert torch.equal(batched.masks, same_gen.masks)
    for p in range(3):
        n = int(valid[p].sum())
        # The loop reference sees the patch alone and unpadded: results must not depend on either.
        single = sample_inlier_sets(M[p : p + 1, :n, :n], valid[p : p + 1, :n], pairs[p : p + 1, :n], CFG, seeds=seeds[p : p + 1])
        s = int(single.valid.sum())
        assert int(batched.valid[p].sum()) == s
        assert torch.equal(batched.masks[p, :s, :n], single.masks[0, :s])
        assert not batched.masks[p, :s, n:].any()
        assert torch.equal(batched.counts[p, :s], single.counts[0, :s])
        torch.testing.assert_close(batched.objective[p, :s], single.objective[0, :s])
        assert int(batched.iterations[p]) == int(single.iterations[0])


def test_seeded_runs_identical_and_seeds_matter() -> None:
    M, valid, pairs = batch([planted_problem(3, 50, 7), planted_problem(4, 50, 7)])
    a = sample_inlier_sets(M, valid, pairs, CFG, torch.Generator().manual_seed(1))
    b = sample_inlier_sets(M, valid, pairs, CFG, torch.Generator().manual_seed(1))
    c = sample_inlier_sets(M, valid, pairs, CFG, torch.Generator().manual_seed(2))
    for field in ("masks", "counts", "objective", "valid", "iterations"):
        assert torch.equal(getattr(a, field), getattr(b, field))
    assert not (a.masks.shape == c.masks.shape and torch.equal(a.masks, c.masks) and torch.equal(a.counts, c.counts))


@pytest.mark.parametrize("rounding", ["clipper", "support"])
def test_planted_set_is_top_and_output_invariants(rounding: str) -> None:
    # round(x'Mx) undercounts weighted cliques, so the reference rounding gets unit weights.
    weight = 1.0 if rounding == "clipper" else 0.9
    problems = [planted_problem(5, 80, 10, weight), planted_problem(6, 60, 8, weight)]
    M, valid, pairs = batch(problems)
    cfg = ParticleConfig(n_particles=32, n_iterations=100, rounding=rounding)
    sets = sample_inlier_sets(M, valid, pairs, cfg, torch.Generator().manual_seed(0))
    for p, (_, _, _, planted) in enumerate(problems):
        n = planted.shape[0]
        assert torch.equal(sets.masks[p, 0, :n], planted)
        v = sets.valid[p]
        # Sorted by J, unique, one-to-one, at least 3 associations, counts within the particle budget.
        assert torch.all(sets.objective[p, v][:-1] >= sets.objective[p, v][1:])
        assert (sets.masks[p, v].sum(-1) >= 3).all()
        assert int(sets.counts[p].sum()) <= sets.n_particles
        assert (sets.counts[p, v] > 0).all() and (sets.counts[p, ~v] == 0).all()
        flat = sets.masks[p, v]
        assert torch.unique(flat, dim=0).shape[0] == flat.shape[0]
        for mask in flat:
            chosen = pairs[p, mask]
            assert torch.unique(chosen[:, 0]).numel() == chosen.shape[0]
            assert torch.unique(chosen[:, 1]).numel() == chosen.shape[0]
        J = (flat.double() @ M[p] * flat.double()).sum(-1) / flat.sum(-1)
        torch.testing.assert_close(sets.objective[p, v], J)


def test_support_pruning_equals_dense_reference() -> None:
    problems = [planted_problem(8, 40, 6), planted_problem(9, 30, 5)]
    M, valid, pairs = batch(problems)
    valid[1, 25:] = False  # padding inside the second patch
    k = 12
    M_kept, kept_valid, pairs_kept, index = support_pruning(M.to_sparse(), valid, pairs, k)
    for p in range(2):
        n = int(valid[p].sum())
        A = M[p, :n, :n] - torch.eye(n, dtype=M.dtype)  # obvious reference: dense walk counts
        walk = A @ (A @ torch.ones(n, dtype=M.dtype))
        degree = A.sum(1)
        score = walk.masked_fill(degree <= 0, float("-inf"))
        expected = torch.sort(torch.sort(score, descending=True, stable=True).indices[:k]).values
        assert torch.equal(index[p][kept_valid[p]], expected[torch.isfinite(score[expected])])
        sel = index[p][kept_valid[p]]
        dense = M_kept.to_dense()[p][kept_valid[p]][:, kept_valid[p]]
        torch.testing.assert_close(dense, M[p][sel][:, sel])
        assert torch.equal(pairs_kept[p][kept_valid[p]], pairs[p][sel])


def test_pruned_sampler_batched_equals_loop_and_finds_planted() -> None:
    torch.set_num_threads(1)
    problems = [planted_problem(10, 70, 9, 1.0), planted_problem(11, 50, 7, 1.0)]
    M, valid, pairs = batch(problems)
    cfg = ParticleConfig(n_particles=24, n_iterations=60, max_associations=20)
    seeds = patch_seeds(2, torch.Generator().manual_seed(3))
    batched = sample_inlier_sets(M, valid, pairs, cfg, seeds=seeds)
    for p, (_, _, _, planted) in enumerate(problems):
        n = planted.shape[0]
        single = sample_inlier_sets(M[p : p + 1, :n, :n], valid[p : p + 1, :n], pairs[p : p + 1, :n], cfg, seeds=seeds[p : p + 1])
        s = int(single.valid.sum())
        assert torch.equal(batched.masks[p, :s, :n], single.masks[0, :s])
        assert torch.equal(batched.counts[p, :s], single.counts[0, :s])
        # Masks are reported over all m associations; the planted clique survives the pruning.
        assert torch.equal(batched.masks[p, 0, :n], planted)
        J = (batched.masks[p, 0].double() @ M[p] * batched.masks[p, 0].double()).sum() / planted.sum()
        torch.testing.assert_close(batched.objective[p, 0], J)


def test_patches_stopping_at_the_same_check_keep_their_results() -> None:
    # Identical problems with identical seeds settle at the same early-stop check; the loop
    # must then end with every patch's result in place (it once crashed on this).
    cfg = ParticleConfig(n_particles=24, n_iterations=200, noise=False)  # noise-free ascent settles early
    problem = planted_problem(5, 40, 6)
    M, valid, pairs = batch([problem, problem, problem])
    seeds = torch.full((3,), 11, dtype=torch.int64)
    out = sample_inlier_sets(M, valid, pairs, cfg, seeds=seeds)
    single = sample_inlier_sets(M[:1], valid[:1], pairs[:1], cfg, seeds=seeds[:1])
    assert int(single.iterations[0]) < cfg.n_iterations  # the early stop did happen
    for p in range(3):
        assert torch.equal(out.masks[p], single.masks[0]) and torch.equal(out.counts[p], single.counts[0])
    # patches without any association stop together too
    empty = sample_inlier_sets(torch.zeros(2, 0, 0), torch.zeros(2, 0, dtype=torch.bool),
                               torch.zeros(2, 0, 2, dtype=torch.int64), cfg)
    assert not empty.valid.any()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("options", [
    {"early_stop": False}, {"early_stop": False, "rmsprop": False}, {"early_stop": False, "anneal": False},
    {"noise": False, "n_iterations": 200},  # noise-free ascent settles: the early stop is exercised
    {"early_stop": False, "start_scale": 2.0},  # a start above 1 survives the first step in part
])
def test_compiled_dynamics_follow_the_torch_loop(dtype: torch.dtype, options: dict) -> None:
    # CPU tensors run the compiled Langevin loop, other devices torch's: the same dynamics and
    # noise, rounded in another order, so the particles agree to rounding, steps included.
    from meridian_torch.matching.particle_problem import _upper_entries
    from meridian_torch.matching.particles import _block_rows, _penalised, _run_dynamics

    cfg = ParticleConfig(**{"n_particles": 40, "n_iterations": 60, **options})
    M, valid, pairs = batch([planted_problem(30, 50, 7), planted_problem(31, 35, 6), planted_problem(32, 8, 4)])
    M = M.to(dtype)
    d = valid.to(dtype).sum(-1)
    A = _penalised(_block_rows(_upper_entries(M, valid)), d)
    seeds = patch_seeds(3, torch.Generator().manual_seed(7))
    x_compiled, steps_compiled = _run_dynamics(A, d, valid, cfg, seeds, compiled=True)
    x_torch, steps_torch = _run_dynamics(A, d, valid, cfg, seeds, compiled=False)
    assert torch.equal(steps_compiled, steps_torch)
    if cfg.early_stop:
        assert int(steps_torch.max()) < cfg.n_iterations
    assert x_torch.abs().amax() > 0.1 and not x_torch[~valid].any() and not x_compiled[~valid].any()
    tolerance = 1e-4 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(x_compiled, x_torch, rtol=0.0, atol=tolerance)


def test_mix_is_the_splitmix64_finaliser() -> None:
    # The sampler's random words: the compiled hash against the finaliser in Python integers.
    from meridian_torch.matching.particle_noise import mix

    def reference(value: int) -> int:
        z = value % 2**64
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) % 2**64
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) % 2**64
        z ^= z >> 31
        return z - 2**64 if z >= 2**63 else z

    words = torch.randint(-(1 << 63), (1 << 63) - 1, (6, 5), generator=torch.Generator().manual_seed(2))
    words[0, :4] = torch.tensor([0, 1, -1, -(1 << 63)])
    mixed = mix(words)
    assert mixed.shape == words.shape and mixed.dtype == torch.int64
    assert mixed.flatten().tolist() == [reference(v) for v in words.flatten().tolist()]
    assert mix(words[:, 1]).tolist() == mixed[:, 1].tolist()  # strided input


@pytest.mark.parametrize("support", [False, True])
def test_compiled_rounding_equals_the_torch_sort(support: bool) -> None:
    # CPU tensors round particles with a compiled selection, other devices with torch's stable
    # sort: the same sets, sizes and one-to-one flags, also with exact zeros and tied values.
    from meridian_torch.matching.particles import _select_sets

    gen = torch.Generator().manual_seed(4)
    _, valid, pairs = batch([planted_problem(40, 30, 6), planted_problem(41, 22, 5), planted_problem(42, 12, 4)])
    valid[1, 3] = False
    x = torch.rand(3, 30, 64, generator=gen)
    x[torch.rand(x.shape, generator=gen) < 0.7] = 0.0  # settled particles are mostly zeros
    x[:, :, :16] = torch.tensor([0.0, 0.25, 0.5])[torch.randint(0, 3, (3, 30, 16), generator=gen)]  # ties
    x = x * valid[:, :, None]
    n_valid = valid.sum(1, keepdim=True)
    k = (torch.rand(3, 64, generator=gen) * (n_valid + 1)).long().clamp(max=n_valid)
    compiled = _select_sets(x, k, valid, pairs, support, compiled=True)
    reference = _select_sets(x, k, valid, pairs, support, compiled=False)
    for got, want in zip(compiled, reference):
        assert torch.equal(got, want)
    masks, size, one_to_one = reference
    assert not (masks & ~valid[:, None, :]).any()
    assert (size > 3).any() and (~one_to_one).any() and one_to_one.any()  # the cases are exercised


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_uniform_takes_the_top_53_bits(dtype: torch.dtype) -> None:
    from meridian_torch.matching.particle_noise import uniform

    words = torch.randint(-(1 << 63), (1 << 63) - 1, (7, 4), generator=torch.Generator().manual_seed(5))
    words[0, :3] = torch.tensor([0, -1, 1 << 11])
    expected = torch.tensor([((v % 2**64) >> 11) * 2.0**-53 for v in words.flatten().tolist()], dtype=torch.float64)
    got = uniform(words, dtype)
    assert got.dtype == dtype and torch.equal(got.flatten(), expected.to(dtype))
    assert got.min() >= 0 and got.max() <= 1 and got[0, 0] == 0 and got[0, 2] == 2.0**-53  # float32 may round up to 1

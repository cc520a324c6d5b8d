"""Compiled passes of the sampler problem and the particles' bookkeeping against the torch
expressions they replace: the same numbers, bit for bit."""

from __future__ import annotations

import pytest
import torch

from meridian_torch.matching.affinity import AffinityEntries
from meridian_torch.matching.particle_problem import _prune


def random_entries(seed: int, n_patches: int, m: int, fill: float, dtype: torch.dtype) -> tuple[AffinityEntries, torch.Tensor]:
    """Random strict upper-triangle entries in a shuffled order (as the affinity emits them,
    not sorted), valid masks with padding, and pairs."""
    gen = torch.Generator().manual_seed(seed)
    upper = (torch.rand(n_patches, m, m, generator=gen) < fill).triu(1)
    index = upper.nonzero()
    index = index[torch.randperm(len(index), generator=gen)]
    value = (0.05 + torch.rand(len(index), generator=gen, dtype=torch.float64)).clamp_max(1.0).to(dtype)
    value[::2] = 0.5  # repeated values: tied walk counts
    valid = torch.rand(n_patches, m, generator=gen) < 0.9
    if n_patches and m:
        valid[0, m // 2 :] = False  # a padded tail
    pairs = torch.randint(0, 50, (n_patches, m, 2), generator=gen)
    return AffinityEntries(index, value, valid), pairs


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(("n_patches", "m", "fill", "k"), [
    (3, 60, 0.2, 12), (2, 40, 0.02, 25), (4, 30, 0.5, 100), (2, 0, 0.0, 5), (3, 25, 0.0, 4), (1, 1, 0.0, 1),
])
def test_compiled_pruning_equals_the_torch_passes(dtype: torch.dtype, n_patches: int, m: int, fill: float, k: int) -> None:
    # CPU tensors prune with compiled walks over the entries, other devices with index_add_:
    # the same scores, kept associations and renumbered entries in the same order.
    entries, pairs = random_entries(m + n_patches, n_patches, m, fill, dtype)
    got = _prune(entries, entries.valid, pairs, k, compiled=True)
    want = _prune(entries, entries.valid, pairs, k, compiled=False)
    for a, b in [(got.entries.index, want.entries.index), (got.entries.value, want.entries.value),
                 (got.entries.valid, want.entries.valid), (got.pairs, want.pairs), (got.index, want.index)]:
        assert a.dtype == b.dtype and torch.equal(a, b)
    assert got.m == want.m == m
    if fill >= 0.2:  # the cases are exercised: entries kept, and some dropped
        assert 0 < len(got.entries.value) < len(entries.value)


@pytest.mark.parametrize(("n_patches", "n_particles", "m"), [(3, 64, 30), (2, 40, 130), (2, 0, 10), (0, 8, 5), (2, 8, 0)])
def test_compiled_merge_equals_the_torch_sorts(n_patches: int, n_particles: int, m: int) -> None:
    # CPU tensors merge identical sets in a compiled pass, other devices with torch's sorts: the
    # same order, sorted masks, firsts and counts, with repeated sets and rejected copies.
    from meridian_torch.matching.particles import _merge

    gen = torch.Generator().manual_seed(n_particles + m)
    distinct = torch.rand(n_patches, 6, m, generator=gen) < 0.2
    masks = distinct.gather(1, torch.randint(0, 6, (n_patches, n_particles, 1), generator=gen).expand(-1, -1, m))
    keep = torch.rand(n_patches, n_particles, generator=gen) < 0.8
    got = _merge(masks, keep, compiled=True)
    want = _merge(masks, keep, compiled=False)
    for a, b in zip(got, want):
        assert a.dtype == b.dtype and torch.equal(a, b)
    if n_patches and n_particles:
        assert (want[3] > 1).any() and int(want[3].sum()) == int(keep.sum())


def test_compiled_merge_never_merges_colliding_keys() -> None:
    # With unit hash weights every two sets of a size collide: the kernel against the plain
    # definition (kept first, by signed key, then particle; runs of equal kept sets).
    from meridian_torch.matching.kernels import merge_sets

    gen = torch.Generator().manual_seed(9)
    masks = torch.rand(2, 50, 8, generator=gen) < 0.3
    masks[:, 25:] = masks[:, :25]  # repeats
    keep = torch.rand(2, 50, generator=gen) < 0.8
    weights = torch.full((8,), 1 << 62)  # keys 0, 2^62, -2^63, -2^62: wrapping and signed order
    order, masks_s, first, counts = (torch.from_numpy(a) for a in merge_sets(masks.numpy(), keep.numpy(), weights.numpy()))
    for p in range(2):
        key = [(int(masks[p, n].sum()) * (1 << 62) + (1 << 63)) % (1 << 64) - (1 << 63) for n in range(50)]
        expected = sorted(range(50), key=lambda n: (not bool(keep[p, n]), key[n], n))
        assert order[p].tolist() == expected
        assert torch.equal(masks_s[p], masks[p, expected])
        runs: list[int] = []
        for j, n in enumerate(expected):
            if not keep[p, n]:
                continue
            if j and torch.equal(masks[p, n], masks[p, expected[j - 1]]) and keep[p, expected[j - 1]]:
                runs[-1] += 1
            else:
                runs.append(1)
        assert counts[p][first[p]].tolist() == runs and int(counts[p][~first[p]].abs().sum()) == 0
    assert len(set(key)) < len(runs)  # colliding keys of different sets were kept apart


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(("n_patches", "m", "fill"), [(3, 40, 0.2), (2, 25, 0.6), (2, 0, 0.0), (0, 5, 0.0), (3, 6, 0.0)])
def test_compiled_block_rows_equal_the_coalesced_matrix(dtype: torch.dtype, n_patches: int, m: int, fill: float) -> None:
    # CPU tensors sort the entries into CSR rows in a compiled pass, other devices go through
    # the coalesced COO: the same rows, columns, patches and values, and the same matrix.
    from meridian_torch.matching.particles import _block_rows

    entries, _ = random_entries(7 * m + n_patches, n_patches, m, fill, dtype)
    got = _block_rows(entries, compiled=True)
    want = _block_rows(entries, compiled=False)
    for name in ("crow", "batch", "row", "col", "value"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and torch.equal(a, b), name
    assert got.m == want.m == m
    dense = torch.zeros(n_patches, m, m, dtype=dtype)
    dense[got.batch, got.row, got.col] = got.value
    assert torch.equal(dense, entries.to_sparse().to_dense())
    if n_patches and m:
        assert torch.equal(got.csr().to_dense(), torch.block_diag(*dense))


def test_compiled_words_noise_and_start_equal_the_torch_expressions() -> None:
    # The particles' words, noise scales and start, each built in one compiled pass, against
    # the torch expressions they replace.
    from meridian_torch.matching.particle_noise import (
        _GOLDEN,
        _TABLE_SIZE,
        ROW,
        initial_positions,
        mix,
        row_words,
        srl,
        step_noise,
        step_words,
        uniform,
        wrap64,
    )

    seeds = torch.tensor([0, 1, -1, 5, (1 << 62) - 1, -(1 << 63)])
    steps = [-1, 0, 1, 7, 99]
    keys = torch.tensor([wrap64((step + 2) * _GOLDEN) for step in steps])
    base = mix(seeds[None, :] + keys[:, None])
    for n in (0, 1, 5, 64):
        assert torch.equal(step_words(seeds, steps, n), mix(base[..., None] + torch.arange(n) * ROW))
    for dtype in (torch.float32, torch.float64):
        sigmas = [1.0, 0.7, 1.0 / 3.0, 0.0]  # the last step of an annealed schedule has no noise
        offsets, scale = step_noise(seeds, sigmas, 9, dtype)
        words = step_words(seeds, list(range(len(sigmas))), 9)
        assert torch.equal(offsets, srl(words[..., 0], 1) % _TABLE_SIZE)
        want = torch.tensor(sigmas, dtype=dtype)[:, None, None] * (1.0 - 2.0 * (words & 1).to(dtype))
        assert scale.dtype == dtype and torch.equal(scale, want)
        assert torch.equal(scale.signbit(), want.signbit())  # -0.0 where a zero sigma is negated
        validf = (torch.rand(6, 11, generator=torch.Generator().manual_seed(1)) < 0.7).to(dtype)
        x = initial_positions(seeds, validf, 13)
        coord_keys = mix(torch.arange(11) + ROW)
        expected = uniform(mix(row_words(seeds, -1, 13)[:, None, :] ^ coord_keys[None, :, None]), dtype) * validf[:, :, None]
        assert x.dtype == dtype and torch.equal(x, expected)
        assert initial_positions(seeds, validf[:, :0], 13).shape == (6, 0, 13)

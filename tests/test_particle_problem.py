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
    valid = torch.rand(n_patches, m, generator=gen) < 0.9
    if m:
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

"""Greedy clustering of inlier sets: the compiled walk, torch's fixed-point sweeps and the plain
definition pick the same representatives."""

from __future__ import annotations

import pytest
import torch

from meridian_torch.matching.hypotheses import _greedy_representatives


@pytest.mark.parametrize("seed", range(4))
def test_greedy_representatives_three_ways(seed: int) -> None:
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
    compiled = _greedy_representatives(close, valid, compiled=True)
    swept = _greedy_representatives(close, valid, compiled=False)
    assert torch.equal(compiled, expected) and torch.equal(swept, expected)
    assert expected.any() and (valid & ~expected).any()  # both outcomes occur

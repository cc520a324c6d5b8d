"""The shared float-comparison helper: it accepts reassociated sums and rejects real differences."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from numerics import assert_close_reassociated, reassociation_tolerance


@given(n=st.integers(1, 20_000), seed=st.integers(0, 2**31 - 1))
def test_sums_in_another_order_are_within_the_tolerance(n: int, seed: int) -> None:
    x = torch.rand(n, generator=torch.Generator().manual_seed(seed), dtype=torch.float32)
    forward = torch.zeros((), dtype=torch.float32)
    for chunk in x.split(97):  # blocked, left to right
        forward = forward + chunk.sum()
    backward = x.flip(0).cumsum(0)[-1]  # sequential, right to left
    mean_f, mean_b = forward / n, backward / n
    assert_close_reassociated(mean_f, mean_b, n_terms=n, magnitude=1.0)


def test_a_real_difference_is_rejected_and_non_finite_entries_must_match() -> None:
    expected = torch.tensor([0.5, 0.25, float("nan")])
    tol = reassociation_tolerance(torch.float32, 1000, 0.5)
    assert_close_reassociated(expected + torch.tensor([tol / 2, 0.0, 0.0]), expected, n_terms=1000)
    with pytest.raises(AssertionError, match="exceeds"):
        assert_close_reassociated(expected + torch.tensor([4 * tol, 0.0, 0.0]), expected, n_terms=1000)
    with pytest.raises(AssertionError, match="non-finite"):
        assert_close_reassociated(torch.tensor([0.5, 0.25, 0.0]), expected, n_terms=1000)
    with pytest.raises(AssertionError, match="dtype/shape"):
        assert_close_reassociated(expected.double(), expected, n_terms=1000)

"""`core.dense_ranks` against np.unique's inverse."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.core.dense_ranks import dense_ranks


@settings(max_examples=120, deadline=None)
@given(
    keys=st.lists(st.integers(-(2**40), 2**40), max_size=200), repeat=st.integers(1, 4),
    span=st.sampled_from([None, 3, 50, 2**62]),
)
def test_dense_ranks_are_numpys_unique_inverse(keys: list[int], repeat: int, span: int | None):
    """Wide keys (sorted) and keys within a few times their count (ranked through a table), up to
    spans past 2**63."""
    if span is not None:  # keys in [-span, span]
        keys = [k % (2 * span + 1) - span for k in keys]
    key = np.array(keys * repeat, dtype=np.int64)  # repeated keys: equal ranks
    uniq, inverse = np.unique(key, return_inverse=True)
    rank, n_distinct = dense_ranks(key)
    assert n_distinct == len(uniq)
    assert np.array_equal(rank, inverse.ravel())


def test_keys_at_the_int64_extremes_are_sorted_not_tabled():
    """A span past 2**63 wraps negative in int64: such keys take the sort, not a huge table."""
    key = np.array([2**63 - 1, -(2**63), 0, 2**63 - 1], dtype=np.int64)
    rank, n_distinct = dense_ranks(key)
    assert n_distinct == 3 and rank.tolist() == [2, 0, 1, 2]

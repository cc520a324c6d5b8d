"""`core.dense_ranks` against np.unique's inverse."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.core.dense_ranks import dense_ranks


@settings(max_examples=60, deadline=None)
@given(keys=st.lists(st.integers(-(2**40), 2**40), max_size=200), repeat=st.integers(1, 4))
def test_dense_ranks_are_numpys_unique_inverse(keys: list[int], repeat: int):
    key = np.array(keys * repeat, dtype=np.int64)  # repeated keys: equal ranks
    uniq, inverse = np.unique(key, return_inverse=True)
    rank, n_distinct = dense_ranks(key)
    assert n_distinct == len(uniq)
    assert np.array_equal(rank, inverse.ravel())

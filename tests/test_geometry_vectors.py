"""The written-out 2-vector products round exactly as torch's reductions they replace, so the
matching code that switched to them gives bitwise the same results."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from meridian_torch.geometry.vectors import cross2, dot2, squared_norm2

vectors = arrays(np.float64, (3, 5, 2), elements=st.floats(-1e6, 1e6, allow_nan=False, width=32))


@settings(max_examples=60, deadline=None)
@given(vectors, vectors, st.sampled_from([torch.float32, torch.float64]))
def test_products_equal_the_reductions(x_np: np.ndarray, y_np: np.ndarray, dtype: torch.dtype) -> None:
    x, y = torch.from_numpy(x_np).to(dtype), torch.from_numpy(y_np).to(dtype)
    assert torch.equal(dot2(x, y), (x * y).sum(-1))
    assert torch.equal(squared_norm2(x), x.square().sum(-1))
    assert torch.equal(cross2(x, x), torch.zeros_like(x[..., 0]))
    # the cross product is the dot product with y turned by +90 degrees
    assert torch.equal(cross2(x, y), dot2(x, torch.stack([y[..., 1], -y[..., 0]], -1)))

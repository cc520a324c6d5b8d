"""The suite's numerical policy in one place (README, "Reproducibility and numerics").

Two kinds of agreement are asserted:
- **bitwise** (`torch.equal`): the same computation on the same inputs, seed, machine, thread
  count and library versions; and results the design computes item by item (per patch, per
  frame, per particle set) where batching or chunking only decides which items travel
  together, with no reduction across them;
- **to a float tolerance** (`assert_close_reassociated`): the same mathematics evaluated with
  sums in another order: a batched BLAS / oneDNN kernel whose blocking depends on the batch
  shape, another thread count, onnxruntime instead of torch, another process. Such results
  differ by rounding alone, so the tolerance is derived from the dtype and the length of the
  longest reduction, never picked to make a test pass.

The tolerance: summing n terms of magnitude at most `magnitude` in two different orders, each
rounding error is at most u * |partial sum| (u = unit roundoff: 2^-24 for float32, 2^-53 for
float64) and the errors behave like independent zero-mean variables, so the difference stays
below lambda * sqrt(n) * u * n_magnitude with overwhelming probability (Higham and Mary, "A new
approach to probabilistic rounding error analysis", SIAM J. Sci. Comput. 2019). For a mean (or a
sum normalized afterwards) the magnitude is that of the terms. We take lambda = 8 and count every
reduction a value passes through.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["UNIT_ROUNDOFF", "reassociation_tolerance", "assert_close_reassociated"]

UNIT_ROUNDOFF = {torch.float16: 2.0**-11, torch.bfloat16: 2.0**-8, torch.float32: 2.0**-24, torch.float64: 2.0**-53}
_LAMBDA = 8.0


def reassociation_tolerance(dtype: torch.dtype, n_terms: int, magnitude: float = 1.0) -> float:
    """Largest difference expected between two summation orders of `n_terms` terms of size `magnitude`."""
    if n_terms < 1 or not magnitude > 0:
        raise ValueError(f"n_terms must be >= 1 and magnitude > 0, got {n_terms} and {magnitude}")
    return _LAMBDA * math.sqrt(n_terms) * UNIT_ROUNDOFF[dtype] * magnitude


def _tensor(x) -> torch.Tensor:
    return x if torch.is_tensor(x) else torch.from_numpy(np.asarray(x))


def assert_close_reassociated(actual, expected, *, n_terms: int, magnitude: float | None = None) -> None:
    """`actual` equals `expected` up to the rounding of reductions over `n_terms` terms.

    `magnitude` defaults to the largest absolute value of `expected` (at least the smallest
    normal number). Shapes, dtypes and non-finite entries must agree exactly.
    """
    actual, expected = _tensor(actual), _tensor(expected)
    if actual.dtype != expected.dtype or actual.shape != expected.shape:
        raise AssertionError(f"dtype/shape differ: {actual.dtype} {tuple(actual.shape)} vs "
                             f"{expected.dtype} {tuple(expected.shape)}")
    finite = torch.isfinite(expected)
    odd_a, odd_e = actual[~finite], expected[~finite]
    if not torch.equal(finite, torch.isfinite(actual)) or not bool(
        ((odd_a == odd_e) | (odd_a.isnan() & odd_e.isnan())).all()
    ):
        raise AssertionError("non-finite entries differ")
    if magnitude is None:
        magnitude = max(float(expected[finite].abs().max()) if finite.any() else 0.0, torch.finfo(expected.dtype).tiny)
    tol = reassociation_tolerance(expected.dtype, n_terms, magnitude)
    diff = float((actual[finite] - expected[finite]).abs().max()) if finite.any() else 0.0
    if diff > tol:
        raise AssertionError(f"max difference {diff:.3g} exceeds the reassociation tolerance {tol:.3g} "
                             f"({expected.dtype}, {n_terms} terms, magnitude {magnitude:.3g})")

"""The output of the CLIPPER solvers: `ClipperResult`, its assembly from the solve state, the
result of empty problems, and the density of a selected set."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from meridian_torch.matching.clipper.ascent import _affinity_mv, _SolveState

__all__ = ["ClipperResult", "inlier_indices"]


@dataclass(frozen=True)
class ClipperResult:
    """Output of `solve_clipper`; every field is batched over the B problems.

    Attributes:
        inliers: (B, n) bool, the selected associations; always a clique of the constraint
            matrix C and never a padded entry.
        u: (B, n) the final continuous iterate, nonnegative with unit norm (all zero for an empty
            problem); exact zeros mark associations the solver pushed out.
        score: (B,) weighted density of the selected set, x'Mx / x'x for its indicator x, with the
            diagonal CLIPPER used (ones by default). A k-clique of unit affinities scores k; an
            empty set scores 0. Comparable across roundings and problems (ROMAN ranks sets by it).
        objective: (B,) the continuous objective u'(M - d Cb)u at the final penalty d
            (the reference's `score`); equals u'Mu when the solve converged.
        iterations: (B,) int64, projected-gradient steps taken.
        penalty_updates: (B,) int64, increases of the penalty weight d (the reference's `ifinal`).
        converged: (B,) bool, the support of u satisfied all constraints before the outer
            iteration cap.
    """

    inliers: Tensor
    u: Tensor
    score: Tensor
    objective: Tensor
    iterations: Tensor
    penalty_updates: Tensor
    converged: Tensor


def inlier_indices(result: ClipperResult, b: int = 0) -> Tensor:
    """Indices (int64, ascending) of the associations selected in problem `b` of a result."""
    return torch.nonzero(result.inliers[b], as_tuple=False).flatten()


def _density(M: Tensor, diag: Tensor, chosen: Tensor) -> Tensor:
    """(B,) x'Ax / x'x of the chosen sets (A = M with diagonal `diag`); 0 for an empty set."""
    x = chosen.to(M.dtype)
    return (x * _affinity_mv(M, diag, x)).sum(-1) / x.sum(-1).clamp_min(1)


def _result(state: _SolveState, inliers: Tensor, score: Tensor) -> ClipperResult:
    return ClipperResult(
        inliers=inliers,
        u=state.u,
        score=score,
        objective=state.objective,
        iterations=state.iterations,
        penalty_updates=state.penalty_updates,
        converged=state.converged,
    )


def _empty_result(B: int, n: int, dtype: torch.dtype, device: torch.device) -> ClipperResult:
    """The result of problems without associations: nothing selected, nothing iterated."""
    zeros_i = torch.zeros(B, dtype=torch.int64, device=device)
    return ClipperResult(
        inliers=torch.zeros((B, n), dtype=torch.bool, device=device),
        u=torch.zeros((B, n), dtype=dtype, device=device),
        score=torch.zeros(B, dtype=dtype, device=device),
        objective=torch.zeros(B, dtype=dtype, device=device),
        iterations=zeros_i,
        penalty_updates=zeros_i.clone(),
        converged=torch.ones(B, dtype=torch.bool, device=device),
    )

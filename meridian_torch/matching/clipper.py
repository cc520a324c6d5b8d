"""Batched CLIPPER: the densest consistent set of associations in a weighted consistency graph.

`solve_clipper` re-implements the projected-gradient / penalty-homotopy solver of CLIPPER
(Lusk et al., v0.2.4) over a batch of dense, padded problems, plus three roundings of the
continuous solution to a set of inliers. Every returned set is a clique of the constraint
graph. Only torch is needed for the solve; the exact "densest" rounding imports scipy lazily.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from meridian_torch.config.matching import ClipperConfig

__all__ = ["ClipperResult", "Edges", "dense_block", "inlier_indices", "restrict_edges", "solve_clipper",
           "solve_clipper_sparse"]

# Tolerances below this many machine epsilons (times sqrt(n) and the objective's scale) cannot be
# met in float32, where the reference's 1e-9 would make every inner loop run to its cap.
_NOISE_EPS_FACTOR = 8.0
# Two candidate densities closer than this (relative) are a tie, resolved towards the larger set.
_DENSITY_TIE_RTOL = 1e-9


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


@torch.no_grad()
def solve_clipper(
    M: Tensor,
    C: Tensor | None = None,
    *,
    valid: Tensor | None = None,
    u0: Tensor | None = None,
    generator: torch.Generator | None = None,
    cfg: ClipperConfig | None = None,
) -> ClipperResult:
    """Find the densest set of mutually consistent associations, for B problems at once.

    CLIPPER relaxes "pick the clique S of the constraint graph maximising x'Mx / x'x" to
    maximising u'(M - d Cb)u over the nonnegative unit sphere, where Cb = 1 - C marks forbidden
    pairs. Projected gradient ascent with backtracking runs for a fixed penalty d; d then grows
    until the support of u contains no forbidden pair. All problems advance in one loop; the ones
    that finish drop out of the working batch. The continuous u is then rounded
    (`cfg.rounding`) and repaired greedily (by decreasing u) into a clique of C if needed:

    - ``"clipper"``: the round(F) largest entries of u, F the final objective (the reference's
      default DSD_HEU). F is the weighted clique size, so it drops members of weighted cliques.
    - ``"support"``: {i : u_i > support_threshold * max(u)}; with threshold 0 this is the
      reference's NONZERO rounding.
    - ``"densest"``: the exact maximiser of x'Mx / x'x over subsets of the support (the
      reference's DSD, which maximises edge weight per vertex: the same sets when the diagonal
      is the identity). "Exact" means optimal up to the LP solver's tolerance (~1e-9): each
      problem solves Charikar's linear program with HiGHS on CPU, s + s(s-1)/2 variables for a
      support of size s (~0.05 s at s = 20, ~0.2 s at s = 50 for a complete support; it grows
      steeply beyond). Supports above `cfg.densest_max_exact` (default 50) use greedy peeling,
      O(s^2) and a 1/2-approximation, instead. This rounding loops over problems.

    Args (torch tensors, or numpy arrays / nested lists, which are converted keeping their dtype):
        M: (B, n, n) or (n, n) affinities, symmetric, finite and nonnegative (padded entries
            too, though their values are ignored), float32 or float64, on any device; results
            come back with M's device and dtype. The diagonal is replaced by ones unless
            `cfg.diagonal == "input"` (then it holds unary weights).
        C: optional constraint mask of M's shape, nonzero = "may be selected together"; symmetric;
            its diagonal is ignored (treated as allowed). Defaults to the pattern M > 0, as
            CLIPPER builds it. Like CLIPPER's C++, pairs with C = 0 keep their affinity, and the
            penalty removes them.
        valid: optional (B, n) (or (n,) for one problem) bool marking real associations; padded entries are never selected
            and do not influence the others. Default: all valid.
        u0: optional (B, n) or (n,) nonnegative start vector; default U[0, 1) drawn from
            `generator` (or from a generator seeded with `cfg.seed`), so runs are reproducible.
        generator: random source for the start vector when `u0` is None.
        cfg: solver parameters; defaults to `ClipperConfig()` (CLIPPER's defaults).

    Returns:
        A `ClipperResult`, always batched: an (n, n) input gives B = 1. Use
        `inlier_indices(result, b)` for the selected indices of problem b. Not differentiable:
        the solve runs under `torch.no_grad`.

    Raises:
        ValueError: on shapes that do not match, a non-floating M, an asymmetric, negative or
            non-finite M, an asymmetric C, or a negative or non-finite u0.

    Example:
        >>> M = torch.ones(3, 3, dtype=torch.float64)
        >>> inlier_indices(solve_clipper(M)).tolist()
        [0, 1, 2]
    """
    cfg = ClipperConfig() if cfg is None else cfg
    M, C, valid, u0 = _check_inputs(M, C, valid, u0)
    B, n = M.shape[0], M.shape[-1]
    dtype, device = M.dtype, M.device
    if B == 0 or n == 0:
        return _empty_result(B, n, dtype, device)

    # M is neither modified nor masked (an n x n pass costs several mat-vecs): its diagonal is
    # corrected on the fly, and padded entries are inert because u stays zero on them.
    if cfg.diagonal == "identity":
        diag = torch.ones((B, n), dtype=dtype, device=device)
    else:
        diag = M.diagonal(0, -2, -1)
    Cb = ((M <= 0) if C is None else (C == 0)).to(dtype)
    Cb.diagonal(0, -2, -1).zero_()
    if C is not None:
        _check_symmetric(Cb, "C")

    if u0 is None:
        if generator is None:
            generator = torch.Generator(device=device).manual_seed(cfg.seed)
        u0 = torch.rand((B, n), generator=generator, device=generator.device, dtype=dtype).to(device)
    validf = valid.to(dtype)
    u = u0 * validf
    if cfg.rescale_u0:
        u = _affinity_mv(M, diag, u) * validf
    u = _normalize(u)

    state = _solve(M, diag, Cb, u, validf, cfg)
    inliers = _round(M, diag, Cb, state.u, state.objective, valid, cfg)
    return _result(state, inliers, _density(M, diag, inliers))


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


Edges = tuple[Tensor, Tensor, Tensor]  # (i, j, value), i < j: the positive off-diagonal entries


def restrict_edges(n: int, edges: Edges, members: Tensor) -> Edges:
    """The edges among `members` (k of n vertices, sorted), renumbered 0..k-1 in their order."""
    i, j, v = edges
    local = torch.full((n,), -1, dtype=torch.int64, device=v.device)
    local[members] = torch.arange(len(members), device=v.device)
    li, lj = local[i], local[j]
    keep = (li >= 0) & (lj >= 0)
    return li[keep], lj[keep], v[keep]


def dense_block(n: int, edges: Edges, members: Tensor) -> Tensor:
    """The symmetric (k, k) affinity among `members` (k of n vertices) from sparse upper-triangle
    edges; zero diagonal."""
    li, lj, v = restrict_edges(n, edges, members)
    W = torch.zeros(len(members), len(members), dtype=v.dtype, device=v.device)
    W[li, lj] = v
    return W + W.T


@torch.no_grad()
def solve_clipper_sparse(
    n: int,
    edges: Edges,
    *,
    generator: torch.Generator | None = None,
    cfg: ClipperConfig | None = None,
) -> ClipperResult:
    """`solve_clipper` for one problem given by its sparse affinity, never forming n x n matrices.

    Args:
        n: number of vertices.
        edges: (i, j, value) with i < j < n: the positive off-diagonal entries of a symmetric M
            whose diagonal is one; the constraint graph is M's pattern (C = M > 0).
        generator, cfg: as for `solve_clipper` (the diagonal is one whatever `cfg.diagonal` says).

    Each mat-vec costs O(edges + n) (`_SparseProblem`) instead of O(n^2); the start vector, steps
    and rounding are those of `solve_clipper` on the dense M (rounding works on the final support
    only, densified), so the result is the same up to floating-point summation order. Returns a
    `ClipperResult` with B = 1.
    """
    cfg = ClipperConfig() if cfg is None else cfg
    i, j, v = edges
    if not v.is_floating_point():
        raise ValueError(f"edge values must be floating point, got {v.dtype}")
    dtype, device = v.dtype, v.device
    if len(i) and not (bool((i < j).all()) and int(i.min()) >= 0 and int(j.max()) < n):
        raise ValueError(f"edges must have 0 <= i < j < n = {n}")
    if len(v) and not (bool(torch.isfinite(v).all()) and bool((v > 0).all())):
        raise ValueError("edge values must be finite and positive")
    if n == 0:
        return _empty_result(1, 0, dtype, device)
    index = torch.stack([torch.cat([i, j]), torch.cat([j, i])])
    with warnings.catch_warnings():  # torch's notes that CSR is "beta" and unchecked: indices are checked above
        warnings.simplefilter("ignore", UserWarning)
        M_off = torch.sparse_coo_tensor(index, torch.cat([v, v]), (n, n)).coalesce().to_sparse_csr()
        pattern = torch.sparse_coo_tensor(index, torch.ones(2 * len(v), dtype=dtype, device=device),
                                          (n, n)).coalesce().to_sparse_csr()
    diag = torch.ones((1, n), dtype=dtype, device=device)
    unpenalized = _SparseProblem(M_off, pattern, diag, torch.zeros(1, dtype=dtype, device=device))

    if generator is None:
        generator = torch.Generator(device=device).manual_seed(cfg.seed)
    u = torch.rand((1, n), generator=generator, device=generator.device, dtype=dtype).to(device)
    if cfg.rescale_u0:
        u = unpenalized.mv(u)
    u = _normalize(u)
    d = _initial_penalty(unpenalized.mv(u), unpenalized.cb_mv(u), u, cfg)
    state = _homotopy(_SparseProblem(M_off, pattern, diag, d.clone()), d, u, torch.ones_like(u), cfg)

    # Rounding looks only at entries with u > 0: densify that support.
    members = torch.nonzero(state.u[0] > 0).flatten()
    W = dense_block(n, edges, members)
    W.diagonal().fill_(1.0)
    Cb = (W <= 0).to(dtype)
    Cb.diagonal().zero_()
    sub_diag = torch.ones((1, len(members)), dtype=dtype, device=device)
    chosen = _round(W[None], sub_diag, Cb[None], state.u[:, members], state.objective,
                    torch.ones((1, len(members)), dtype=torch.bool, device=device), cfg)
    inliers = torch.zeros((1, n), dtype=torch.bool, device=device)
    inliers[0, members[chosen[0]]] = True
    return _result(state, inliers, _density(W[None], sub_diag, chosen))


# --------------------------------------------------------------------------------------------
# input handling


def _check_inputs(
    M: Tensor, C: Tensor | None, valid: Tensor | None, u0: Tensor | None
) -> tuple[Tensor, Tensor | None, Tensor, Tensor | None]:
    """Validate and batch the inputs: M (B, n, n), C like M or None, valid (B, n), u0 (B, n) or None.

    numpy arrays (and nested lists) are converted with `torch.as_tensor`, keeping their dtype.
    """
    def as_tensor(x: object, name: str) -> Tensor:
        if isinstance(x, Tensor):
            return x
        try:
            return torch.as_tensor(x)
        except (TypeError, ValueError, RuntimeError) as error:
            raise ValueError(f"{name} is not convertible to a tensor ({error})") from None

    M = as_tensor(M, "M")
    C = None if C is None else as_tensor(C, "C")
    valid = None if valid is None else as_tensor(valid, "valid")
    u0 = None if u0 is None else as_tensor(u0, "u0")
    if not M.is_floating_point():
        raise ValueError(f"M must be a floating-point tensor, got {getattr(M, 'dtype', type(M))}")
    if M.dim() == 2:
        M = M.unsqueeze(0)
    if M.dim() != 3 or M.shape[-1] != M.shape[-2]:
        raise ValueError(f"M must have shape (B, n, n) or (n, n), got {tuple(M.shape)}")
    B, n = M.shape[0], M.shape[-1]
    if C is not None:
        if C.dim() == 2:
            C = C.unsqueeze(0)
        if C.shape != M.shape:
            raise ValueError(f"C must have M's shape {tuple(M.shape)}, got {tuple(C.shape)}")
        C = C.to(M.device)
    if valid is None:
        valid = torch.ones((B, n), dtype=torch.bool, device=M.device)
    elif valid.dim() == 1 and B == 1:
        valid = valid.unsqueeze(0)
    if valid.shape != (B, n) or valid.dtype != torch.bool:
        raise ValueError(
            f"valid must be a bool tensor of shape {(B, n)}, got {valid.dtype} {tuple(valid.shape)}"
        )
    valid = valid.to(M.device)
    if u0 is not None:
        if u0.dim() == 1:
            u0 = u0.unsqueeze(0).expand(B, -1)
        if u0.shape != (B, n):
            raise ValueError(f"u0 must have shape {(B, n)} or {(n,)}, got {tuple(u0.shape)}")
        u0 = u0.to(device=M.device, dtype=M.dtype)
        if not bool(torch.isfinite(u0).all()) or bool((u0 < 0).any()):
            raise ValueError("u0 must be finite and nonnegative")
    if M.numel() > 0:
        low, high = torch.aminmax(M)
        # NaN propagates into the minimum, so this also rejects NaN.
        if not (float(low) >= 0.0 and math.isfinite(float(high))):
            raise ValueError("M must be finite and nonnegative")
        _check_symmetric(M, "M")
    return M, C, valid, u0


def _check_symmetric(X: Tensor, name: str) -> None:
    """Raise unless X (B, n, n) is symmetric, tested as X r == X' r for a fixed pseudo-random r.

    Two mat-vecs instead of an n x n comparison; a real asymmetry passes only with probability 0.
    """
    B, n = X.shape[0], X.shape[-1]
    r = torch.rand((B, n), generator=torch.Generator().manual_seed(12345), dtype=X.dtype).to(X.device)
    diff = torch.linalg.vector_norm(_bmv(X, r) - _bmv(X.mT, r))
    scale = torch.linalg.vector_norm(_bmv(X, r))
    if float(diff) > 1e-5 * max(float(scale), 1.0):
        raise ValueError(f"{name} must be symmetric")


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


# --------------------------------------------------------------------------------------------
# the continuous solve


@dataclass(frozen=True)
class _SolveState:
    u: Tensor
    objective: Tensor
    iterations: Tensor
    penalty_updates: Tensor
    converged: Tensor


def _bmv(A: Tensor, x: Tensor) -> Tensor:
    """Batched matrix-vector product (B, n, n) x (B, n) -> (B, n)."""
    return torch.bmm(A, x.unsqueeze(-1)).squeeze(-1)


def _affinity_mv(M: Tensor, diag: Tensor, x: Tensor) -> Tensor:
    """A x for the affinity A = M with its diagonal replaced by `diag` (B, n)."""
    return _bmv(M, x) + (diag - M.diagonal(0, -2, -1)) * x


def _normalize(u: Tensor) -> Tensor:
    """u / ||u|| per row; an all-zero row (empty or fully padded problem) stays zero."""
    norm = torch.linalg.vector_norm(u, dim=-1, keepdim=True)
    return u / norm.clamp_min(torch.finfo(u.dtype).tiny)


class _DenseProblem:
    """The penalised matrix Md = A - d Cb of a batch, held densely and updated in place when d grows,
    so each objective evaluation is one batched mat-vec and each penalty increase one n x n pass."""

    def __init__(self, Md: Tensor, Cb: Tensor) -> None:
        self.Md, self.Cb = Md, Cb

    def mv(self, u: Tensor) -> Tensor:
        return _bmv(self.Md, u)

    def cb_mv(self, u: Tensor) -> Tensor:
        return _bmv(self.Cb, u)

    def select(self, keep: Tensor) -> "_DenseProblem":
        return _DenseProblem(self.Md[keep], self.Cb[keep])

    def penalize(self, increment: Tensor) -> None:
        self.Md.addcmul_(self.Cb, increment[:, None, None], value=-1.0)


class _SparseProblem:
    """One problem (B = 1) from its sparse affinity M (CSR, no diagonal), never densified: with P
    the pattern of M, the forbidden pairs are Cb = 1 - I - P, so Cb u = sum(u) - u - P u and
    Md u = M u + diag u - d Cb u cost O(nnz + n) instead of O(n^2)."""

    def __init__(self, M_off: Tensor, pattern: Tensor, diag: Tensor, d: Tensor) -> None:
        self.M_off, self.pattern, self.diag, self.d = M_off, pattern, diag, d

    def cb_mv(self, u: Tensor) -> Tensor:
        return u.sum(-1, keepdim=True) - u - (self.pattern @ u.T).T

    def mv(self, u: Tensor) -> Tensor:
        return (self.M_off @ u.T).T + self.diag * u - self.d[:, None] * self.cb_mv(u)

    def select(self, keep: Tensor) -> "_SparseProblem":
        return self  # one problem: selecting it keeps it, and an empty selection is never used

    def penalize(self, increment: Tensor) -> None:
        self.d = self.d + increment


def _penalty_ratio(Au: Tensor, Cbu: Tensor, u: Tensor, eps: float) -> tuple[Tensor, Tensor]:
    """Mean of |(Au)_i / (Cb u)_i| over the support entries touching a forbidden pair.

    Returns (ratio (B,), violated (B,) bool); the ratio is 0 where nothing is violated. This is
    CLIPPER's initial d and its increment: the smallest d pushing those entries to the boundary.
    """
    touched = (Cbu > eps) & (u > eps)
    count = touched.sum(-1)
    safe = torch.where(touched, Cbu, torch.ones_like(Cbu))
    ratio = torch.where(touched, (Au / safe).abs(), torch.zeros_like(Au))
    return ratio.sum(-1) / count.clamp_min(1).to(Au.dtype), count > 0


def _initial_penalty(Au: Tensor, Cbu: Tensor, u: Tensor, cfg: ClipperConfig) -> Tensor:
    """The starting penalty d (B,): CLIPPER's ratio at the start vector, or `cfg.initial_d`."""
    if cfg.initial_d is None:
        return _penalty_ratio(Au, Cbu, u, cfg.eps)[0]
    return torch.full((u.shape[0],), cfg.initial_d, dtype=u.dtype, device=u.device)


def _solve(M: Tensor, diag: Tensor, Cb: Tensor, u: Tensor, validf: Tensor, cfg: ClipperConfig) -> _SolveState:
    """Penalty homotopy around batched projected-gradient ascent (clipper.md section 2), dense."""
    d = _initial_penalty(_affinity_mv(M, diag, u), _bmv(Cb, u), u, cfg)
    Md = M.clone()
    Md.addcmul_(Cb, d[:, None, None], value=-1.0)
    Md.diagonal(0, -2, -1).copy_(diag)
    return _homotopy(_DenseProblem(Md, Cb), d, u, validf, cfg)


def _homotopy(problem: "_DenseProblem | _SparseProblem", d: Tensor, u: Tensor, validf: Tensor,
              cfg: ClipperConfig) -> _SolveState:
    """The penalty loop on a problem whose Md already includes the penalty `d`."""
    B, n = u.shape
    dtype, device = u.dtype, u.device
    noise = _NOISE_EPS_FACTOR * torch.finfo(dtype).eps * math.sqrt(n)
    tol_u = max(cfg.tol_u, noise)
    objective = torch.zeros(B, dtype=dtype, device=device)
    iterations = torch.zeros(B, dtype=torch.int64, device=device)
    penalty_updates = torch.zeros(B, dtype=torch.int64, device=device)
    live = torch.arange(B, device=device)  # problems still running, the rows of `problem`
    for _ in range(cfg.max_outer_iterations):
        u_l, g_l, F_l, steps = _ascend(problem, u[live], validf[live], cfg, tol_u, noise)
        Cbu = problem.cb_mv(u_l)
        d_l = d[live]
        ratio, violated = _penalty_ratio(g_l + d_l[:, None] * Cbu, Cbu, u_l, cfg.eps)
        u[live] = u_l
        objective[live] = F_l
        iterations[live] += steps
        # A feasible support ends that problem; the others get a larger penalty.
        penalty_updates[live] += violated.to(torch.int64)
        d[live] = d_l + torch.where(violated, ratio, torch.zeros_like(ratio))
        if not bool(violated.all()):
            live, problem, ratio = live[violated], problem.select(violated), ratio[violated]
            if live.numel() == 0:
                break
        problem.penalize(ratio)
    converged = torch.ones(B, dtype=torch.bool, device=device)
    converged[live] = False
    return _SolveState(
        u=u, objective=objective, iterations=iterations, penalty_updates=penalty_updates, converged=converged
    )


def _ascend(
    problem: "_DenseProblem | _SparseProblem", u: Tensor, validf: Tensor, cfg: ClipperConfig, tol_u: float,
    noise: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Projected gradient ascent on u'Md u for a fixed penalty, every problem of the batch at once.

    Each step backtracks alpha = 1, beta, beta^2, ... until F does not drop by more than eps; if
    every trial fails the last one is taken (the reference's behaviour, then u barely moves).
    A problem leaves when ||du|| < tol_u or |dF| < tol_F. The direction is Md u, half the
    gradient and not projected on the sphere's tangent, as in the reference. Returns
    (u, g = Md u, F = u'Md u, steps per problem).
    """
    K = u.shape[0]
    g = problem.mv(u)
    F = (u * g).sum(-1)
    steps = torch.zeros(K, dtype=torch.int64, device=u.device)
    live = torch.arange(K, device=u.device)  # problems still iterating, into the batch
    p_l, u_l, g_l, F_l, v_l = problem, u, g, F, validf
    for _ in range(cfg.max_inner_iterations):
        # Float32 cannot resolve the reference's 1e-9 on an objective of size ~F.
        slack = torch.clamp(noise * (1.0 + F_l.abs()), min=cfg.eps)
        u_n, g_n, F_n = u_l, g_l, F_l
        searching = torch.ones(live.numel(), dtype=torch.bool, device=u.device)
        alpha = torch.ones_like(F_l)
        for _ in range(cfg.max_line_search_iterations):
            # Orthant, then sphere; padded entries are held at zero.
            cand = _normalize(torch.clamp(u_l + alpha[:, None] * g_l, min=0.0) * v_l)
            g_c = p_l.mv(cand)
            F_c = (cand * g_c).sum(-1)
            s = searching[:, None]
            u_n = torch.where(s, cand, u_n)
            g_n = torch.where(s, g_c, g_n)
            F_n = torch.where(searching, F_c, F_n)
            # A step that clamps every entry to zero is no solution, although F = 0 can beat
            # the negative F of a heavily penalised dense problem: shrink the step instead.
            collapsed = (cand.abs().sum(-1) == 0) & (u_l.abs().sum(-1) > 0)
            searching = searching & ((F_c - F_l < -slack) | collapsed)
            if not bool(searching.any()):
                break
            alpha = torch.where(searching, alpha * cfg.beta, alpha)
        du = torch.linalg.vector_norm(u_n - u_l, dim=-1)
        dF = (F_n - F_l).abs()
        u_l, g_l, F_l = u_n, g_n, F_n
        steps[live] += 1
        running = (du >= tol_u) & (dF >= torch.clamp(slack, min=cfg.tol_F))
        if not bool(running.all()):
            # Write the finished problems back and shrink the working batch to the rest.
            fin = ~running
            u[live[fin]] = u_l[fin]
            g[live[fin]] = g_l[fin]
            F[live[fin]] = F_l[fin]
            live, p_l, v_l = live[running], p_l.select(running), v_l[running]
            u_l, g_l, F_l = u_l[running], g_l[running], F_l[running]
            if live.numel() == 0:
                break
    u[live] = u_l
    g[live] = g_l
    F[live] = F_l
    return u, g, F, steps


# --------------------------------------------------------------------------------------------
# rounding


def _round(
    M: Tensor, diag: Tensor, Cb: Tensor, u: Tensor, F: Tensor, valid: Tensor, cfg: ClipperConfig
) -> Tensor:
    """Turn the continuous u into a clique of the constraint graph, per `cfg.rounding`."""
    umax = u.amax(-1, keepdim=True)
    support = (u > cfg.support_threshold * umax) & (u > 0) & valid
    if cfg.rounding == "clipper":
        # std::round(F) largest entries, ties to the lower index (stable sort). Unlike the
        # reference, never pick beyond the support: zero entries of u carry no evidence.
        omega = torch.floor(F + 0.5).clamp_min(0).to(torch.int64)
        order = torch.sort(u, dim=-1, descending=True, stable=True).indices
        positions = torch.arange(u.shape[-1], device=u.device).expand_as(order)
        rank = torch.empty_like(order).scatter_(-1, order, positions)
        chosen = (rank < omega[:, None]) & (u > 0) & valid
        return _repair_clique(Cb, u, chosen)
    support = _repair_clique(Cb, u, support)
    if cfg.rounding == "support":
        return support
    return _densest(M, diag, support, cfg.densest_max_exact)


def _repair_clique(Cb: Tensor, u: Tensor, chosen: Tensor) -> Tensor:
    """Largest-u-first greedy clique inside `chosen`: a vertex is kept if it has no forbidden
    pair with the vertices kept before it. Sets that are already cliques come back unchanged."""
    x = chosen.to(Cb.dtype)
    broken = ((x * _bmv(Cb, x)).sum(-1) > 0) & chosen.any(-1)
    if not bool(broken.any()):
        return chosen
    idx = torch.nonzero(broken).flatten()
    forbidden, uu, cand = Cb[idx] > 0, u[idx], chosen[idx]
    priority = torch.where(cand, uu, torch.full_like(uu, -1.0))
    order = torch.sort(priority, dim=-1, descending=True, stable=True).indices
    kept = torch.zeros_like(cand)
    rows = torch.arange(idx.numel(), device=u.device)
    for k in range(int(cand.sum(-1).max())):
        v = order[:, k]
        ok = cand[rows, v] & ~(forbidden[rows, v] & kept).any(-1)
        kept[rows, v] = ok
    out = chosen.clone()
    out[idx] = kept
    return out


def _densest(M: Tensor, diag: Tensor, support: Tensor, max_exact: int) -> Tensor:
    """Per problem, the subset S of the support maximising x'Ax / x'x (exact up to
    `max_exact` vertices, greedy peeling above). Subsets of a clique are cliques."""
    out = torch.zeros_like(support)
    for b in torch.nonzero(support.any(-1)).flatten().tolist():
        members = torch.nonzero(support[b]).flatten()
        W = M[b][members][:, members].detach().to("cpu", torch.float64).numpy().copy()
        np.fill_diagonal(W, diag[b, members].detach().to("cpu", torch.float64).numpy())
        keep = _densest_exact(W) if W.shape[0] <= max_exact else _densest_peeling(W)
        out[b, members[torch.from_numpy(keep).to(members.device)]] = True
    return out


def _prefix_densities(W: np.ndarray, order: np.ndarray) -> np.ndarray:
    """x'Wx / x'x of every prefix order[:k+1] of a vertex ordering, in O(s^2)."""
    Wo = W[np.ix_(order, order)]
    # Adding vertex k adds its diagonal term plus twice its weight to the vertices before it.
    gain = np.diag(Wo) + 2.0 * np.tril(Wo, -1).sum(1)
    return np.cumsum(gain) / np.arange(1, len(order) + 1)


def _best_prefix(W: np.ndarray, orders: list[np.ndarray]) -> np.ndarray:
    """The densest prefix over several vertex orderings; near-ties go to the larger set (recall)."""
    dens = [_prefix_densities(W, order) for order in orders]
    top = max(float(d.max()) for d in dens)
    floor = top - _DENSITY_TIE_RTOL * max(1.0, abs(top))
    size, order = max(
        ((int(np.nonzero(d >= floor)[0][-1]) + 1, o) for d, o in zip(dens, orders)), key=lambda t: t[0]
    )
    return np.sort(order[:size])


def _peeling_order(W: np.ndarray) -> np.ndarray:
    """Vertices in reverse peeling order: repeatedly remove the one of least weighted degree
    (diagonal counted once, as in x'Wx). Prefixes of the result are the peeled subgraphs."""
    s = W.shape[0]
    deg = np.diag(W) + 2.0 * (W.sum(1) - np.diag(W))
    alive = np.ones(s, dtype=bool)
    removed = []
    for _ in range(s):
        v = int(np.argmin(np.where(alive, deg, np.inf)))
        removed.append(v)
        alive[v] = False
        deg -= 2.0 * W[v]
    return np.asarray(removed[::-1], dtype=np.int64)


def _densest_peeling(W: np.ndarray) -> np.ndarray:
    """Greedy peeling (Charikar): the densest of the n nested peeled subgraphs, O(s^2)."""
    return _best_prefix(W, [_peeling_order(W)])


def _densest_exact(W: np.ndarray) -> np.ndarray:
    """Exact densest subset via Charikar's LP: maximise sum_e w_e y_e + sum_i (W_ii / 2) x_i
    subject to y_e <= x_i, y_e <= x_j, sum x = 1, x, y >= 0. Its optimum equals the best density
    (x'Wx / 2x'x) and some level set {x_i >= r} attains it, so the densest prefix of x sorted
    in decreasing order is optimal (to the LP solver's tolerance, ~1e-9). The peeling prefixes,
    the full support among them, are candidates too: a guard against an inaccurate LP solution."""
    from scipy.optimize import linprog
    from scipy.sparse import coo_matrix

    s = W.shape[0]
    iu, ju = np.nonzero(np.triu(W, 1) > 0)
    E = iu.size
    if E == 0:
        return _densest_peeling(W)
    cost = -np.concatenate([np.diag(W) / 2.0, W[iu, ju]])
    rows = np.repeat(np.arange(2 * E), 2)
    y_cols = np.concatenate([s + np.arange(E), s + np.arange(E)])
    cols = np.stack([y_cols, np.concatenate([iu, ju])], 1).ravel()
    vals = np.tile([1.0, -1.0], 2 * E)
    A_ub = coo_matrix((vals, (rows, cols)), shape=(2 * E, s + E)).tocsr()
    A_eq = coo_matrix((np.ones(s), (np.zeros(s, dtype=np.int64), np.arange(s))), shape=(1, s + E)).tocsr()
    lp = linprog(
        cost, A_ub=A_ub, b_ub=np.zeros(2 * E), A_eq=A_eq, b_eq=[1.0], bounds=(0, None), method="highs"
    )
    orders = [_peeling_order(W)]
    if lp.status == 0:
        orders.append(np.argsort(-lp.x[:s], kind="stable"))
    return _best_prefix(W, orders)

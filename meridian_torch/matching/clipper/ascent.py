"""The continuous CLIPPER solve shared by the dense and the sparse solver: the penalised problem
(dense or sparse mat-vecs), the initial penalty and its increments, the penalty homotopy and the
batched projected-gradient ascent with backtracking on the nonnegative unit sphere."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from meridian_torch.config.matching import ClipperConfig

# Tolerances below this many machine epsilons (times sqrt(n) and the objective's scale) cannot be
# met in float32, where the reference's 1e-9 would make every inner loop run to its cap.
_NOISE_EPS_FACTOR = 8.0


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
    Md u = M u + diag u - d Cb u cost O(nnz + n) instead of O(n^2).

    On the CPU in float64 the products run in scipy: torch's CSR product starts a parallel region
    per call (milliseconds each when the other core is busy, for tens of microseconds of work),
    and scipy sums each row in the same order on one thread (bitwise torch's, tested)."""

    def __init__(self, M_off: Tensor, pattern: Tensor, diag: Tensor, d: Tensor) -> None:
        self.M_off, self.pattern, self.diag, self.d = M_off, pattern, diag, d
        self._scipy = None
        if M_off.device.type == "cpu" and M_off.dtype == torch.float64:
            import scipy.sparse

            index = (M_off.col_indices().numpy(), M_off.crow_indices().numpy())
            self._scipy = tuple(scipy.sparse.csr_matrix((A.values().numpy(), *index), shape=A.shape)
                                for A in (M_off, pattern))

    def _product(self, which: int, u: Tensor) -> Tensor:
        """(M_off or pattern) u' for u (B, n), as (B, n)."""
        if self._scipy is None:
            return ((self.M_off, self.pattern)[which] @ u.T).T
        return torch.from_numpy(self._scipy[which] @ u.numpy().T).T

    def cb_mv(self, u: Tensor) -> Tensor:
        return u.sum(-1, keepdim=True) - u - self._product(1, u)

    def mv(self, u: Tensor) -> Tensor:
        return self._product(0, u) + self.diag * u - self.d[:, None] * self.cb_mv(u)

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


def _tolerances(n: int, dtype: torch.dtype, cfg: ClipperConfig) -> tuple[float, float]:
    """(tol_u, noise): the step tolerance and the rounding noise of an objective of size 1."""
    noise = _NOISE_EPS_FACTOR * torch.finfo(dtype).eps * math.sqrt(n)
    return max(cfg.tol_u, noise), noise


def _homotopy(problem: "_DenseProblem | _SparseProblem", d: Tensor, u: Tensor, validf: Tensor,
              cfg: ClipperConfig) -> _SolveState:
    """The penalty loop on a problem whose Md already includes the penalty `d`."""
    B, n = u.shape
    dtype, device = u.dtype, u.device
    tol_u, noise = _tolerances(n, dtype, cfg)
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


def _compiled_homotopy(M_off: Tensor, d: Tensor, u: Tensor, cfg: ClipperConfig) -> _SolveState:
    """`_homotopy` on one sparse CPU problem (M_off in CSR, unit diagonal, start u (1, n) and
    penalty d (1,)) as one compiled call (`kernels.sparse_homotopy`); u is updated in place."""
    from meridian_torch.matching.clipper.kernels import sparse_homotopy

    tol_u, noise = _tolerances(u.shape[1], u.dtype, cfg)
    objective, iterations, updates, converged = sparse_homotopy(
        M_off.crow_indices().numpy(), M_off.col_indices().numpy(), M_off.values().numpy(), u[0].numpy(),
        float(d[0]), tol_u, noise, cfg.eps, cfg.tol_F, cfg.beta, cfg.max_inner_iterations,
        cfg.max_line_search_iterations, cfg.max_outer_iterations)
    return _SolveState(
        u=u, objective=torch.tensor([objective], dtype=u.dtype), iterations=torch.tensor([iterations]),
        penalty_updates=torch.tensor([updates]), converged=torch.tensor([converged]),
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

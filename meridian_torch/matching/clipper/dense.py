"""`solve_clipper`: CLIPPER over a batch of dense, padded problems, with its input checks."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from meridian_torch.config.matching import ClipperConfig
from meridian_torch.matching.clipper.ascent import (
    _affinity_mv,
    _bmv,
    _DenseProblem,
    _homotopy,
    _initial_penalty,
    _normalize,
    _SolveState,
)
from meridian_torch.matching.clipper.result import ClipperResult, _density, _empty_result, _result
from meridian_torch.matching.clipper.rounding import _round

__all__ = ["solve_clipper"]


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


def _solve(M: Tensor, diag: Tensor, Cb: Tensor, u: Tensor, validf: Tensor, cfg: ClipperConfig) -> _SolveState:
    """Penalty homotopy around batched projected-gradient ascent (clipper.md section 2), dense."""
    d = _initial_penalty(_affinity_mv(M, diag, u), _bmv(Cb, u), u, cfg)
    Md = M.clone()
    Md.addcmul_(Cb, d[:, None, None], value=-1.0)
    Md.diagonal(0, -2, -1).copy_(diag)
    return _homotopy(_DenseProblem(Md, Cb), d, u, validf, cfg)


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

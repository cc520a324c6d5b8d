"""`solve_clipper_sparse`: CLIPPER on one problem given by its sparse upper-triangle edges, never
forming n x n matrices, and the helpers that restrict and densify such edges."""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

from meridian_torch.config.matching import ClipperConfig
from meridian_torch.matching.clipper.ascent import (
    _compiled_homotopy,
    _homotopy,
    _initial_penalty,
    _normalize,
    _SparseProblem,
)
from meridian_torch.matching.clipper.result import ClipperResult, _density, _empty_result, _result
from meridian_torch.matching.clipper.rounding import _round

__all__ = ["Edges", "dense_block", "restrict_edges", "solve_clipper_sparse"]

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
    W[lj, li] = v  # in place: W + W.T would hold a second k x k matrix
    return W


def _symmetric_csr(n: int, i: Tensor, j: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """The symmetric (n, n) CSR matrix of the edges (i < j) and its pattern (ones), sharing one
    index structure. Raises ValueError if a pair repeats.

    Built by one sort of the row-major keys, with int32 indices where they fit: the long-drive
    final pass holds millions of edges, and going through COO coalescing held about 200 bytes per
    edge at its peak.
    """
    index_dtype = torch.int32 if max(n, 2 * len(v)) < 2**31 else torch.int64
    i, j = i.to(torch.int64), j.to(torch.int64)  # row * n + column overflows int32 indices
    rows = torch.cat([i, j])
    key = rows * n
    key += torch.cat([j, i])
    order = torch.argsort(key)
    del key
    col = torch.cat([j, i])[order].to(index_dtype)
    crow = torch.zeros(n + 1, dtype=torch.int64, device=v.device)
    crow[1:] = torch.cumsum(torch.bincount(rows, minlength=n), 0)
    del rows
    crow = crow.to(index_dtype)
    repeated = col[1:] == col[:-1]  # within a row the columns are sorted: a duplicate is a repeat
    row_start = crow[1:-1].to(torch.int64)
    repeated[row_start[(row_start > 0) & (row_start < len(col))] - 1] = False  # ... not across rows
    if bool(repeated.any()):
        raise ValueError("edges must not repeat a pair (i, j)")
    values = torch.cat([v, v])[order]
    del order
    with warnings.catch_warnings():  # torch's notes that CSR is "beta" and unchecked: indices are checked by the caller
        warnings.simplefilter("ignore", UserWarning)
        M_off = torch.sparse_csr_tensor(crow, col, values, (n, n))
        pattern = torch.sparse_csr_tensor(crow, col, torch.ones_like(values), (n, n))
    return M_off, pattern


@torch.no_grad()
def solve_clipper_sparse(
    n: int,
    edges: Edges,
    *,
    generator: torch.Generator | None = None,
    cfg: ClipperConfig | None = None,
    compiled: bool | None = None,
) -> ClipperResult:
    """`solve_clipper` for one problem given by its sparse affinity, never forming n x n matrices.

    Args:
        n: number of vertices.
        edges: (i, j, value) with i < j < n, each pair once: the positive off-diagonal entries of a symmetric M
            whose diagonal is one; the constraint graph is M's pattern (C = M > 0).
        generator, cfg: as for `solve_clipper` (the diagonal is one whatever `cfg.diagonal` says).
        compiled: run the continuous solve as one compiled call (`kernels.sparse_homotopy`, the
            same steps to rounding) instead of torch's loop; default: on CPU float64 edges.

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
    M_off, pattern = _symmetric_csr(n, i, j, v)
    diag = torch.ones((1, n), dtype=dtype, device=device)
    unpenalized = _SparseProblem(M_off, pattern, diag, torch.zeros(1, dtype=dtype, device=device))

    if generator is None:
        generator = torch.Generator(device=device).manual_seed(cfg.seed)
    u = torch.rand((1, n), generator=generator, device=generator.device, dtype=dtype).to(device)
    if cfg.rescale_u0:
        u = unpenalized.mv(u)
    u = _normalize(u)
    d = _initial_penalty(unpenalized.mv(u), unpenalized.cb_mv(u), u, cfg)
    if compiled is None:
        compiled = device.type == "cpu" and dtype == torch.float64
    if compiled:
        state = _compiled_homotopy(M_off, d, u, cfg)
    else:
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

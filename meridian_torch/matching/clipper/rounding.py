"""Rounding of CLIPPER's continuous solution to a set of inliers: the round(F) largest entries,
the support, or the densest subset (exact by Charikar's LP up to a size, greedy peeling above),
repaired greedily into a clique of the constraint graph."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from meridian_torch.config.matching import ClipperConfig
from meridian_torch.matching.clipper.ascent import _bmv

# Two candidate densities closer than this (relative) are a tie, resolved towards the larger set.
_DENSITY_TIE_RTOL = 1e-9


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

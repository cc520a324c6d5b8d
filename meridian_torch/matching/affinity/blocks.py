"""Gated evaluation of the affinity: a cheap necessary condition over all association pairs of
a row block, the exact scores only on the survivors, as flat index lists; for CPU tensors the
compiled kernel (`compiled`) does both pair by pair."""

from __future__ import annotations

import math

import torch

from meridian_torch.config.matching import AffinityConfig
from meridian_torch.matching.affinity.compiled import _compiled_entries
from meridian_torch.matching.affinity.gather import _Gathered, _rotate
from meridian_torch.matching.affinity.scores import (
    _GATE_SLACK,
    _line_line_score,
    _point_line_score,
    _point_pair_score,
)


def _take(table: torch.Tensor, key: torch.Tensor, cos_sin: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor:
    """Table columns at key (n,) -> (F, n); vector fields 3, 4 rotated by the per-entry (cos, sin)."""
    out = table.index_select(1, key)
    if cos_sin is not None:
        vx, vy = _rotate(*cos_sin, out[3], out[4])
        out = torch.cat([out[:3], vx[None], vy[None]])
    return out


def _pair_scores(gat: _Gathered, b: torch.Tensor, i: torch.Tensor, j: torch.Tensor, kind: str, cfg: AffinityConfig) -> torch.Tensor:
    """Exact s of the association pairs (b, i, j), flat (n,); kind 'pp', 'pl' (i point, j line) or 'll'."""
    rotated = gat.cos_sin is not None
    cos_sin = (gat.cos_sin[0][b], gat.cos_sin[1][b]) if rotated else None
    mp = gat.n_point_assoc
    if kind == "pp":
        return _point_pair_score(
            gat.a_px[b, i] - gat.a_px[b, j],
            gat.a_py[b, i] - gat.a_py[b, j],
            gat.g_px[b, i] - gat.g_px[b, j],
            gat.g_py[b, i] - gat.g_py[b, j],
            0.0,
            cfg,
            rotated,
            min_separation=True,
        )
    if kind == "pl":
        a_key = (b * gat.n_aerial_points + gat.a_pt[b, i]) * gat.n_aerial_lines + gat.a_ln[b, j - mp]
        g_key = gat.g_pt[b, i] * gat.n_ground_lines + gat.g_ln[b, j - mp]
        # Ground tables are in the odom frame; only their vectors need the patch's prior rotation.
        return _point_line_score(_take(gat.a_pl, a_key, None), _take(gat.g_pl, g_key, cos_sin), cfg, rotated)
    n_al = gat.n_aerial_lines
    a_key = (b * n_al + gat.a_ln[b, i - mp]) * n_al + gat.a_ln[b, j - mp]
    g_key = gat.g_ln[b, i - mp] * gat.n_ground_lines + gat.g_ln[b, j - mp]
    return _line_line_score(_take(gat.a_ll, a_key, None), _take(gat.g_ll, g_key, cos_sin), cfg, rotated)


def _gate(gat: _Gathered, r0: int, r1: int, c0: int, c1: int, kind: str, cfg: AffinityConfig) -> torch.Tensor:
    """(P, r1 - r0, c1 - c0) bool: pairs of rows [r0, r1) and columns [c0, c1) (strict upper
    triangle) that may score non-zero: the kind's table values within tolerance (which also
    excludes shared primitives)."""
    n_patches = gat.valid.shape[0]
    mp = gat.n_point_assoc
    patch = torch.arange(n_patches, device=gat.valid.device)[:, None, None]
    if kind == "pp":
        rows_a, cols_a, rows_g, cols_g = gat.a_pt[:, r0:r1], gat.a_pt[:, c0:c1], gat.g_pt[:, r0:r1], gat.g_pt[:, c0:c1]
        n_a, n_g, tol = (gat.n_aerial_points, gat.n_aerial_points), (gat.n_ground_points,) * 2, cfg.epsilon_t_m
        tables = gat.a_pp_gate, gat.g_pp_gate
    elif kind == "pl":
        rows_a, cols_a = gat.a_pt[:, r0:r1], gat.a_ln[:, c0 - mp : c1 - mp]
        rows_g, cols_g = gat.g_pt[:, r0:r1], gat.g_ln[:, c0 - mp : c1 - mp]
        n_a, n_g, tol = (gat.n_aerial_points, gat.n_aerial_lines), (gat.n_ground_points, gat.n_ground_lines), cfg.epsilon_t_m
        tables = gat.a_pl_gate, gat.g_pl_gate
    else:
        rows_a, cols_a = gat.a_ln[:, r0 - mp : r1 - mp], gat.a_ln[:, c0 - mp : c1 - mp]
        rows_g, cols_g = gat.g_ln[:, r0 - mp : r1 - mp], gat.g_ln[:, c0 - mp : c1 - mp]
        n_a, n_g = (gat.n_aerial_lines,) * 2, (gat.n_ground_lines,) * 2
        tol, tables = math.radians(cfg.epsilon_theta_deg), (gat.a_ll_gate, gat.g_ll_gate)
    # int32 keys and in-place arithmetic: this runs on every pair, so memory traffic is the cost.
    a_key = ((patch * n_a[0] + rows_a[:, :, None]) * n_a[1]).to(torch.int32) + cols_a[:, None, :].to(torch.int32)
    g_key = (rows_g[:, :, None] * n_g[1]).to(torch.int32) + cols_g[:, None, :].to(torch.int32)
    diff = tables[0].index_select(0, a_key.view(-1))
    diff.sub_(tables[1].index_select(0, g_key.view(-1))).abs_()
    ok = (diff <= tol + _GATE_SLACK).view(a_key.shape)
    # q_i q_j is not gated here: pairs with q = 0 (padding included) score 0 and are dropped after scoring.
    if c0 < r1:
        ok &= torch.arange(c0, c1, device=ok.device)[None, None, :] > torch.arange(r0, r1, device=ok.device)[None, :, None]
    return ok


def _spans(gat: _Gathered, cfg: AffinityConfig) -> list[tuple[int, int, int, int, str]]:
    """The evaluation order: row blocks of ~block_pairs pairs (which bound the torch path's peak
    memory), each with its column spans, as (r0, r1, c0, c1, kind), strict upper triangle."""
    n_patches, m = gat.valid.shape
    mp = gat.n_point_assoc
    rows = max(1, cfg.block_pairs // max(1, n_patches * m))
    spans = []
    for start, stop in ((0, mp), (mp, m)):
        for r0 in range(start, stop, rows):
            r1 = min(r0 + rows, stop)
            candidates = [(r0, mp, "pp"), (mp, m, "pl")] if r0 < mp else [(r0, m, "ll")]
            spans += [(r0, r1, c0, c1, kind) for c0, c1, kind in candidates if c0 < c1]
    return spans


def _entries(gat: _Gathered, cfg: AffinityConfig, compiled: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Non-zero strict-upper-triangle entries: indices (n, 3) of (patch, i, j) and M values (n,).

    M = cbrt(s q_i q_j); one-to-one conflicts, entries with M <= affinity_eps and padding are
    left out. compiled: score with the numba kernel (`compiled`; default: for CPU tensors)
    instead of the torch ops. Both emit the same entries in the same order, span by span and
    within a span by (patch, i, j): sums over the entries downstream (the pruning's index_add_)
    then do not depend on the path. Values may differ by a few ulps (see `compiled`).
    """
    spans = _spans(gat, cfg)
    if compiled is None:
        compiled = gat.q.device.type == "cpu"
    if compiled:
        return _compiled_entries(gat, spans, cfg)
    indices, values = [], []
    for r0, r1, c0, c1, kind in spans:
        nz = _gate(gat, r0, r1, c0, c1, kind, cfg).nonzero()
        b, i, j = nz[:, 0], nz[:, 1] + r0, nz[:, 2] + c0
        product = _pair_scores(gat, b, i, j, kind, cfg) * gat.q[b, i] * gat.q[b, j]
        keep = product > cfg.affinity_eps**3
        indices.append(torch.stack([b, i, j], 1)[keep])
        values.append(product[keep].pow(1.0 / 3.0))
    if not indices:
        return torch.zeros(0, 3, dtype=torch.int64, device=gat.q.device), gat.q.new_zeros(0)
    return torch.cat(indices), torch.cat(values)

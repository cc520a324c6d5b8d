"""The consistency graph between loop-closure candidates and its CLIPPER inliers.

Two candidates i, j (submaps at path lengths l_i, l_j) are consistent when the relative motion
they imply, T_world_base_i^-1 T_world_base_j, agrees with the odometry's relative motion
T_odom_base_i^-1 T_odom_base_j. With E = odom_rel^-1 cv_rel, e_yaw = |yaw(E)|, e_t = |xy(E)|
and the noise at l = |l_j - l_i|: sigma_yaw(l) = sigma_yaw + slope_yaw * l (likewise sigma_t),

    s(i, j) = sqrt(exp(-e_yaw^2 / 2 sigma_yaw^2) * exp(-e_t^2 / 2 sigma_t^2))
              if e_yaw < sigma_yaw and e_t < sigma_t, else 0,

and 0 for two candidates of one submap (at most one inlier per submap). The affinity fuses the
qualities by a geometric mean, cbrt(s q_i q_j), with a unit diagonal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from meridian_torch.backend.candidates import LoopClosureCandidates
from meridian_torch.backend.consistency_kernels import ball_heading_pairs
from meridian_torch.config import BackendConfig
from meridian_torch.geometry.se2 import se2_inverse, wrap_angle, yaw_of
from meridian_torch.matching.clipper.sparse import Edges, dense_block, restrict_edges, solve_clipper_sparse

__all__ = [
    "Edges",
    "InlierSelection",
    "PairErrors",
    "consistency_affinity",
    "consistency_scores",
    "pair_errors",
    "select_inliers",
    "select_inliers_in_windows",
    "sparse_affinity",
]


@dataclass(frozen=True)
class PairErrors:
    """(N, N) pairwise quantities of a candidate set."""

    yaw_error: Tensor  # radians, |yaw(E)|
    translation_error: Tensor  # metres, |xy(E)|
    sigma_yaw: Tensor  # radians, noise at the pair's path-length difference
    sigma_t: Tensor  # metres


# Rows of the per-candidate pair features (float64): every pair's errors need only these, and
# the yaws with their cosines and sines are computed once per candidate instead of once per pair
# (atan2 over millions of gathered 3x3 poses was most of the cost of a large pool).
_WX, _WY, _WYAW, _WCOS, _WSIN, _OX, _OY, _OYAW, _OCOS, _OSIN, _LENGTH, _QUALITY, _SUBMAP = range(13)


def _features(c: LoopClosureCandidates) -> Tensor:
    """(13, N) pair features of the candidates (rows as above; feature-major, so that the features
    of gathered candidates, `features[:, index]`, are contiguous rows)."""
    world_yaw, odom_yaw = yaw_of(c.T_world_base), yaw_of(c.T_odom_base)
    return torch.stack([
        c.T_world_base[:, 0, 2], c.T_world_base[:, 1, 2], world_yaw, torch.cos(world_yaw), torch.sin(world_yaw),
        c.T_odom_base[:, 0, 2], c.T_odom_base[:, 1, 2], odom_yaw, torch.cos(odom_yaw), torch.sin(odom_yaw),
        c.path_length_m, c.quality, c.submap_index.to(torch.float64),
    ])


def _relative(rows: Tensor, cols: Tensor, x: int) -> tuple[Tensor, Tensor, Tensor]:
    """x, y, yaw of T_i^-1 T_j for the pose whose features start at row x, elementwise over
    broadcastable (13, ...) features."""
    dx = cols[x] - rows[x]
    dy = cols[x + 1] - rows[x + 1]
    c, s = rows[x + 3], rows[x + 4]
    return c * dx + s * dy, -s * dx + c * dy, cols[x + 2] - rows[x + 2]


def _pair_errors(rows: Tensor, cols: Tensor, cfg: BackendConfig) -> PairErrors:
    """Errors of the pairs (row, column) of (13, ...) features, elementwise over their broadcast shape."""
    ox, oy, oyaw = _relative(rows, cols, _OX)
    cx, cy, cyaw = _relative(rows, cols, _WX)
    length = (rows[_LENGTH] - cols[_LENGTH]).abs()
    if not cfg.path_length_scaling:
        length = torch.zeros_like(length)
    return PairErrors(
        yaw_error=wrap_angle(cyaw - oyaw).abs(),
        translation_error=torch.hypot(cx - ox, cy - oy),
        sigma_yaw=math.radians(cfg.sigma_yaw_deg) + math.radians(cfg.sigma_yaw_deg_per_m) * length,
        sigma_t=cfg.sigma_t_m + cfg.sigma_t_m_per_m * length,
    )


def pair_errors(c: LoopClosureCandidates, cfg: BackendConfig) -> PairErrors:
    """Odometry-vs-cross-view relative motion errors and the path-length-scaled noise of all pairs.

    E = odom_rel^-1 cv_rel has yaw(E) = yaw(cv_rel) - yaw(odom_rel) and |xy(E)| =
    |xy(cv_rel) - xy(odom_rel)| (the rotation by -yaw(odom_rel) keeps the norm).
    """
    f = _features(c)
    return _pair_errors(f[:, :, None], f[:, None], cfg)


def _affinity(rows: Tensor, cols: Tensor, cfg: BackendConfig) -> Tensor:
    """Fused affinity of the pairs (row, column) of features, elementwise (broadcast), no diagonal handling."""
    e = _pair_errors(rows, cols, cfg)
    inside = (e.yaw_error < e.sigma_yaw) & (e.translation_error < e.sigma_t)
    log_k = -0.5 * (e.yaw_error / e.sigma_yaw).square() - 0.5 * (e.translation_error / e.sigma_t).square()
    s = torch.where(inside, torch.exp(0.5 * log_k), torch.zeros_like(log_k))
    s = s.masked_fill(rows[_SUBMAP] == cols[_SUBMAP], 0.0)
    if cfg.fuse_quality:
        s = (s * rows[_QUALITY] * cols[_QUALITY]).pow(1.0 / 3.0)
    return s.masked_fill(s <= cfg.affinity_eps, 0.0)


def consistency_scores(c: LoopClosureCandidates, cfg: BackendConfig) -> Tensor:
    """(N, N) symmetric pairwise consistency s(i, j) in [0, 1]; 0 on the diagonal and within a submap."""
    raw = cfg.model_copy(update={"fuse_quality": False, "affinity_eps": 0.0})
    # |xy(E)| of (i, j) and (j, i) differ slightly (E_ji is E_ij seen from the other end); score
    # each pair once, as i < j, like the reference's pair loop.
    f = _features(c)
    s = _affinity(f[:, :, None], f[:, None], raw).triu(1)
    return s + s.T


def consistency_affinity(c: LoopClosureCandidates, cfg: BackendConfig) -> Tensor:
    """(N, N) dense CLIPPER affinity: cbrt(s q_i q_j) (or s), <= affinity_eps dropped, unit diagonal."""
    f = _features(c)
    M = _affinity(f[:, :, None], f[:, None], cfg).triu(1)
    M = M + M.T
    M.diagonal().fill_(1.0)
    return M


def _submap_groups(c: LoopClosureCandidates) -> tuple[Tensor, Tensor]:
    """(G, 6) key rows (submap, path length, odom x, y, cos, sin) and (N,) each candidate's group.

    Candidates of one submap share its odometry pose and path length; keying on them too keeps
    the grouping right for any input."""
    T = c.T_odom_base
    key = torch.stack(
        [c.submap_index.to(torch.float64), c.path_length_m, T[:, 0, 2], T[:, 1, 2], T[:, 0, 0], T[:, 1, 0]], dim=1
    )
    # Usually each submap has one key: then its rows in submap order are torch.unique's rows
    # (sorted lexicographically, the submap first), found without sorting N rows of 6 floats.
    key_np = key.numpy()
    _, first, group = np.unique(c.submap_index.numpy(), return_index=True, return_inverse=True)
    if bool((key_np[first][group] == key_np).all()):
        return torch.from_numpy(key_np[first]), torch.from_numpy(group)
    return torch.unique(key, dim=0, return_inverse=True)


# Pairs scored at once: each costs ~500 bytes in gathered candidates and temporaries, so 2^18
# pairs hold ~130 MiB (2^21 held ~1 GiB, the peak of a run before its fix); larger chunks were
# no faster. A heading bin's pairs are scored in pieces of the pairs of this many queries (the
# chunks of an earlier tree query, whose hits were Python lists): a pair's place in its piece fixes
# its rounding (see `_submap_edges`).
_CHUNK_PAIRS = 1 << 18
_CHUNK_QUERIES = 1 << 12


def _cat_edges(parts: list[Edges]) -> Edges:
    empty = (torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.float64))
    return tuple(torch.cat(x) for x in zip(empty, *parts))  # type: ignore[return-value]


def _pair_edges(features: Tensor, cfg: BackendConfig, i: Tensor, j: Tensor) -> Edges:
    """The non-zero affinities of the pairs (i, j), each scored with its lower index as the row."""
    lo, hi = torch.minimum(i, j), torch.maximum(i, j)
    parts = []
    for k in range(0, len(lo), _CHUNK_PAIRS):
        a, b = lo[k : k + _CHUNK_PAIRS], hi[k : k + _CHUNK_PAIRS]
        v = _affinity(features[:, a], features[:, b], cfg)
        keep = v > 0
        parts.append((a[keep], b[keep], v[keep]))
    return _cat_edges(parts)


def _queries(
    c: LoopClosureCandidates, cfg: BackendConfig, mine: Tensor, others: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, int]:
    """The radius queries of `others` into the candidates `mine` (see `_submap_edges`): the
    queried candidates (those whose disk is not wide), their predicted positions, radii and yaw
    gates, the wide mask over `others`, and the number of heading bins of `mine`."""
    offset = se2_inverse(c.T_odom_base[others]) @ c.T_odom_base[mine[0]]  # odometry motion to `mine`'s submap
    predicted = (c.T_world_base[others] @ offset)[:, :2, 2]
    length = (c.path_length_m[others] - c.path_length_m[mine[0]]).abs()
    if not cfg.path_length_scaling:
        length = torch.zeros_like(length)
    sigma_t = cfg.sigma_t_m + cfg.sigma_t_m_per_m * length
    sigma_yaw = math.radians(cfg.sigma_yaw_deg) + math.radians(cfg.sigma_yaw_deg_per_m) * length
    radius = sigma_t + offset[:, :2, 2].norm(dim=1) * sigma_yaw + 1e-6
    xy = c.T_world_base[mine, :2, 2]
    extent = (xy.amax(0) - xy.amin(0)).clamp_min(1.0)
    wide = math.pi * radius.square() >= 0.1 * float(extent.prod())
    queries, query_xy, query_radius = others[~wide], predicted[~wide], radius[~wide]
    query_sigma_yaw = sigma_yaw[~wide] + 1e-9  # the margin covers rounding (the exact test is in the affinity)
    # `mine` split by heading into bins at least the widest sigma_yaw wide: a query searches its
    # own bin and the two beside it, which hold every heading within its sigma_yaw
    n_bins = int(2.0 * math.pi / (float(query_sigma_yaw.max()) * (1.0 + 1e-6))) if len(queries) else 1
    n_bins = n_bins if n_bins >= 3 else 1
    return queries, query_xy, query_radius, query_sigma_yaw, wide, n_bins


def _submap_edges(
    c: LoopClosureCandidates, features: Tensor, heading: Tensor, cfg: BackendConfig, mine: Tensor, others: Tensor
) -> Edges:
    """Non-zero affinities between the candidates `mine` (one submap) and `others` (other submaps).

    For a candidate b of submap B, the pose it predicts for submap A's base is
    Q = T_world_base_b * T_odom_base_B^-1 * T_odom_base_A, and the translation error of (b, a)
    scored with b as the row is |t_a - t_Q|. Scored with a as the row, it differs from that by
    at most |o| * yaw error (o = odometry offset between the submaps), and a non-zero affinity
    needs yaw error < sigma_yaw and translation error < sigma_t. So only the candidates of A
    within sigma_t + |o| sigma_yaw of t_Q can pair with b: a radius query finds them. The yaw
    error of a pair is the difference of the two candidates' T_world_odom (`heading`), so A's
    candidates are searched by heading bin, and hits whose headings differ by sigma_yaw or more
    are dropped before they are scored (most of them before a fix: about 20 M hits for 0.1 M
    edges); both tests run in one compiled pass (`ball_heading_pairs`). Where that disk covers
    much of A's candidates (far-apart submaps: the noise grows with path length) scoring every
    pair is cheaper than the query, and gives the same edges.
    """
    queries, query_xy, query_radius, query_sigma_yaw, wide, n_bins = _queries(c, cfg, mine, others)
    # The bins' bookkeeping in numpy: per bin, torch's ops over the whole pool were each a
    # parallel region (tens of thousands per call), and each can wait for a busy second core.
    mine_bin, query_bin = (_heading_bin(heading[x], n_bins).numpy() for x in (mine, queries))
    mine_by_bin, query_by_bin = (np.argsort(x, kind="stable") for x in (mine_bin, query_bin))
    mine_start, query_start = (np.searchsorted(x[o], np.arange(n_bins + 1)) for x, o in
                               ((mine_bin, mine_by_bin), (query_bin, query_by_bin)))
    world_xy, heading_np, queries_np = c.T_world_base[:, :2, 2].numpy(), heading.numpy(), queries.numpy()
    query_xy, query_radius, query_sigma_yaw = query_xy.numpy(), query_radius.numpy(), query_sigma_yaw.numpy()
    parts = []
    for b in range(n_bins):
        members = mine.numpy()[mine_by_bin[mine_start[b] : mine_start[b + 1]]]  # ascending
        near_bins = {(b - 1) % n_bins, b, (b + 1) % n_bins} if n_bins > 1 else {0}
        searching = np.sort(np.concatenate([query_by_bin[query_start[x] : query_start[x + 1]] for x in near_bins]))
        if len(members) == 0 or len(searching) == 0:
            continue
        query, member = ball_heading_pairs(
            world_xy[members], heading_np[members], query_xy[searching], query_radius[searching],
            heading_np[queries_np[searching]], query_sigma_yaw[searching],
        )
        # Scored in the pieces of the earlier query chunks: torch's pow and hypot round the tail
        # of a call's vector loop differently, so each pair keeps its place in its piece.
        pieces = np.searchsorted(query, np.arange(_CHUNK_QUERIES, len(searching), _CHUNK_QUERIES))
        for q, m in zip(np.split(query, pieces), np.split(member, pieces)):
            if len(q):
                rows, cols = torch.from_numpy(members[m]), torch.from_numpy(queries_np[searching[q]])
                parts.append(_pair_edges(features, cfg, rows, cols))
    return _cat_edges([*parts, _block_edges(features, cfg, mine, others[wide])])


def _heading_bin(heading: Tensor, n_bins: int) -> Tensor:
    """Bin 0..n_bins-1 of each heading (radians) on the circle cut into n_bins equal arcs."""
    if n_bins == 1:
        return torch.zeros(heading.shape, dtype=torch.int64)
    arc = ((wrap_angle(heading) + math.pi) * (n_bins / (2.0 * math.pi))).floor().to(torch.int64)
    return arc.clamp(0, n_bins - 1)


def _block_edges(features: Tensor, cfg: BackendConfig, rows: Tensor, cols: Tensor) -> Edges:
    """The non-zero affinities of every pair of `rows` x `cols` (disjoint), each scored with its
    lower index as the row, by broadcasting (no gathers), a block of rows at a time."""
    parts = []
    b = features[:, cols]
    step = max(1, _CHUNK_PAIRS // max(len(cols), 1))
    for k0 in range(0, len(rows) if len(cols) else 0, step):
        block = rows[k0 : k0 + step]
        a = features[:, block]
        lower = block[:, None] < cols[None, :]
        if bool(lower.all()):
            M = _affinity(a[:, :, None], b[:, None], cfg)
        elif not bool(lower.any()):
            M = _affinity(b[:, :, None], a[:, None], cfg).T
        else:
            M = torch.where(lower, _affinity(a[:, :, None], b[:, None], cfg), _affinity(b[:, :, None], a[:, None], cfg).T)
        r, k = torch.nonzero(M, as_tuple=True)
        parts.append((torch.minimum(block[r], cols[k]), torch.maximum(block[r], cols[k]), M[r, k]))
    return _cat_edges(parts)


def sparse_affinity(c: LoopClosureCandidates, cfg: BackendConfig, *, first_new: int = 0) -> Edges:
    """Non-zero off-diagonal affinities (i < j) as (i, j, value), the same values as the dense matrix.

    Only pairs with j >= `first_new` are scored (the others are known from an earlier call on a
    prefix of the same candidates). Each submap with new candidates is scored against the
    candidates of the submaps not yet done (`_submap_edges`: a radius query skips the pairs that
    cannot be consistent), so time grows with the pairs of nearby predictions, not with N^2.
    """
    keys, group = _submap_groups(c)
    features = _features(c)
    heading = features[_WYAW] - features[_OYAW]  # of T_world_odom: a pair's yaw error is their difference
    # The submaps' bookkeeping in numpy (see `_submap_edges`).
    group_np, submap = group.numpy(), keys[:, 0].numpy()
    pending = np.ones(len(keys), dtype=bool)  # submaps whose pairs with the rest are not yet found
    parts = []
    for g in np.unique(group_np[first_new:]):
        pending[g] = False
        others = np.flatnonzero(pending[group_np] & (submap[group_np] != submap[g]))
        if len(others):
            mine = np.flatnonzero(group_np == g)
            parts.append(_submap_edges(c, features, heading, cfg, torch.from_numpy(mine), torch.from_numpy(others)))
    # A final pass over a long drive holds millions of edges: free each copy as the next is made.
    i, j, v = _cat_edges(parts)
    del parts
    keep = j >= first_new
    if not bool(keep.all()):
        i, j, v = i[keep], j[keep], v[keep]
    del keep
    order = torch.argsort(i * max(len(c), 1) + j)
    i = i[order]
    j = j[order]
    v = v[order]
    return i, j, v


@dataclass(frozen=True)
class InlierSelection:
    inliers: Tensor  # (N,) bool, at most one per submap
    score: float  # CLIPPER density x'Mx / x'x of the selected set (0 when empty)
    # the consistency graph of all N candidates (reusable via `known_edges`); None when it was
    # never built whole (`select_inliers_in_windows`)
    edges: Edges | None

    @property
    def count(self) -> int:
        return int(self.inliers.sum())


def _solve(
    n: int,
    edges: tuple[Tensor, Tensor, Tensor],
    index: Tensor,
    cfg: BackendConfig,
    generator: torch.Generator | None,
) -> tuple[Tensor, float]:
    """CLIPPER on the candidates `index` (sorted) from the sparse edges; (selected indices, density).
    The consistency graph is sparse (candidates agree with few others), so the solve works on the
    edges (`solve_clipper_sparse`: O(edges) per step instead of O(k^2) for k candidates)."""
    result = solve_clipper_sparse(len(index), restrict_edges(n, edges, index), generator=generator, cfg=cfg.clipper)
    return index[result.inliers[0]], float(result.score[0])


def _greedy_clique(n: int, edges: tuple[Tensor, Tensor, Tensor]) -> tuple[Tensor, float]:
    """A greedy clique grown from the best-connected candidate: (indices, density x'Mx / x'x)."""
    i, j, v = edges
    degree = torch.zeros(n, dtype=v.dtype).index_add_(0, i, v).index_add_(0, j, v)
    seed = int(torch.argmax(degree))
    nbrs = torch.unique(torch.cat([j[i == seed], i[j == seed]]))
    members = torch.cat([torch.tensor([seed]), nbrs])
    W = dense_block(n, edges, members)
    clique = [0]
    allowed = W[0] > 0
    while allowed.any():
        gain = torch.where(allowed, W[clique].sum(0), torch.full_like(W[0], -1.0))
        k = int(torch.argmax(gain))
        clique.append(k)
        allowed &= W[k] > 0
        allowed[clique] = False
    sub = W[clique][:, clique]
    return members[clique], float((len(clique) + sub.sum()) / len(clique))


def _peel(n: int, edges: tuple[Tensor, Tensor, Tensor], lower_bound: float) -> Tensor:
    """Candidates that can belong to a clique of density >= lower_bound (sorted indices).

    In the densest clique S every member v has 1 + 2 sum_{u in S} M_uv >= density(S) (else
    dropping v would make it denser), so a candidate whose total weighted degree is below
    (lower_bound - 1) / 2 cannot be in it; removing it lowers its neighbours' degrees: repeat.
    """
    i, j, v = edges
    alive = torch.zeros(n, dtype=torch.bool)
    alive[i] = True
    alive[j] = True
    while True:
        e = alive[i] & alive[j]
        degree = torch.zeros(n, dtype=v.dtype).index_add_(0, i[e], v[e]).index_add_(0, j[e], v[e])
        drop = alive & (1.0 + 2.0 * degree < lower_bound - 1e-9)
        if not drop.any():
            return torch.nonzero(alive).flatten()
        alive &= ~drop


def select_inliers(
    c: LoopClosureCandidates,
    cfg: BackendConfig,
    generator: torch.Generator | None = None,
    *,
    known_edges: tuple[int, Edges] | None = None,
) -> InlierSelection:
    """The densest mutually consistent candidate set by CLIPPER.

    Only candidates that can belong to a clique at least as dense as a greedy one enter the solve
    (`_peel`; exact for the densest clique, and it removes the many candidates without consistent
    partners); without any edge the best-quality candidate (then the most probable) is the single
    inlier. Pools still larger than `cfg.max_clipper_candidates` are split into even chunks, each
    solved on its own; the pooled chunk inliers are solved once more (the reference's chunking).
    `known_edges` = (n_known, edges of the first n_known candidates of `c`) skips scoring those
    pairs again (a pool that only grew since).
    """
    n = len(c)
    inliers = torch.zeros(n, dtype=torch.bool)
    first_new, known = known_edges if known_edges is not None else (0, None)
    if not 0 <= first_new <= n:
        raise ValueError(f"known_edges covers {first_new} candidates, the set has {n}")
    new = sparse_affinity(c, cfg, first_new=first_new)
    edges = new if known is None else tuple(torch.cat([k, e]) for k, e in zip(known, new))
    if n == 0:
        return InlierSelection(inliers, 0.0, edges)
    if len(edges[0]) == 0:
        best = int(torch.argmax(c.quality + 1e-9 * c.probability))
        inliers[best] = True
        return InlierSelection(inliers, 1.0, edges)
    greedy, greedy_density = _greedy_clique(n, edges)
    index = _peel(n, edges, greedy_density)
    if len(index) > cfg.max_clipper_candidates:
        chunks = torch.tensor_split(index, len(index) // cfg.max_clipper_candidates + 1)
        index = torch.cat([_solve(n, edges, ch, cfg, generator)[0] for ch in chunks]).sort().values
    selected, score = _solve(n, edges, index, cfg, generator)
    if score < greedy_density:  # a failed solve never does worse than the greedy clique
        selected, score = greedy, greedy_density
    inliers[selected] = True
    return InlierSelection(inliers, score, edges)


def select_inliers_in_windows(
    c: LoopClosureCandidates, cfg: BackendConfig, generator: torch.Generator | None = None
) -> InlierSelection:
    """`select_inliers` with memory bounded by `cfg.max_clipper_candidates` whatever the drive's length.

    A set of at most that many candidates is `select_inliers`'s. A larger one is cut into even
    windows of consecutive submaps (in submap order, a submap never split), each window's inliers
    are selected on its own graph, and the pooled window inliers once more. For the final pass:
    its candidates (every submap re-matched near the final trajectory) are mostly true and
    mutually consistent, so their one graph is nearly complete, ~N^2/2 edges (4 passes of the
    KITTI 09 drive: 4009 candidates, 5.7 M edges, about 1 GB while built and solved), and the
    chunks `select_inliers` would solve anyway are then windows of the drive.
    """
    n = len(c)
    if n <= cfg.max_clipper_candidates:
        return select_inliers(c, cfg, generator)
    order = torch.argsort(c.submap_index, stable=True)
    _, counts = torch.unique_consecutive(c.submap_index[order], return_counts=True)
    n_windows = n // cfg.max_clipper_candidates + 1
    before = torch.cumsum(counts, 0) - counts  # candidates of the submaps before each submap
    window_of_submap = before * n_windows // n
    window = torch.repeat_interleave(window_of_submap, counts)
    pooled = []
    for w in torch.unique(window_of_submap).tolist():
        members = order[window == w]
        selected = select_inliers(c.select(members), cfg, generator)
        pooled.append(members[selected.inliers])
    index = torch.cat(pooled).sort().values
    final = select_inliers(c.select(index), cfg, generator)
    inliers = torch.zeros(n, dtype=torch.bool)
    inliers[index[final.inliers]] = True
    return InlierSelection(inliers, final.score, None)

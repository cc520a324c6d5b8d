"""Distribution over inlier sets: batched Langevin particles on the penalised affinity.

For every patch p with affinity M (m x m, unit diagonal on valid associations) the sampler
runs N particles x on the nonnegative unit sphere with the target F(x) = x' M_d x, where
M_d = M - d * Cb, Cb = 1[M == 0] on valid pairs (one-to-one conflicts, inconsistent pairs and
pairs below the affinity threshold alike) and d = the patch's number of valid associations
(reference `langevin_matcher.py`). One iteration:

    g = x M_d;  v = g + sigma_t * xi;  h = alpha h + (1 - alpha) v^2 (h = v^2 at t = 0);
    x = normalize(max(x + eta * v / (sqrt(h) + 1e-6), 0)),  sigma_t = sqrt(eta) (1 - t / (T - 1)).

Batching: all P patches and all N particles live in one (P, N, m) tensor and advance together.
Because Cb = J - 1[M != 0] on the valid block, x M_d = x A - d * sum(x) with A = M + d 1[M != 0]
sharing M's sparsity, so a sparse affinity stays sparse (the rows of one block-diagonal CSR
matrix, built once per batch) and each step is one batched product. Every `check_interval`
iterations a patch whose EMA of the mean objective has settled for `patience` checks is frozen
and dropped from the working batch.

Randomness is counter based: a 64-bit mix (splitmix64 finaliser) of (patch seed, iteration,
particle, association index). The per-patch seeds are drawn from the caller's generator, so
one seed gives identical runs, and a patch's trajectory depends on nothing but its own seed and
data (not on the other patches in the batch, their early stopping or the padded width m). The
Gaussian noise of one step is a slab of a fixed table of standard normals (made once per
process) read from a random offset per patch, entry (i, n) for coordinate i and particle n,
with a random sign per particle: hashing every entry would cost as much as the drift.

Cost: on the CPU the loop and the rounding are compiled (`matching.kernels`): one patch's
particles at a time, in cache, each step in a few fused passes (3.4x less time than the torch
loop, which stays for other devices: every step in place on the (P, m, N) buffers). On the
CPU the bookkeeping around the loop is compiled too (the CSR rows, the particles' words, noise
signs and start, the merge of identical sets): as torch ops over the P x m x N words and masks
they cost a quarter of the time of the loop.

Rounding (reference DSD_HEU): k = round(x' M_d x) clamped to [0, m_valid], the set is the k
largest entries of x. Sets smaller than `min_set_size` or using a ground or aerial primitive
twice are discarded, identical sets are merged (hash keys + exact comparison) with their
particle counts summed, and the sets are ranked by J(S) = 1_S' M 1_S / |S| (unpenalised M).

Pruning: before sampling, each patch keeps its `max_associations` best supported associations
(`particle_problem.support_pruning`, two-step walk counts on the affinity graph); masks are
reported over all m.
Particles x iterations on a CPU: the defaults are `ParticleConfig`'s, the measurements behind
them in the README (Why the defaults are what they are). Early stopping rarely fires before T,
and fewer steps are no cure: the preconditioner's first average is the huge penalty gradient of
the dense random start (|g| ~ 10^4 against ~10^2 later), so the effective step grows from ~0.02 to ~1 only over
the whole schedule (the mean objective turns positive only after ~40 of 100 steps). Measured on the KITTI
00 / 09 worlds' rendered submaps (each against its true patch): 50 steps (also with alpha =
0.81, the same schedule compressed) lost 15-26 points of known-rotation top-25 success, a
preconditioner restarted after the first step found nothing.

Start: x0 uniform in [0, s) per coordinate (s = `start_scale`, `start_scale_free_rotation` for
matches without a rotation prior). The first step moves almost every coordinate by -1
(RMSprop's first step is v / |v|, and the dense start's penalty gradient is negative), so at
s = 1 it clears the start and the particles set out from the next step's noise; at s = 2 the
entries above 1/2 survive, and the first squared gradient, ~s^2, makes the step grow more
slowly. s = 2 found the true set more often without a rotation prior on the worlds it was
measured on, and not on two others; with one it found it less often. Both stay at 1 (README,
Why the defaults).
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from meridian_torch.config.matching import ParticleConfig
from meridian_torch.core.parallel import cpu_threads, thread_map
from meridian_torch.core.timing import stage
from meridian_torch.matching.affinity import AffinityEntries
from meridian_torch.matching.kernels import block_rows, langevin_patches, merge_sets, round_particles
from meridian_torch.matching.particle_noise import (
    add_noise_,
    circular_table,
    initial_positions,
    patch_seeds,
    slab_table,
    step_noise,
)
from meridian_torch.matching.particle_problem import SamplerProblem, sampler_problem

__all__ = ["InlierSets", "sample_inlier_sets", "sample_problem", "patch_seeds"]

# Fixed seed (independent of the caller's generator) of the set-hash weights.
_SET_HASH_SEED = 0x5E7


@dataclass(frozen=True)
class InlierSets:
    """Unique inlier sets of P patches, padded to S sets, sorted by objective (descending).

    Attributes:
        masks: (P, S, m) bool, the associations of each set.
        counts: (P, S) int64, particles that rounded to the set (0 on padding).
        objective: (P, S) J(S) = 1' M 1 / |S| with the unpenalised M (0 on padding).
        valid: (P, S) bool, False for padding.
        iterations: (P,) int64, Langevin steps run per patch (early stopping).
        n_particles: particles per patch; counts / n_particles is each set's probability mass.
    """

    masks: Tensor
    counts: Tensor
    objective: Tensor
    valid: Tensor
    iterations: Tensor
    n_particles: int


@dataclass(frozen=True)
class _BlockRows:
    """P symmetric (m, m) matrices of one sparsity as the rows p m + i of one block-diagonal CSR
    matrix (P m, P m), columns ascending in each row (a coalesced COO's order).

    Attributes:
        crow: (P m + 1,) int64 row offsets.
        batch, row, col: (nnz,) int64 patch p, row i and column j of each entry.
        value: (nnz,) the entries.
        m: the size of a block.
    """

    crow: Tensor
    batch: Tensor
    row: Tensor
    col: Tensor
    value: Tensor
    m: int

    def csr(self) -> Tensor:
        """The matrix as a sparse CSR tensor (P m, P m)."""
        size = len(self.crow) - 1
        with warnings.catch_warnings():  # "sparse CSR support is in beta"
            warnings.simplefilter("ignore", UserWarning)
            return torch.sparse_csr_tensor(self.crow, self.batch * self.m + self.col, self.value, (size, size),
                                           check_invariants=False)

    def select(self, keep: Tensor) -> _BlockRows:
        """The blocks `keep` (ascending indices), renumbered 0 .. len(keep) - 1."""
        new_id = torch.full(((len(self.crow) - 1) // max(self.m, 1),), -1, dtype=torch.int64, device=keep.device)
        new_id[keep] = torch.arange(keep.numel(), device=keep.device)
        b = new_id[self.batch]
        use = b >= 0
        # Rows are sorted by (batch, row, col); keeping batches in order keeps them sorted.
        return _BlockRows.of_sorted(b[use], self.row[use], self.col[use], self.value[use], self.m, keep.numel())

    @staticmethod
    def of_sorted(batch: Tensor, row: Tensor, col: Tensor, value: Tensor, m: int, n_blocks: int) -> _BlockRows:
        """The rows of entries already sorted by (batch, row, col), with their offsets counted."""
        crow = torch.zeros(n_blocks * m + 1, dtype=torch.int64, device=batch.device)
        crow[1:] = torch.cumsum(torch.bincount(batch * m + row, minlength=n_blocks * m), 0)
        return _BlockRows(crow, batch, row, col, value, m)


def _block_rows(entries: AffinityEntries, compiled: bool | None = None) -> _BlockRows:
    """The affinity of `entries` (unit diagonal on its valid associations) as `_BlockRows`.
    `compiled` (default: on CPU tensors) sorts the entries into rows in one compiled pass
    (`kernels.block_rows`), else through the coalesced COO (other devices): the same rows
    (entries are unique, as `AffinityEntries` promises; a COO would sum repeats)."""
    m = entries.valid.shape[1]
    if entries.valid.device.type == "cpu" if compiled is None else compiled:
        arrays = [x.contiguous().numpy() for x in (entries.index, entries.value, entries.valid)]
        return _BlockRows(*(torch.from_numpy(a) for a in block_rows(*arrays)), m)
    M = entries.to_sparse()
    return _BlockRows.of_sorted(*M.indices(), M.values(), m, len(entries.valid))


class _BlockOperator:
    """P symmetric (m, m) matrices as one block-diagonal CSR matrix: y = A x for x (P, m, N) in
    one sparse product. A COO `bmm` is ~6x slower on CPU and a dense one does 20x the work at
    the ~5 % fill of affinities."""

    def __init__(self, rows: _BlockRows) -> None:
        self.rows = rows
        self.csr = rows.csr()

    def keep(self, keep: Tensor) -> None:
        """Restrict to the batch entries `keep` (ascending indices into the current batch)."""
        self.rows = self.rows.select(keep)
        self.csr = self.rows.csr()

    def __call__(self, x: Tensor) -> Tensor:
        P, m, N = x.shape
        return (self.csr @ x.reshape(P * m, N)).reshape(P, m, N)


def _penalised(M: _BlockRows, d: Tensor) -> _BlockRows:
    """A = M + d 1[M != 0] (same sparsity as M); x M_d = A x - d sum(x) on valid coordinates."""
    return dataclasses.replace(M, value=M.value + d[M.batch] * (M.value != 0))


def _drift(A: _BlockOperator, d: Tensor, validf: Tensor, x: Tensor) -> Tensor:
    """g = M_d x for x (P, m, N); zero on padded coordinates."""
    return A(x).addcmul_(validf[:, :, None], d[:, None, None] * x.sum(1, keepdim=True), value=-1.0)


def _noise_schedule(cfg: ParticleConfig) -> list[float]:
    """sigma_t of every step: sqrt(eta), decaying linearly to 0 with `anneal`."""
    sqrt_eta, T = cfg.step_size**0.5, cfg.n_iterations
    return [sqrt_eta * (1.0 - t / (T - 1)) if cfg.anneal else sqrt_eta for t in range(T)]


@torch.no_grad()
def _run_dynamics(
    A: _BlockRows, d: Tensor, valid: Tensor, cfg: ParticleConfig, seeds: Tensor, compiled: bool | None = None
) -> tuple[Tensor, Tensor]:
    """Langevin loop for all patches on the penalised affinity A; returns final x (P, m, N) and
    iterations (P,). `compiled` (default: on CPU tensors) runs the compiled loop, else torch's
    (other devices)."""
    dtype, device = d.dtype, d.device
    validf = valid.to(dtype)
    x = initial_positions(seeds, validf, cfg.n_particles)
    if cfg.start_scale != 1.0:
        x.mul_(cfg.start_scale)
    offsets, scale = step_noise(seeds, _noise_schedule(cfg), cfg.n_particles, dtype)
    if device.type == "cpu" if compiled is None else compiled:
        return _compiled_dynamics(A, d, validf, x, offsets, scale, cfg)
    return _torch_dynamics(_BlockOperator(A), d, validf, x, offsets, scale, cfg)


def _compiled_dynamics(
    A: _BlockRows, d: Tensor, validf: Tensor, x: Tensor, offsets: Tensor, scale: Tensor, cfg: ParticleConfig
) -> tuple[Tensor, Tensor]:
    """`langevin_patches` on CPU tensors, the patches dealt round-robin to torch's CPU threads
    (each patch's steps are independent of the others')."""
    n_patches, m = validf.shape
    iterations = torch.empty(n_patches, dtype=torch.int64)
    table = circular_table(m * cfg.n_particles, x.dtype, x.device)
    constants = torch.tensor([cfg.step_size, cfg.alpha, 1.0 - cfg.alpha, 1e-6, 0.0], dtype=x.dtype)
    arrays = [t.numpy() for t in (A.crow, A.col, A.value, d, validf, x, iterations, table, offsets, scale, constants)]

    def run(patches: Tensor) -> None:
        langevin_patches(patches.numpy(), *arrays, cfg.noise, cfg.rmsprop, cfg.early_stop, cfg.check_interval,
                         cfg.obj_tol, cfg.patience)

    threads = max(1, min(cpu_threads(), n_patches))
    thread_map(run, [torch.arange(k, n_patches, threads) for k in range(threads)])
    return x, iterations


def _torch_dynamics(
    A: _BlockOperator, d: Tensor, validf: Tensor, x: Tensor, offsets: Tensor, scale: Tensor, cfg: ParticleConfig
) -> tuple[Tensor, Tensor]:
    """The Langevin loop as torch ops on the whole (P, m, N) batch (A is consumed): every step in
    place (allocating the buffers cost more than the arithmetic)."""
    n_patches, m = validf.shape
    T, dtype, device = cfg.n_iterations, x.dtype, x.device
    slabs = slab_table(m * cfg.n_particles, dtype, device) if cfg.noise else None
    x_out = x
    iterations = torch.full((n_patches,), T, dtype=torch.int64, device=device)
    # Working batch: the patches still running (indices into the full batch).
    active = torch.arange(n_patches, device=device)
    d_act, v_act, x = d, validf[:, :, None], x_out.clone()
    h = torch.zeros_like(x)
    ema = torch.zeros(n_patches, dtype=dtype, device=device)
    settled = torch.zeros(n_patches, dtype=torch.int64, device=device)

    for t in range(T):
        g = _drift(A, d_act, v_act[..., 0], x)
        if cfg.early_stop and t > 0 and t % cfg.check_interval == 0:
            objective = (g * x).sum(1).mean(-1)
            if t == cfg.check_interval:
                ema[active] = objective
            else:
                old = ema[active]
                new = 0.5 * old + 0.5 * objective
                ema[active] = new
                calm = (new - old).abs() / (old.abs() + 1e-12) < cfg.obj_tol
                settled[active] = torch.where(calm, settled[active] + 1, 0)
            done = settled[active] >= cfg.patience
            if bool(done.any()):
                finished = active[done]
                x_out[finished] = x[done]
                iterations[finished] = t
                keep = (~done).nonzero().squeeze(1)
                active = active[keep]
                x, h, g = x[keep], h[keep], g[keep]
                if active.numel() == 0:
                    break
                A.keep(keep)
                d_act, v_act = d_act[keep], v_act[keep]
        if slabs is not None:
            add_noise_(g, slabs, offsets[t, active], scale[t, active])
        if cfg.rmsprop:
            if t == 0:
                h = g.square()
            else:
                h.mul_(cfg.alpha).addcmul_(g, g, value=1.0 - cfg.alpha)
            x.addcdiv_(g, h.sqrt().add_(1e-6), value=cfg.step_size)
        else:
            x.add_(g, alpha=cfg.step_size)
        x.clamp_min_(0.0).mul_(v_act)
        x.div_((x * x).sum(1, keepdim=True).sqrt_().clamp_min_(1e-6))
    x_out[active] = x
    return x_out, iterations


def _rounded_sets(A: _BlockRows, d: Tensor, valid: Tensor, pairs: Tensor, x: Tensor, rounding: str) -> tuple[Tensor, Tensor, Tensor]:
    """Each particle x (P, m, N) rounded to a set (`_select_sets`) of its round(x' M_d x)
    largest valid entries, or its support ('support' rounding); A is the penalised affinity."""
    support = rounding == "support"
    k = torch.zeros(x.shape[0], x.shape[2], dtype=torch.int64, device=x.device)
    if not support:
        quad = (_drift(_BlockOperator(A), d, valid.to(x.dtype), x) * x).sum(1)
        k = quad.round().clamp(min=0).minimum(d[:, None]).to(torch.int64)
    return _select_sets(x, k, valid, pairs, support)


def _select_sets(
    x: Tensor, k: Tensor, valid: Tensor, pairs: Tensor, support: bool, compiled: bool | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Masks (P, N, m) bool of the k (P, N) largest valid entries of each particle x (P, m, N),
    ties in index order (with `support`: its valid entries > 0), their sizes (P, N) and whether
    the set uses no ground and no aerial primitive twice (P, N). `compiled` (default: on CPU
    tensors) selects with `round_particles`, else with torch's stable sort (other devices): the
    same sets."""
    if x.device.type == "cpu" if compiled is None else compiled:
        arrays = [t.detach().cpu().contiguous().numpy() for t in (x, k, valid, pairs)]
        return tuple(torch.from_numpy(a).to(x.device) for a in round_particles(*arrays, support))
    if support:
        masks = (x > 0).transpose(1, 2) & valid[:, None, :]
    else:
        x = x.transpose(1, 2)
        # Padded entries sort last; the stable sort keeps ties (e.g. exact zeros) in index order.
        order = torch.sort(x.masked_fill(~valid[:, None, :], -1.0), dim=-1, descending=True, stable=True).indices
        take = torch.arange(x.shape[-1], device=x.device) < k[..., None]
        masks = torch.zeros_like(take).scatter_(-1, order, take)
    return masks, masks.sum(-1), _one_to_one(masks, pairs)


def _one_to_one(masks: Tensor, pairs: Tensor) -> Tensor:
    """(P, N) bool: no ground and no aerial primitive is used twice by a set."""
    ok = torch.ones(masks.shape[:2], dtype=torch.bool, device=masks.device)
    weight = masks.to(torch.int32)
    for side in range(2):
        index = pairs[..., side].clamp_min(0)
        width = int(index.max()) + 1 if index.numel() else 1
        use = torch.zeros(masks.shape[:2] + (width,), dtype=torch.int32, device=masks.device)
        use.scatter_add_(2, index[:, None, :].expand_as(weight), weight)
        ok &= use.amax(-1) <= 1
    return ok


def _merge(masks: Tensor, keep: Tensor, compiled: bool | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Merge identical sets per patch.

    Returns (order (P, N) particle permutation, the masks in that order (P, N, m), first (P, N)
    bool marking the first particle of each group of identical kept sets in that order, counts
    (P, N) group sizes at those firsts). `compiled` (default: on CPU tensors) hashes, sorts and
    compares in one compiled pass per patch (`kernels.merge_sets`), else with torch's sorts
    (other devices): the same integers.
    """
    n_patches, n_particles, m = masks.shape
    gen = torch.Generator(device=masks.device).manual_seed(_SET_HASH_SEED)
    weights = torch.randint(-(1 << 62), 1 << 62, (m,), generator=gen, device=masks.device)
    if masks.device.type == "cpu" if compiled is None else compiled:
        order, masks_s, first, counts = merge_sets(masks.contiguous().numpy(), keep.contiguous().numpy(), weights.numpy())
        return torch.from_numpy(order), torch.from_numpy(masks_s), torch.from_numpy(first), torch.from_numpy(counts)
    key = (masks.to(torch.int64) * weights).sum(-1)  # wraps mod 2^64: a random linear hash
    order = torch.sort(key, dim=1, stable=True).indices
    # Kept sets first, each run of equal keys contiguous inside them.
    order = order.gather(1, torch.sort((~keep).gather(1, order).to(torch.int8), dim=1, stable=True).indices)
    key_s, keep_s = key.gather(1, order), keep.gather(1, order)
    masks_s = _rows(masks, order)
    # Exact verification: a key collision between different sets never merges them.
    same = (key_s[:, 1:] == key_s[:, :-1]) & (masks_s[:, 1:] == masks_s[:, :-1]).all(-1) & keep_s[:, 1:]
    first = torch.cat([keep_s[:, :1], keep_s[:, 1:] & ~same], dim=1)
    group = (torch.cumsum(first.to(torch.int64), dim=1) - 1).clamp_min(0)
    sizes = torch.zeros_like(group).scatter_add_(1, group, keep_s.to(torch.int64))
    counts = torch.where(first, sizes.gather(1, group), 0)
    return order, masks_s, first, counts


def _rows(x: Tensor, index: Tensor) -> Tensor:
    """x[p, index[p, j]] (P, J, ...) for x (P, N, ...): whole rows by indexing (a gather through
    an index expanded over the rows costs ~3x)."""
    return x[torch.arange(len(x), device=x.device)[:, None], index]


@torch.no_grad()
def sample_problem(problem: SamplerProblem, cfg: ParticleConfig, seeds: Tensor) -> InlierSets:
    """Inlier sets of a `SamplerProblem` with per-patch seeds (P,), masks over its m associations."""
    valid = problem.entries.valid
    kept = _sample(_block_rows(problem.entries), valid, problem.pairs, cfg, seeds.to(device=valid.device, dtype=torch.int64))
    masks = torch.zeros(kept.masks.shape[:2] + (problem.m + 1,), dtype=torch.bool, device=valid.device)
    masks.scatter_(2, problem.index[:, None, :].expand_as(kept.masks), kept.masks)
    return dataclasses.replace(kept, masks=masks[..., : problem.m])


@torch.no_grad()
def sample_inlier_sets(
    M: Tensor | AffinityEntries,
    valid: Tensor,
    pairs: Tensor,
    cfg: ParticleConfig | None = None,
    generator: torch.Generator | None = None,
    *,
    seeds: Tensor | None = None,
) -> InlierSets:
    """Sample inlier sets of P patches with N Langevin particles each, all in one batch.

    Args:
        M: (P, m, m) affinity, symmetric, in [0, 1], unit diagonal on valid associations and zero
            on padded rows / columns; dense or sparse COO (as `matching.affinity.affinity` returns),
            or `AffinityEntries` (`matching.affinity.affinity_entries`; pruning then never builds
            the full matrix).
        valid: (P, m) bool, real associations.
        pairs: (P, m, 2) int64 (ground index, aerial index) of each association (-1 on padding);
            used for the one-to-one check.
        cfg: sampler parameters; defaults to `ParticleConfig()`.
        generator: source of the per-patch seeds; default a generator seeded with `cfg.seed`.
        seeds: (P,) int64 explicit per-patch seeds (overrides `generator`); patch p's result
            depends only on (M[p], valid[p], pairs[p], seeds[p]).

    Returns:
        `InlierSets` with S = the largest number of unique accepted sets over the patches.
    """
    cfg = cfg or ParticleConfig()
    problem = sampler_problem(M, valid, pairs, cfg)
    if seeds is None:
        if generator is None:
            generator = torch.Generator(device=valid.device).manual_seed(cfg.seed)
        seeds = patch_seeds(len(valid), generator)
    return sample_problem(problem, cfg, seeds)


def _sample(M: _BlockRows, valid: Tensor, pairs: Tensor, cfg: ParticleConfig, seeds: Tensor) -> InlierSets:
    """`sample_inlier_sets` on the (possibly pruned) problem."""
    dtype = M.value.dtype
    d = valid.to(dtype).sum(-1)
    penalised = _penalised(M, d)
    with stage("langevin"):  # the loop alone: most of a match (bench_matching.py separates it)
        x, iterations = _run_dynamics(penalised, d, valid, cfg, seeds)

    masks, size, one_to_one = _rounded_sets(penalised, d, valid, pairs, x, cfg.rounding)
    keep = (size >= cfg.min_set_size) & one_to_one
    order, masks_s, first, counts = _merge(masks, keep)

    # Rank the unique sets by J, padding last; S = the most unique sets any patch has (at least
    # one padded column, so that downstream gathers never see an empty axis).
    n_sets = max(int(first.sum(1).max()), 1)
    maskf = masks_s.to(dtype)
    J = (_BlockOperator(M)(maskf.transpose(1, 2)).transpose(1, 2) * maskf).sum(-1) / size.gather(1, order).clamp_min(1).to(dtype)
    rank = torch.sort(J.masked_fill(~first, float("-inf")), dim=1, descending=True, stable=True).indices[:, :n_sets]
    out_valid = first.gather(1, rank)
    return InlierSets(
        masks=_rows(masks_s, rank) & out_valid[..., None],
        counts=counts.gather(1, rank),
        objective=J.gather(1, rank).masked_fill(~out_valid, 0.0),
        valid=out_valid,
        iterations=iterations,
        n_particles=cfg.n_particles,
    )

"""What the particle sampler runs on: `SamplerProblem`, the affinities of P patches over all their
associations or the best supported k of them (`support_pruning`: two-step walk counts on the
affinity graph)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from meridian_torch.config.matching import ParticleConfig
from meridian_torch.matching.affinity import AffinityEntries
from meridian_torch.matching.kernels import renumbered_entries, support_walks

__all__ = ["SamplerProblem", "sampler_problem", "support_pruning"]


@dataclass(frozen=True)
class SamplerProblem:
    """What the sampler runs on for P patches: their affinities over k <= m associations (all m,
    or the best supported k of `support_pruning`) and where those sit among the m.

    Attributes:
        entries: (P, k, k) affinity as `AffinityEntries` (unit diagonal on entries.valid).
        pairs: (P, k, 2) int64 (ground index, aerial index) of each association (-1 on padding).
        index: (P, k) int64 position among the m associations (m on padding).
        m: the length of the association axis the sets are reported over.
    """

    entries: AffinityEntries
    pairs: Tensor
    index: Tensor
    m: int


def support_pruning(
    M: Tensor | AffinityEntries, valid: Tensor, pairs: Tensor, k: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Keep the k associations per patch with the largest two-step walk count w = M' (M' 1),
    M' = M without its diagonal (the weighted number of paths of length two, which grows with
    the square of the size of a consistent set an association belongs to); associations with no
    off-diagonal support are always dropped (they cannot join a set of two or more).

    Args: M (P, m, m) dense or sparse COO, or its `AffinityEntries`; valid (P, m) bool; pairs
        (P, m, 2) int64; k >= 1.

    Returns:
        M_kept (P, k', k') sparse COO (unit diagonal on kept associations), valid_kept (P, k'),
        pairs_kept (P, k', 2) and index (P, k') int64 into the m associations (m on padding),
        k' = min(k, m). Kept associations stay in their original order, so a patch's result does
        not depend on the others.
    """
    kept = _prune(M, valid, pairs, k)
    return kept.entries.to_sparse(), kept.entries.valid, kept.pairs, kept.index


def _upper_entries(M: Tensor, valid: Tensor) -> AffinityEntries:
    """The strict upper triangle of a dense or sparse COO (P, m, m) affinity as `AffinityEntries`."""
    M = (M if M.is_sparse else M.to_sparse()).coalesce()
    upper = M.indices()[1] < M.indices()[2]
    return AffinityEntries(M.indices()[:, upper].T, M.values()[upper], valid)


def _prune(
    M: Tensor | AffinityEntries, valid: Tensor, pairs: Tensor, k: int, compiled: bool | None = None
) -> SamplerProblem:
    """`support_pruning` as a `SamplerProblem` (the kept entries without their diagonal).
    `compiled` (default: on CPU tensors) walks the entries in compiled passes (`kernels.support_walks`,
    `kernels.renumbered_entries`; as ~15 torch ops over a match's ~400k entries they took 5 % of
    it), else in torch's (other devices): the same numbers."""
    n_patches, m = valid.shape
    entries = M if isinstance(M, AffinityEntries) else _upper_entries(M, valid)
    index, value = entries.index, entries.value
    validf = valid.to(value.dtype)
    compiled = valid.device.type == "cpu" if compiled is None else compiled
    if compiled:
        degree, walk = (torch.from_numpy(a) for a in support_walks(
            index.contiguous().numpy(), value.contiguous().numpy(), validf.contiguous().numpy()))
    else:
        (b, i, j) = index.T

        def times(x: Tensor) -> Tensor:  # M' x for x (P, m), from the upper-triangle entries
            out = torch.zeros(n_patches * m, dtype=x.dtype, device=x.device)
            out.index_add_(0, b * m + i, value * x[b, j]).index_add_(0, b * m + j, value * x[b, i])
            return out.view(n_patches, m)

        degree = times(validf) * validf
        walk = times(degree)
    score = walk.masked_fill(~valid | (degree <= 0), float("-inf"))
    k = min(k, m)
    top = torch.sort(score, dim=1, descending=True, stable=True).indices[:, :k]
    kept_index = torch.sort(top, dim=1).values
    kept_valid = torch.isfinite(score.gather(1, kept_index))
    kept_index = kept_index.masked_fill(~kept_valid, m)
    new_of_old = torch.full((n_patches, m + 1), -1, dtype=torch.int64, device=valid.device)
    new_of_old.scatter_(1, kept_index, torch.arange(k, device=valid.device).expand(n_patches, k).contiguous())
    new_of_old[:, m] = -1
    if compiled:
        kept = AffinityEntries(*(torch.from_numpy(a) for a in renumbered_entries(
            index.contiguous().numpy(), value.contiguous().numpy(), new_of_old.numpy())), kept_valid)
    else:
        ni, nj = new_of_old[b, i], new_of_old[b, j]
        use = (ni >= 0) & (nj >= 0)
        kept = AffinityEntries(torch.stack([b[use], ni[use], nj[use]], 1), value[use], kept_valid)
    pairs_kept = torch.cat([pairs, pairs.new_full((n_patches, 1, 2), -1)], 1).gather(1, kept_index[..., None].expand(-1, -1, 2))
    return SamplerProblem(kept, pairs_kept, kept_index, m)


def sampler_problem(M: Tensor | AffinityEntries, valid: Tensor, pairs: Tensor, cfg: ParticleConfig) -> SamplerProblem:
    """The problem `sample_inlier_sets` samples: pruned to `cfg.max_associations` when set and
    smaller than m, else all m associations (arguments as there)."""
    n_patches, m = valid.shape
    if tuple(M.shape) != (n_patches, m, m) or tuple(pairs.shape) != (n_patches, m, 2):
        raise ValueError(f"expected M (P, m, m) and pairs (P, m, 2) for valid {tuple(valid.shape)}, "
                         f"got {tuple(M.shape)} and {tuple(pairs.shape)}")
    if cfg.max_associations is not None and cfg.max_associations < m:
        return _prune(M, valid, pairs, cfg.max_associations)
    entries = M if isinstance(M, AffinityEntries) else _upper_entries(M, valid)
    index = torch.arange(m, device=valid.device).expand(n_patches, m).masked_fill(~valid, m)
    return SamplerProblem(entries, pairs, index, m)

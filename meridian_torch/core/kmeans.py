"""Seeded spherical (cosine) k-means on L2-normalized vectors."""

from __future__ import annotations

import torch

__all__ = ["cosine_kmeans"]


def cosine_kmeans(
    x: torch.Tensor, k: int, *, iterations: int = 30, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cluster rows of `x` (N, D) by cosine similarity: returns centres (k', D) and labels (N,).

    k' = min(k, N). Initialization is k-means++ on cosine distance with the given generator, so
    a seeded generator gives identical clusters on every run.
    """
    x = torch.nn.functional.normalize(x, dim=1)
    n = x.shape[0]
    k = min(k, n)
    if k == 0:
        return x.new_zeros(0, x.shape[1]), torch.zeros(0, dtype=torch.int64, device=x.device)
    first = torch.randint(n, (1,), generator=generator, device="cpu").item()
    centres = [x[first]]
    for _ in range(1, k):
        dist = (1.0 - x @ torch.stack(centres).T).clamp_min(0).min(dim=1).values
        weights = dist.cpu() + 1e-12
        centres.append(x[torch.multinomial(weights, 1, generator=generator).item()])
    c = torch.stack(centres)
    labels = torch.zeros(n, dtype=torch.int64, device=x.device)
    for _ in range(iterations):
        new_labels = (x @ c.T).argmax(dim=1)
        sums = torch.zeros_like(c).index_add_(0, new_labels, x)
        empty = sums.norm(dim=1) == 0
        c = torch.where(empty[:, None], c, torch.nn.functional.normalize(sums, dim=1))
        if torch.equal(new_labels, labels):
            break
        labels = new_labels
    return c, labels

"""Seeded degradation of a primitive set (missing, spurious and noisy primitives), to measure
how matching holds up when perception is worse than the renderer's.

Of N points (and, separately, of N lines) round(missing x N) are dropped, round(spurious x N)
spurious ones are added (fractions of the original count), and every kept coordinate gets
Gaussian noise of `noise_m` per axis (a line's two endpoints independently). A spurious
primitive is a copy of a random primitive of the same kind (its descriptor; for lines also the
kind and length) placed uniformly in the axis-aligned extent of the original set (a line by its
midpoint, at a uniform orientation); its segment id is new. All zero returns the set unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from meridian_torch.types import PrimitiveSet

__all__ = ["Perturbation", "parse_perturbation", "perturb_primitives"]


@dataclass(frozen=True)
class Perturbation:
    """Fractions of primitives dropped (`missing`, in [0, 1]) and added (`spurious`, >= 0), and
    the standard deviation of the coordinate noise (`noise_m`, metres)."""

    missing: float = 0.0
    spurious: float = 0.0
    noise_m: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.missing <= 1.0:
            raise ValueError(f"Perturbation.missing: expected a fraction in [0, 1], got {self.missing}")
        if self.spurious < 0.0:
            raise ValueError(f"Perturbation.spurious: expected >= 0, got {self.spurious}")
        if self.noise_m < 0.0:
            raise ValueError(f"Perturbation.noise_m: expected >= 0, got {self.noise_m}")

    @property
    def is_identity(self) -> bool:
        return self.missing == 0.0 and self.spurious == 0.0 and self.noise_m == 0.0


def parse_perturbation(text: str) -> Perturbation:
    """`"missing=0.4,spurious=0.2,noise_m=1.0"` (any subset, in any order; "" = none)."""
    values: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or key.strip() not in Perturbation.__dataclass_fields__:
            raise ValueError(f"perturbation {text!r}: expected key=value with keys missing, spurious, noise_m; got {item!r}")
        try:
            values[key.strip()] = float(value)
        except ValueError:
            raise ValueError(f"perturbation {text!r}: {key.strip()} = {value!r} is not a number") from None
    return Perturbation(**values)


def _keep_and_spurious(rng: np.random.Generator, n: int, p: Perturbation) -> tuple[np.ndarray, np.ndarray]:
    """Sorted indices kept (n - round(missing n)) and the template index of each spurious copy."""
    keep = np.sort(rng.permutation(n)[: n - int(round(p.missing * n))])
    n_spurious = int(round(p.spurious * n)) if n else 0
    return keep, rng.integers(0, max(n, 1), size=n_spurious)


def perturb_primitives(primitives: PrimitiveSet, perturbation: Perturbation, seed: int) -> PrimitiveSet:
    """`primitives` degraded by `perturbation`; one seed gives one result (see the module docstring)."""
    if perturbation.is_identity:
        return primitives
    p, rng = primitives, np.random.default_rng(seed)
    pts, lns = p.points_xy.double().cpu().numpy(), p.line_endpoints.double().cpu().numpy()
    corners = np.concatenate([pts, lns.reshape(-1, 2)])
    low, high = (corners.min(0), corners.max(0)) if len(corners) else (np.zeros(2), np.zeros(2))
    ids = torch.cat([p.point_segment_ids, p.line_segment_ids])
    next_id = int(ids.max()) + 1 if len(ids) else 0

    keep_pt, tmpl_pt = _keep_and_spurious(rng, len(pts), perturbation)
    keep_ln, tmpl_ln = _keep_and_spurious(rng, len(lns), perturbation)
    new_pts = np.concatenate([
        pts[keep_pt] + rng.normal(0.0, perturbation.noise_m, (len(keep_pt), 2)),
        rng.uniform(low, high, (len(tmpl_pt), 2)),
    ])
    length = np.linalg.norm(lns[:, 1] - lns[:, 0], axis=-1)[tmpl_ln] if len(lns) else np.zeros(0)
    angle = rng.uniform(-np.pi, np.pi, len(tmpl_ln))
    half = 0.5 * length[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    mid = rng.uniform(low, high, (len(tmpl_ln), 2))
    new_lns = np.concatenate([
        lns[keep_ln] + rng.normal(0.0, perturbation.noise_m, (len(keep_ln), 2, 2)),
        np.stack([mid - half, mid + half], 1),
    ])

    device = p.points_xy.device

    def rows(x: torch.Tensor, keep: np.ndarray, template: np.ndarray) -> torch.Tensor:
        return x[torch.as_tensor(np.concatenate([keep, template]), dtype=torch.long, device=x.device)]

    def fresh(n: int, start: int) -> torch.Tensor:
        return torch.arange(start, start + n, dtype=torch.int64, device=device)

    keep_pt_t = torch.as_tensor(keep_pt, dtype=torch.long, device=device)
    keep_ln_t = torch.as_tensor(keep_ln, dtype=torch.long, device=device)
    return PrimitiveSet(
        points_xy=torch.as_tensor(new_pts, dtype=p.points_xy.dtype, device=device),
        point_descriptors=rows(p.point_descriptors, keep_pt, tmpl_pt),
        point_segment_ids=torch.cat([p.point_segment_ids[keep_pt_t], fresh(len(tmpl_pt), next_id)]),
        line_endpoints=torch.as_tensor(new_lns, dtype=p.line_endpoints.dtype, device=device),
        line_kinds=rows(p.line_kinds, keep_ln, tmpl_ln),
        line_descriptors=rows(p.line_descriptors, keep_ln, tmpl_ln),
        line_segment_ids=torch.cat([p.line_segment_ids[keep_ln_t], fresh(len(tmpl_ln), next_id + len(tmpl_pt))]),
    )

"""Public matching entry point: one ground submap against P aerial patches, all at once.

associations -> affinity -> inlier sets (Langevin particles, or CLIPPER) -> batched SE(2)
registration of every set -> greedy clustering into L weighted hypotheses T_world_odom.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from meridian_torch.matching.affinity import affinity
from meridian_torch.matching.associations import putative_associations
from meridian_torch.matching.clipper import solve_clipper
from meridian_torch.matching.config import MatchConfig
from meridian_torch.matching.hypotheses import Hypotheses, cluster_hypotheses
from meridian_torch.matching.particles import InlierSets, sample_inlier_sets
from meridian_torch.types import PrimitiveBatch, PrimitiveSet, stack_primitive_sets

__all__ = ["match_submap", "match_arrays"]


def _clipper_sets(M: Tensor, valid: Tensor, config: MatchConfig, generator: torch.Generator | None) -> InlierSets:
    """One CLIPPER set per patch as an `InlierSets` with a single particle (probability 1)."""
    dense = M.to_dense() if M.is_sparse else M
    result = solve_clipper(dense, valid=valid, generator=generator, cfg=config.clipper)
    masks = result.inliers[:, None, :]
    ok = masks.sum(-1) >= config.particles.min_set_size
    return InlierSets(
        masks=masks & ok[..., None],
        counts=ok.to(torch.int64),
        objective=result.score[:, None].masked_fill(~ok, 0.0),
        valid=ok,
        iterations=result.iterations,
        n_particles=1,
    )


@torch.no_grad()
def match_submap(
    ground: PrimitiveSet,
    aerial: PrimitiveBatch,
    *,
    rotation_prior: Tensor | float | None = None,
    config: MatchConfig | None = None,
    generator: torch.Generator | None = None,
) -> Hypotheses:
    """Weighted SE(2) hypotheses T_world_odom of one ground submap against P aerial patches.

    Args:
        ground: the submap's primitives in the odom frame (x-y metres).
        aerial: P padded aerial patches in the world frame (metres, x east, y north).
        rotation_prior: known yaw of T_world_odom (radians), one per patch (P,) or one float for
            all; it sharpens the affinity (known-rotation mode, with
            `affinity.rotation_uncertainty_deg` slack); registration still estimates the yaw.
        config: all matching parameters; defaults to `MatchConfig()`.
        generator: seeds the solver (per-patch seeds for the particles, the start vector for
            CLIPPER); default a generator seeded with `config.particles.seed`. One seed gives
            identical output.

    Returns:
        `Hypotheses` with (P, L) entries, L = `config.hypotheses_per_patch`, heaviest first.
    """
    cfg = config or MatchConfig()
    device, dtype = aerial.points_xy.device, aerial.points_xy.dtype
    if generator is None:
        generator = torch.Generator(device=device).manual_seed(cfg.particles.seed)
    prior = None
    if rotation_prior is not None:
        prior = torch.as_tensor(rotation_prior, dtype=dtype, device=device).expand(len(aerial)).contiguous()
    ac = cfg.associations
    assoc = putative_associations(
        ground, aerial, k_prim=ac.k_prim, direction=ac.direction, min_line_length_m=ac.min_line_length_m
    )
    M = affinity(ground, aerial, assoc, cfg.affinity, rotation_prior=prior)
    if cfg.solver == "clipper":
        sets = _clipper_sets(M, assoc.valid, cfg, generator)
    else:
        sets = sample_inlier_sets(M, assoc.valid, assoc.pairs, cfg.particles, generator)
    return cluster_hypotheses(
        sets,
        assoc,
        ground,
        aerial,
        n_hypotheses=cfg.hypotheses_per_patch,
        translation_m=cfg.cluster_translation_m,
        rotation_deg=cfg.cluster_rotation_deg,
        registration=cfg.registration,
    )


def _as_tensor(x: object, dtype: torch.dtype, shape_tail: tuple[int, ...]) -> Tensor:
    t = torch.as_tensor(x, dtype=dtype)
    return t.reshape(-1, *shape_tail)


def _primitive_set(points: object, point_desc: object, lines: object, line_kinds: object, line_desc: object) -> PrimitiveSet:
    pts = _as_tensor(points, torch.float32, (2,))
    lns = _as_tensor(lines, torch.float32, (2, 2))
    pd = torch.as_tensor(point_desc, dtype=torch.float32)
    ld = torch.as_tensor(line_desc, dtype=torch.float32)
    dim = pd.shape[-1] if pd.dim() == 2 else ld.shape[-1]
    return PrimitiveSet(
        points_xy=pts,
        point_descriptors=pd.reshape(-1, dim),
        point_segment_ids=torch.arange(pts.shape[0]),
        line_endpoints=lns,
        line_kinds=torch.as_tensor(line_kinds, dtype=torch.int64).reshape(-1),
        line_descriptors=ld.reshape(-1, dim),
        line_segment_ids=torch.arange(lns.shape[0]),
    )


def match_arrays(
    ground_points: object,
    ground_point_desc: object,
    ground_lines: object,
    ground_line_kinds: object,
    ground_line_desc: object,
    aerial_points: Sequence[object],
    aerial_point_desc: Sequence[object],
    aerial_lines: Sequence[object],
    aerial_line_kinds: Sequence[object],
    aerial_line_desc: Sequence[object],
    *,
    rotation_prior: Tensor | float | None = None,
    config: MatchConfig | None = None,
    generator: torch.Generator | None = None,
) -> Hypotheses:
    """`match_submap` on plain arrays (numpy or torch, converted to float32 / int64).

    Ground (one submap, odom frame, x-y metres):
        ground_points (Ng, 2); ground_point_desc (Ng, D);
        ground_lines (Ngl, 2, 2) two endpoints per line; ground_line_kinds (Ngl,) with
        0 = segment between the endpoints, 1 = ray from endpoint 0 through endpoint 1,
        2 = infinite line through both; ground_line_desc (Ngl, D).
    Aerial (P patches, world frame, metres, x east, y north): sequences of length P of
        points (Na_p, 2), point descriptors (Na_p, D), lines (Nal_p, 2, 2), kinds (Nal_p,)
        and line descriptors (Nal_p, D). Descriptors need not be normalised (cosines are used).

    Returns:
        `Hypotheses`; `T_world_odom[p, l]` (3 x 3) maps odom x-y into world x-y for patch p.
    """
    ground = _primitive_set(ground_points, ground_point_desc, ground_lines, ground_line_kinds, ground_line_desc)
    patches = [
        _primitive_set(*fields)
        for fields in zip(aerial_points, aerial_point_desc, aerial_lines, aerial_line_kinds, aerial_line_desc, strict=True)
    ]
    return match_submap(
        ground, stack_primitive_sets(patches), rotation_prior=rotation_prior, config=config, generator=generator
    )

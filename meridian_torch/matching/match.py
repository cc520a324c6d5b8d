"""Public matching entry point: one ground submap against P aerial patches, all at once.

associations -> affinity -> inlier sets (Langevin particles, or CLIPPER) -> batched SE(2)
registration of every set -> greedy clustering into weighted hypotheses T_world_odom ->
geometric verification (alignment of the whole submap beyond chance) -> the L best.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import torch
from torch import Tensor

from meridian_torch.config.matching import MatchConfig, ParticleConfig
from meridian_torch.core.parallel import cpu_threads, thread_map
from meridian_torch.core.timing import stage
from meridian_torch.matching.affinity import affinity, affinity_entries
from meridian_torch.matching.associations import Associations, putative_associations
from meridian_torch.matching.clipper import solve_clipper
from meridian_torch.matching.hypotheses import Hypotheses, cluster_hypotheses
from meridian_torch.matching.particle_problem import sampler_problem
from meridian_torch.matching.particles import InlierSets, patch_seeds, sample_problem
from meridian_torch.matching.verification import reweight_hypotheses
from meridian_torch.types import PrimitiveBatch, PrimitiveSet, stack_primitive_sets

__all__ = ["match_submap", "match_arrays"]

# (patch, set, set) entries clustered together; a few such tensors live at once.
_CLUSTER_ELEMENTS = 1 << 21


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


def _offset_aerial_lines(pairs: Tensor, old: int, new: Tensor | int) -> Tensor:
    """(P, m, 2) pairs with aerial line indices counted from `new` points instead of `old` (the
    padded point count; `new` per patch (P,) or one int). Points and padding (-1) stay."""
    aerial_index = pairs[..., 1]
    new = torch.as_tensor(new, device=pairs.device).reshape(-1, 1)
    aerial_index = torch.where(aerial_index >= old, aerial_index - old + new, aerial_index)
    return torch.stack([pairs[..., 0], aerial_index], dim=-1)


def _patch_chunk(assoc: Associations, aerial: PrimitiveBatch, part: Tensor) -> tuple[Associations, PrimitiveBatch]:
    """Patches `part` without the padding none of them uses, their associations re-indexed to
    the trimmed point axis (aerial line indices are offset by it). Scores are unchanged: only
    unused padding goes, and the (patch, line, line) tables shrink to the chunk's largest patch."""
    aerial_part = aerial.select(part).trimmed()
    n_points = int(aerial_part.points_xy.shape[1])
    assoc_part = dataclasses.replace(
        assoc,
        pairs=_offset_aerial_lines(assoc.pairs[part], assoc.n_aerial_points, n_points),
        is_line=assoc.is_line[part],
        valid=assoc.valid[part],
        cosine=assoc.cosine[part],
        n_aerial_points=n_points,
    )
    return assoc_part, aerial_part


def _take_patches(sets: InlierSets, index: Tensor) -> InlierSets:
    """The patches `index` of `sets`, in that order."""
    return dataclasses.replace(
        sets,
        masks=sets.masks[index],
        counts=sets.counts[index],
        objective=sets.objective[index],
        valid=sets.valid[index],
        iterations=sets.iterations[index],
    )


def _select_associations(assoc: Associations, part: Tensor) -> Associations:
    """The associations of patches `part`, in the same (untrimmed) index spaces."""
    return dataclasses.replace(
        assoc, pairs=assoc.pairs[part], is_line=assoc.is_line[part], valid=assoc.valid[part],
        cosine=assoc.cosine[part],
    )


def _take_hypotheses(h: Hypotheses, index: Tensor) -> Hypotheses:
    """The patches `index` of `h`, in that order."""
    return Hypotheses(**{f.name: getattr(h, f.name)[index] for f in dataclasses.fields(h)})


def _concat_hypotheses(parts: list[Hypotheses]) -> Hypotheses:
    """Hypotheses of consecutive patch chunks (same L and association axis) as one."""
    if len(parts) == 1:
        return parts[0]
    names = [f.name for f in dataclasses.fields(parts[0])]
    return Hypotheses(**{name: torch.cat([getattr(h, name) for h in parts]) for name in names})


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
        `Hypotheses` with (P, L) entries, L = `config.hypotheses_per_patch`, most probable first
        (alignment beyond chance with `config.verification`, particle mass alone without).
    """
    cfg = config or MatchConfig()
    device, dtype = aerial.points_xy.device, aerial.points_xy.dtype
    if generator is None:
        generator = torch.Generator(device=device).manual_seed(cfg.particles.seed)
    prior = None
    if rotation_prior is not None:
        prior = torch.as_tensor(rotation_prior, dtype=dtype, device=device).expand(len(aerial)).contiguous()
    ac = cfg.associations
    with stage("associations"):
        assoc = putative_associations(
            ground, aerial, k_prim=ac.k_prim, direction=ac.direction, min_line_length_m=ac.min_line_length_m
        )
    if cfg.solver == "clipper":
        with stage("affinity"):
            M = affinity(ground, aerial, assoc, cfg.affinity, rotation_prior=prior)
        with stage("clipper"):
            sets = _clipper_sets(M, assoc.valid, cfg, generator)
        return _hypotheses(sets, ground, aerial, assoc, cfg)
    # Seeds are drawn per patch up front, so a patch's result does not depend on its group.
    seeds = patch_seeds(len(aerial), generator)
    groups = _patch_groups(aerial, cfg.patch_chunk)
    # A group's sets, hypotheses and alignment depend on its patches alone, so on the CPU the
    # groups run side by side, one torch thread each: every stage after the associations uses
    # every core, not only the Langevin loop (the rest are one-thread kernels and small ops).
    # The groups are the same for any thread count, and so are the results (a lone group runs on
    # the caller's threads, as every match did before).
    threads = cpu_threads() if device.type == "cpu" else 1
    particles = cfg.particles  # the sampler's settings, chosen once for every group
    if prior is None:
        particles = particles.model_copy(update={"start_scale": particles.start_scale_free_rotation})
    parts = thread_map(
        lambda group: _group_hypotheses(ground, aerial, assoc, prior, seeds, group, cfg, particles),
        groups,
        threads,
        torch_threads_each=1,
    )
    return _take_hypotheses(_concat_hypotheses(parts), torch.argsort(torch.cat(groups)))


def _patch_groups(aerial: PrimitiveBatch, size: int) -> list[Tensor]:
    """The patches by size (most lines first) in ceil(P / size) groups of at most `size`, so that
    each group's tables are padded only to patches like its own. The groups are as equal as can
    be (25 patches in groups of at most 8: 7, 6, 6, 6, not 8, 8, 8, 1), so that threads taking
    them finish together."""
    by_size = torch.argsort(aerial.used_lengths()[1], descending=True, stable=True)
    return list(by_size.tensor_split(max(1, -(-len(by_size) // size))))


def _group_hypotheses(
    ground: PrimitiveSet, aerial: PrimitiveBatch, assoc: Associations, prior: Tensor | None, seeds: Tensor,
    group: Tensor, cfg: MatchConfig, particles: ParticleConfig,
) -> Hypotheses:
    """Particle sets (sampled with `particles`) and hypotheses of the patches `group` (seeds: one
    per patch of `aerial`)."""
    assoc_g, aerial_g = _patch_chunk(assoc, aerial, group)
    with stage("affinity"):
        M = affinity_entries(ground, aerial_g, assoc_g, cfg.affinity, rotation_prior=None if prior is None else prior[group])
    with stage("pruning"):
        problem = sampler_problem(M, assoc_g.valid, assoc_g.pairs, cfg.particles)
    del M
    with stage("particles"):
        sets = sample_problem(problem, particles, seeds[group])
    return _hypotheses(sets, ground, aerial.select(group), _select_associations(assoc, group), cfg)


def _hypotheses(
    sets: InlierSets, ground: PrimitiveSet, aerial: PrimitiveBatch, assoc: Associations, cfg: MatchConfig
) -> Hypotheses:
    """Registration, clustering and (if enabled) verification of the patches' inlier sets."""
    verify = cfg.verification
    n_clustered = max(verify.candidates, cfg.hypotheses_per_patch) if verify.enabled else cfg.hypotheses_per_patch
    # Clustering compares every pair of a patch's sets, (P, S, S): a group of patches at a time, so
    # that its peak memory does not grow with the number of patches (609 patches: 2.1 -> 1.1 GB).
    group = max(1, _CLUSTER_ELEMENTS // max(int(sets.masks.shape[1]) ** 2, 1))
    hypotheses = _concat_hypotheses([
        cluster_hypotheses(
            _take_patches(sets, part),
            _select_associations(assoc, part),
            ground,
            aerial.select(part),
            n_hypotheses=n_clustered,
            translation_m=cfg.cluster_translation_m,
            rotation_deg=cfg.cluster_rotation_deg,
            registration=cfg.registration,
        )
        for part in torch.arange(len(aerial), device=sets.masks.device).split(group)
    ])
    if not verify.enabled:
        return hypotheses
    with stage("verification"):
        return reweight_hypotheses(hypotheses, ground, aerial, verify, cfg.hypotheses_per_patch)


def _array(x: object, name: str, tail: tuple[int, ...], dtype: torch.dtype) -> Tensor:
    """`x` (numpy, torch, nested lists) as a CPU tensor of shape (N, *tail); an empty input of
    any shape counts as N = 0. Wrong shapes and non-finite values raise ValueError naming `name`."""
    if x is None:
        raise ValueError(f"{name}: expected an array of shape (N, {', '.join(map(str, tail))}), got None")
    try:
        t = torch.as_tensor(x).detach().cpu()
    except (TypeError, ValueError, RuntimeError) as error:
        raise ValueError(f"{name}: not convertible to an array ({error})") from None
    if t.numel() == 0:
        return torch.zeros((0, *tail), dtype=dtype)
    if t.dim() != 1 + len(tail) or tuple(t.shape[1:]) != tail:
        want = "(N" + "".join(f", {n}" for n in tail) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {tuple(t.shape)}")
    if t.is_complex() or t.dtype == torch.bool:
        raise ValueError(f"{name}: expected real numbers, got dtype {t.dtype}")
    if not dtype.is_floating_point and t.is_floating_point() and not bool((t == t.round()).all()):
        raise ValueError(f"{name}: expected integers, got {t[t != t.round()][0].item()}")
    t = t.to(dtype)
    if dtype.is_floating_point and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return t


def _descriptors(x: object, name: str, n: int) -> Tensor:
    """(n, D) float32 descriptors; (0, 0) when n == 0 and the input is empty."""
    if x is None:
        raise ValueError(f"{name}: expected an array of shape ({n}, D), got None")
    t = torch.as_tensor(x).detach().cpu()
    if t.numel() == 0 and n == 0:
        return torch.zeros((0, t.shape[-1] if t.dim() == 2 else 0), dtype=torch.float32)
    if t.dim() != 2 or t.shape[0] != n or t.shape[1] == 0:
        raise ValueError(f"{name}: expected shape ({n}, D), one descriptor per primitive, got {tuple(t.shape)}")
    t = t.to(torch.float32)
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return t


def _primitive_set(
    points: object, point_desc: object, lines: object, line_kinds: object, line_desc: object, names: tuple[str, ...]
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Validated (points, point descriptors, lines, kinds, line descriptors) of one primitive set."""
    pts = _array(points, names[0], (2,), torch.float32)
    lns = _array(lines, names[2], (2, 2), torch.float32)
    kinds = _array(line_kinds, names[3], (), torch.int64)
    if kinds.shape[0] != lns.shape[0]:
        raise ValueError(f"{names[3]}: expected {lns.shape[0]} kinds (one per line), got {kinds.shape[0]}")
    if bool(((kinds < 0) | (kinds > 2)).any()):
        raise ValueError(f"{names[3]}: kinds must be 0 (segment), 1 (ray) or 2 (infinite line)")
    if bool(((lns[:, 1] - lns[:, 0]).norm(dim=-1) <= 0).any()):
        raise ValueError(f"{names[2]}: a line's two endpoints coincide (its direction is undefined)")
    return pts, _descriptors(point_desc, names[1], pts.shape[0]), lns, kinds, _descriptors(line_desc, names[4], lns.shape[0])


def _with_dim(fields: tuple[Tensor, ...], dim: int) -> PrimitiveSet:
    pts, pd, lns, kinds, ld = fields
    pd = pd if pd.shape[0] else pd.new_zeros(0, dim)
    ld = ld if ld.shape[0] else ld.new_zeros(0, dim)
    return PrimitiveSet(pts, pd, torch.arange(pts.shape[0]), lns, kinds, ld, torch.arange(lns.shape[0]))


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
    rotation_prior: object = None,
    config: MatchConfig | None = None,
    generator: torch.Generator | None = None,
) -> Hypotheses:
    """`match_submap` on plain arrays: numpy arrays, torch tensors or nested lists (CPU, float32).

    Ground (one submap, odom frame, x-y metres):
        ground_points (Ng, 2); ground_point_desc (Ng, D);
        ground_lines (Ngl, 2, 2) two endpoints per line; ground_line_kinds (Ngl,) integers with
        0 = segment between the endpoints, 1 = ray from endpoint 0 through endpoint 1,
        2 = infinite line through both; ground_line_desc (Ngl, D).
    Aerial (P patches, world frame, metres, x east, y north, right-handed): five sequences of
        length P with each patch's points (Na_p, 2), point descriptors (Na_p, D), lines
        (Nal_p, 2, 2), kinds (Nal_p,) and line descriptors (Nal_p, D).
    Any of these may be empty (no points, no lines, or a patch without primitives; an empty
    array of any shape, e.g. `np.zeros((0, 2))` or `[]`). Descriptors need not be normalised
    (cosines are used); D must be the same everywhere.

    Args:
        rotation_prior: known yaw of T_world_odom in radians (a float for all patches, or P
            values); None = unknown rotation.
        config: matching parameters (default `MatchConfig()`); generator: seeds the solver.

    Returns:
        `Hypotheses` with P rows: `T_world_odom[p, l]` (3 x 3 homogeneous SE(2)) maps odom x-y
        into world x-y for patch p, most probable first; `probability`, `valid` and
        `association_mask` as documented there (float32 on the CPU). `pairs[p, k]` =
        (ground index, aerial index), each counting points first, then lines: ground line i is
        Ng + i, aerial line j of patch p is Na_p + j (patch p's own point count); -1 on padding.
        Patches without usable associations get only invalid rows (valid False, probability 0).

    Raises:
        ValueError: naming the argument, on wrong shapes, non-finite values, unknown line kinds,
            lines with coinciding endpoints, descriptor dimensions that differ, sequences of
            different lengths, no patch at all, or a rotation prior of the wrong size.
    """
    names = ("points", "point_desc", "lines", "line_kinds", "line_desc")
    ground = _primitive_set(
        ground_points, ground_point_desc, ground_lines, ground_line_kinds, ground_line_desc,
        tuple(f"ground_{n}" for n in names),
    )
    sequences = (aerial_points, aerial_point_desc, aerial_lines, aerial_line_kinds, aerial_line_desc)
    for name, seq in zip(names, sequences):
        if isinstance(seq, (str, bytes)) or not hasattr(seq, "__len__"):
            raise ValueError(f"aerial_{name}: expected a sequence with one array per patch")
    lengths = {f"aerial_{n}": len(seq) for n, seq in zip(names, sequences)}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"aerial sequences must have one entry per patch, got lengths {lengths}")
    n_patches = len(aerial_points)
    if n_patches == 0:
        raise ValueError("aerial_points: at least one aerial patch is needed")
    patches = [
        _primitive_set(*fields, tuple(f"aerial_{n}[{p}]" for n in names))
        for p, fields in enumerate(zip(*sequences))
    ]
    described = [("ground_point_desc", ground[1]), ("ground_line_desc", ground[4])] + [
        (f"aerial_{kind}[{p}]", fields[k]) for p, fields in enumerate(patches)
        for kind, k in (("point_desc", 1), ("line_desc", 4))
    ]
    described = [(name, int(d.shape[1])) for name, d in described if d.shape[0]]
    for name, d in described[1:]:
        if d != described[0][1]:
            raise ValueError(f"{name}: descriptors of dimension {d}, but {described[0][0]} has "
                             f"{described[0][1]}; D must be the same everywhere")
    dim = described[0][1] if described else 1
    prior = None
    if rotation_prior is not None:
        try:
            flat = torch.as_tensor(rotation_prior).reshape(-1)
        except (TypeError, ValueError, RuntimeError) as error:
            raise ValueError(f"rotation_prior: not convertible to an array ({error})") from None
        prior = _array(flat, "rotation_prior", (), torch.float32)
        if prior.shape[0] not in (1, n_patches):
            raise ValueError(f"rotation_prior: expected one yaw or {n_patches} (one per patch), got {prior.shape[0]}")
    aerial = stack_primitive_sets([_with_dim(p, dim) for p in patches])
    hypotheses = match_submap(_with_dim(ground, dim), aerial, rotation_prior=prior, config=config, generator=generator)
    # Internally aerial line j of every patch is (padded point count) + j; a caller indexes each
    # patch's own arrays: (its number of points) + j.
    n_points = torch.tensor([p[0].shape[0] for p in patches])
    pairs = _offset_aerial_lines(hypotheses.pairs, int(aerial.points_xy.shape[1]), n_points)
    return dataclasses.replace(hypotheses, pairs=pairs)

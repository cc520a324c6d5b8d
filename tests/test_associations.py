"""Putative associations: batched K-NN over patches equals a per-patch, per-primitive loop."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from meridian_torch.config.matching import AssociationConfig
from meridian_torch.matching import associations
from meridian_torch.matching.associations import putative_associations
from meridian_torch.types import LineKind, PrimitiveSet, stack_primitive_sets


def _settings(**overrides) -> dict:
    """The shipped association settings (the config's defaults) with `overrides`."""
    return {**AssociationConfig().model_dump(), **overrides}


def random_set(n_points: int, n_lines: int, dim: int, gen: torch.Generator, short_fraction: float = 0.3) -> PrimitiveSet:
    """Random primitives; about `short_fraction` of the lines are shorter than 2 m."""
    e0 = torch.rand(n_lines, 2, generator=gen, dtype=torch.float64) * 50
    angle = torch.rand(n_lines, generator=gen, dtype=torch.float64) * math.pi
    short = torch.rand(n_lines, generator=gen) < short_fraction
    length = torch.where(short, 0.5 + torch.rand(n_lines, generator=gen, dtype=torch.float64), 3 + 10 * torch.rand(n_lines, generator=gen, dtype=torch.float64))
    e1 = e0 + length[:, None] * torch.stack([angle.cos(), angle.sin()], dim=1)
    desc = lambda n: torch.nn.functional.normalize(torch.randn(n, dim, generator=gen, dtype=torch.float64), dim=1)  # noqa: E731
    return PrimitiveSet(
        points_xy=torch.rand(n_points, 2, generator=gen, dtype=torch.float64) * 50,
        point_descriptors=desc(n_points),
        point_segment_ids=torch.arange(n_points),
        line_endpoints=torch.stack([e0, e1], dim=1),
        line_kinds=torch.randint(0, 3, (n_lines,), generator=gen),
        line_descriptors=desc(n_lines),
        line_segment_ids=torch.arange(n_lines),
    )


def usable_lines(s: PrimitiveSet, min_len: float) -> list[bool]:
    out = []
    for e, k in zip(s.line_endpoints.tolist(), s.line_kinds.tolist()):
        length = math.dist(e[0], e[1])
        out.append(length > 0 and (k != int(LineKind.SEGMENT) or length >= min_len))
    return out


def loop_reference(ground: PrimitiveSet, patches: list[PrimitiveSet], k: int, union: bool, min_len: float) -> list[dict]:
    """Per patch: {(ground index, aerial index in the batch's unified space): cosine}."""
    n_gp = ground.points_xy.shape[0]
    n_ap = max(p.points_xy.shape[0] for p in patches)
    out = []
    for patch in patches:
        pairs: dict[tuple[int, int], float] = {}
        for kind in ("points", "lines"):
            gd = ground.point_descriptors if kind == "points" else ground.line_descriptors
            ad = patch.point_descriptors if kind == "points" else patch.line_descriptors
            g_ok = [True] * gd.shape[0] if kind == "points" else usable_lines(ground, min_len)
            a_ok = [True] * ad.shape[0] if kind == "points" else usable_lines(patch, min_len)
            g_off, a_off = (0, 0) if kind == "points" else (n_gp, n_ap)

            def cos(gi, ai, gd=gd, ad=ad):
                return float(gd[gi] @ ad[ai])

            jitter = associations.tie_break_jitter(gd.shape[0], ad.shape[0], torch.device("cpu"))

            def rank_key(gi, ai, jitter=jitter):
                # descending similarity as float32; exact ties by the fixed (ground, aerial) hash
                return (-float(np.float32(cos(gi, ai))), -float(jitter[gi, ai]))

            g_ids = [i for i, ok in enumerate(g_ok) if ok]
            a_ids = [i for i, ok in enumerate(a_ok) if ok]
            for gi in g_ids:
                for ai in sorted(a_ids, key=lambda a: rank_key(gi, a))[:k]:
                    pairs[(gi + g_off, ai + a_off)] = cos(gi, ai)
            if union:
                for ai in a_ids:
                    for gi in sorted(g_ids, key=lambda g: rank_key(g, ai))[:k]:
                        pairs[(gi + g_off, ai + a_off)] = cos(gi, ai)
        out.append(pairs)
    return out


@pytest.mark.parametrize("direction", ["ground_to_aerial", "union"])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("patches_per_chunk", [None, 1, 3])
def test_batched_topk_equals_loop(direction: str, seed: int, patches_per_chunk: int | None,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    gen = torch.Generator().manual_seed(seed)
    ground = random_set(9, 8, 16, gen)
    # Different sizes per patch, so the batch carries padding on both types.
    patches = [random_set(n_p, n_l, 16, gen) for n_p, n_l in ((12, 10), (3, 2), (7, 14), (0, 5))]
    k = 4
    batch = stack_primitive_sets(patches)
    whole = putative_associations(ground, batch, k_prim=k, direction=direction, min_line_length_m=2.0)
    if patches_per_chunk is not None:  # similarities ranked a few patches at a time: the same result
        monkeypatch.setattr(associations, "_SIMILARITY_ELEMENTS", patches_per_chunk * 9 * 14)
    assoc = putative_associations(ground, batch, k_prim=k, direction=direction, min_line_length_m=2.0)
    for name in ("pairs", "valid", "is_line"):
        assert torch.equal(getattr(assoc, name), getattr(whole, name))
    # the similarity product's rounding may depend on the batch's size (BLAS blocking)
    torch.testing.assert_close(assoc.cosine, whole.cosine, rtol=0, atol=1e-12)
    ref = loop_reference(ground, patches, k, direction == "union", 2.0)
    for p in range(len(patches)):
        v = assoc.valid[p]
        got = {tuple(pair): c for pair, c in zip(assoc.pairs[p][v].tolist(), assoc.cosine[p][v].tolist())}
        assert set(got) == set(ref[p])
        for key, c in ref[p].items():
            assert got[key] == pytest.approx(c, abs=1e-12)
        # valid pairs first, each block sorted by (ground index, aerial index)
        for block in (~assoc.is_line[p], assoc.is_line[p]):
            flags = v[block]
            assert not (~flags[:-1] & flags[1:]).any()
            keys = [tuple(x) for x in assoc.pairs[p][block][flags].tolist()]
            assert keys == sorted(keys)
        # Padding is marked, and the point / line blocks hold their own type only.
        assert (assoc.pairs[p][~v] == -1).all() and (assoc.cosine[p][~v] == 0).all()
        g_idx, a_idx = assoc.pairs[p, :, 0], assoc.pairs[p, :, 1]
        is_line = assoc.is_line[p]
        assert (is_line == (torch.arange(assoc.size) >= assoc.n_point_assoc)).all()
        assert (g_idx[v & ~is_line] < assoc.n_ground_points).all() and (g_idx[v & is_line] >= assoc.n_ground_points).all()
        assert (a_idx[v & ~is_line] < assoc.n_aerial_points).all() and (a_idx[v & is_line] >= assoc.n_aerial_points).all()
    # ground_to_aerial bounds the size by k per ground primitive.
    if direction == "ground_to_aerial":
        assert int(assoc.valid.sum(1).max()) <= k * (9 + 8)


def with_shared_descriptors(s: PrimitiveSet, n_distinct: int, gen: torch.Generator) -> PrimitiveSet:
    """`s` with every descriptor drawn from `n_distinct` vectors, as when primitives share their segment's."""
    dim = s.line_descriptors.shape[1]
    table = torch.nn.functional.normalize(torch.randn(n_distinct, dim, generator=gen, dtype=torch.float64), dim=1)
    pick = lambda n: table[torch.randint(0, n_distinct, (n,), generator=gen)]  # noqa: E731
    return PrimitiveSet(
        points_xy=s.points_xy,
        point_descriptors=pick(s.points_xy.shape[0]),
        point_segment_ids=s.point_segment_ids,
        line_endpoints=s.line_endpoints,
        line_kinds=s.line_kinds,
        line_descriptors=pick(s.line_endpoints.shape[0]),
        line_segment_ids=s.line_segment_ids,
    )


@pytest.mark.parametrize("direction", ["ground_to_aerial", "union"])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_tied_similarities_do_not_depend_on_the_other_patches(direction: str, seed: int) -> None:
    # Few distinct descriptors on both sides: most similarities tie, also at the k-th rank.
    gen = torch.Generator().manual_seed(seed)
    ground = with_shared_descriptors(random_set(10, 30, 8, gen), 3, gen)
    patches = [with_shared_descriptors(random_set(n_p, n_l, 8, gen), 4, gen)
               for n_p, n_l in ((6, 40), (25, 9), (11, 120), (2, 70))]
    k = 5
    together = putative_associations(ground, stack_primitive_sets(patches), k_prim=k, direction=direction, min_line_length_m=2.0)
    ref = loop_reference(ground, patches, k, direction == "union", 2.0)
    for p, patch in enumerate(patches):
        alone = putative_associations(ground, stack_primitive_sets([patch]), k_prim=k, direction=direction, min_line_length_m=2.0)
        n_points = patch.points_xy.shape[0]
        assert torch.equal(patch_local_pairs(together, p, n_points), patch_local_pairs(alone, 0, n_points))
        got = {tuple(x) for x in together.pairs[p][together.valid[p]].tolist()}
        assert got == set(ref[p])


def test_ground_primitives_sharing_a_descriptor_take_different_tied_aerial_ones() -> None:
    # One descriptor on each side: every similarity ties. Each ground point still gets k aerial
    # points, but its own share of them, so together they cover far more than k.
    gen = torch.Generator().manual_seed(7)
    ground = with_shared_descriptors(random_set(12, 0, 8, gen), 1, gen)
    patch = with_shared_descriptors(random_set(60, 0, 8, gen), 1, gen)
    k = 4
    assoc = putative_associations(ground, stack_primitive_sets([patch]), k_prim=k, direction="ground_to_aerial", min_line_length_m=2.0)
    pairs = assoc.pairs[0][assoc.valid[0]]
    assert torch.bincount(pairs[:, 0], minlength=12).tolist() == [k] * 12
    assert pairs[:, 1].unique().numel() > 3 * k


def patch_local_pairs(assoc, row: int, n_patch_points: int) -> torch.Tensor:
    """Valid pairs of one patch with aerial line indices offset by the patch's own point count, not the batch's."""
    pairs = assoc.pairs[row][assoc.valid[row]].clone()
    line = pairs[:, 0] >= assoc.n_ground_points
    pairs[line, 1] -= assoc.n_aerial_points - n_patch_points
    return pairs


def test_min_line_length_filter_and_kinds() -> None:
    d = torch.eye(4, dtype=torch.float64)
    endpoints = torch.tensor(
        [[[0, 0], [1, 0]], [[0, 5], [1, 5]], [[0, 9], [1, 9]], [[0, 12], [8, 12]]], dtype=torch.float64
    )
    kinds = torch.tensor([int(LineKind.SEGMENT), int(LineKind.RAY), int(LineKind.INFINITE), int(LineKind.SEGMENT)])
    lines = PrimitiveSet(
        points_xy=torch.zeros(0, 2, dtype=torch.float64),
        point_descriptors=torch.zeros(0, 4, dtype=torch.float64),
        point_segment_ids=torch.zeros(0, dtype=torch.int64),
        line_endpoints=endpoints,
        line_kinds=kinds,
        line_descriptors=d,
        line_segment_ids=torch.arange(4),
    )
    assoc = putative_associations(lines, stack_primitive_sets([lines]), **_settings(k_prim=4))
    used = assoc.pairs[0][assoc.valid[0]]
    # The 1 m segment (index 0) is gone on both sides; the 1 m ray and infinite line stay.
    assert not (used == 0).any()
    assert set(used[:, 0].tolist()) == {1, 2, 3} and set(used[:, 1].tolist()) == {1, 2, 3}
    assoc = putative_associations(lines, stack_primitive_sets([lines]), **_settings(k_prim=4, min_line_length_m=0.5))
    assert 0 in assoc.pairs[0][assoc.valid[0]][:, 0].tolist()


def test_k_larger_than_candidates_and_empty_types() -> None:
    gen = torch.Generator().manual_seed(5)
    ground = random_set(3, 0, 8, gen)
    patches = [random_set(2, 4, 8, gen), random_set(5, 1, 8, gen)]
    assoc = putative_associations(ground, stack_primitive_sets(patches), **_settings(k_prim=20))
    assert assoc.n_point_assoc == assoc.size  # no ground lines: no line block
    assert assoc.valid.sum(1).tolist() == [3 * 2, 3 * 5]


def mask_pairs(ground_desc, ground_ok, aerial_desc, aerial_ok, k: int, direction: str):
    """`_chunk_pairs` by its plain definition: the picks as a (P, G, A) mask, then its non-zeros."""
    n_patches, n_aerial = aerial_ok.shape
    n_ground = ground_ok.shape[0]
    cosine = torch.einsum(
        "gd,pad->pga",
        torch.nn.functional.normalize(ground_desc.double(), dim=-1),
        torch.nn.functional.normalize(aerial_desc.double(), dim=-1),
    )
    usable = ground_ok[None, :, None] & aerial_ok[:, None, :]
    ranked = cosine.float().double() + associations.tie_break_jitter(n_ground, n_aerial, cosine.device)
    ranked.masked_fill_(~usable, float("-inf"))
    selected = torch.zeros_like(usable)
    if min(k, n_aerial) > 0:
        selected.scatter_(2, ranked.topk(min(k, n_aerial), dim=2).indices, True)
    if direction == "union" and min(k, n_ground) > 0:
        selected.scatter_(1, ranked.topk(min(k, n_ground), dim=1).indices, True)
    selected &= usable
    flat = selected.reshape(n_patches, n_ground * n_aerial)
    width = int(flat.sum(1).max()) if flat.numel() else 0
    pairs = torch.full((n_patches, width, 2), -1, dtype=torch.int64)
    cos = torch.zeros(n_patches, width, dtype=ground_desc.dtype)
    for p in range(n_patches):
        index = flat[p].nonzero()[:, 0]
        pairs[p, : len(index)] = torch.stack([index // n_aerial, index % n_aerial], 1)
        cos[p, : len(index)] = cosine.reshape(n_patches, n_ground * n_aerial)[p, index].to(ground_desc.dtype)
    return pairs, pairs[..., 0] >= 0, cos


@pytest.mark.parametrize("direction", ["ground_to_aerial", "union"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("compiled", [True, False])
def test_chunk_pairs_equal_mask_definition(direction: str, dtype: torch.dtype, compiled: bool) -> None:
    """The sorted picks (compiled, and torch's topk path) give the mask's pairs and cosines exactly:
    with tied descriptors, unusable primitives on both sides, k above the candidates, and no ground
    or aerial primitives."""
    gen = torch.Generator().manual_seed(11)
    for n_ground, n_patches, n_aerial, k in ((9, 4, 30, 3), (9, 3, 5, 7), (0, 2, 6, 3), (5, 2, 0, 3), (4, 0, 3, 2)):
        ground_desc = torch.randn(n_ground, 6, generator=gen).to(dtype)
        aerial_desc = torch.randn(n_patches, n_aerial, 6, generator=gen).to(dtype)
        if n_ground > 2 and n_aerial > 4:  # exact ties within and across the sides
            ground_desc[1] = ground_desc[0]
            aerial_desc[:, 1:4] = aerial_desc[:, :1]
            aerial_desc[:, 4] = ground_desc[2] * 3
        ground_ok = torch.rand(n_ground, generator=gen) > 0.2
        aerial_ok = torch.rand(n_patches, n_aerial, generator=gen) > 0.3
        got = associations._chunk_pairs(ground_desc, ground_ok, aerial_desc, aerial_ok, k, direction, compiled)
        expected = mask_pairs(ground_desc, ground_ok, aerial_desc, aerial_ok, k, direction)
        for x, y in zip(got, expected):
            assert x.dtype == y.dtype and torch.equal(x, y)


def test_rejects_bad_arguments() -> None:
    gen = torch.Generator().manual_seed(0)
    s = random_set(2, 2, 4, gen)
    with pytest.raises(ValueError):
        putative_associations(s, stack_primitive_sets([s]), **_settings(k_prim=0))
    with pytest.raises(ValueError):
        putative_associations(s, stack_primitive_sets([s]), **_settings(direction="aerial_to_ground"))

"""Affinity M_DA: batched scores equal a plain per-pair loop; closed-form cases for every score."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from meridian_torch.config.matching import AffinityConfig
from meridian_torch.matching.affinity import (
    AffinityEntries,
    affinity,
    affinity_entries,
    affinity_matrix,
    affinity_matrix_sparse,
    closest_points_between_lines,
    kernel,
    nearest_point_on_line,
    unary_scores,
)
from meridian_torch.matching.affinity.blocks import _entries
from meridian_torch.matching.affinity.compiled import (
    _compiled_line_pair_table,
    _constants,
    _gathered,
    _kernel,
    _passed_columns,
    _passing,
    _point_pair_score,
)
from meridian_torch.matching.affinity.gather import _PARALLEL_GATE_OFFSET, _gate_tables, _gather
from meridian_torch.matching.affinity.lines import _closest_params, _line_params
from meridian_torch.matching.affinity.scores import _GATE_SLACK, _line_pair_table
from meridian_torch.matching.associations import Associations, putative_associations
from meridian_torch.types import LineKind, PrimitiveSet, stack_primitive_sets

SEG, RAY, INF = int(LineKind.SEGMENT), int(LineKind.RAY), int(LineKind.INFINITE)
CFG = AffinityConfig(parallel_line_pairs="reject")  # the reference semantics; "separation" is tested explicitly
TAN = math.tan(math.radians(20.0))

# ------------------------------------------------------------------------------------------
# Slow reference: the affinity rules, one pair at a time, in plain Python floats.
# ------------------------------------------------------------------------------------------


def sub(u, v):
    return (u[0] - v[0], u[1] - v[1])


def dot(u, v):
    return u[0] * v[0] + u[1] * v[1]


def crs(u, v):
    return u[0] * v[1] - u[1] * v[0]


def make_line(e, kind):
    d = sub(e[1], e[0])
    length = math.hypot(*d)
    d = (d[0] / length, d[1] / length)
    ref = e[0] if kind == RAY else ((e[0][0] + e[1][0]) / 2, (e[0][1] + e[1][1]) / 2)
    ends = [e[0], e[1]] if kind == SEG else ([e[0]] if kind == RAY else [])
    lo = -math.inf if kind == INF else 0.0
    hi = length if kind == SEG else math.inf
    return {"o": e[0], "d": d, "lo": lo, "hi": hi, "ref": ref, "ends": ends, "inf": kind == INF}


def ref_nearest(x, ln):
    t = min(max(dot(sub(x, ln["o"]), ln["d"]), ln["lo"]), ln["hi"])
    return (ln["o"][0] + t * ln["d"][0], ln["o"][1] + t * ln["d"][1])


def ref_on_line(x, ln):
    t = dot(sub(x, ln["o"]), ln["d"])
    return ln["lo"] - 1e-3 <= t <= ln["hi"] + 1e-3


def ref_closest(l1, l2):
    if abs(dot(l1["d"], l2["d"])) >= math.cos(math.radians(0.1)):
        if l1["inf"]:
            return l1["ref"], ref_nearest(l1["ref"], l2)
        if l2["inf"]:
            return ref_nearest(l2["ref"], l1), l2["ref"]
    else:
        w = sub(l2["o"], l1["o"])
        t1 = crs(w, l2["d"]) / crs(l1["d"], l2["d"])
        x = (l1["o"][0] + t1 * l1["d"][0], l1["o"][1] + t1 * l1["d"][1])
        if ref_on_line(x, l1) and ref_on_line(x, l2):
            return x, x
    best, best_d = None, math.inf
    for e in l1["ends"]:
        n = ref_nearest(e, l2)
        if math.dist(e, n) < best_d:
            best, best_d = (e, n), math.dist(e, n)
    for e in l2["ends"]:
        n = ref_nearest(e, l1)
        if math.dist(e, n) < best_d:
            best, best_d = (n, e), math.dist(e, n)
    return best


def f(c, sigma, eps):
    return math.exp(-c * c / (2 * sigma * sigma)) if c <= eps else 0.0


def ref_point_pair(da, dg, delta, rotated, min_sep):
    l1, l2 = math.hypot(*da), math.hypot(*dg)
    if min_sep and (l1 < 3.0 or l2 < 3.0):
        return 0.0
    e0 = f(abs(l1 - l2), 2.0 + delta, 2.0)
    if not rotated:
        return e0
    s = math.sin(math.radians(20.0))
    cx, cy = abs(da[0] - dg[0]), abs(da[1] - dg[1])
    wx, wy = 0.5 * (abs(da[0]) + abs(dg[0])) * s, 0.5 * (abs(da[1]) + abs(dg[1])) * s
    sx, sy, ex, ey = 2.0 + delta + wx, 2.0 + delta + wy, 2.0 + delta + wx, 2.0 + delta + wy
    if cx > ex / math.sqrt(2) or cy > ey / math.sqrt(2):
        return 0.0
    return min(e0, math.exp(-0.5 * (cx**2 / (sx**2 / 2) + cy**2 / (sy**2 / 2))))


def angle(d1, d2):
    return math.acos(min(1.0, abs(dot(d1, d2))))


def ref_separation(li, lj):
    """Separation vector (line i minus line j, across both directions) of near-parallel lines
    measured at their reference points, and the along-line offset of the reference points."""
    w = sub(lj["ref"], li["ref"])
    across_i = sub(w, (dot(w, li["d"]) * li["d"][0], dot(w, li["d"]) * li["d"][1]))
    across_j = sub(w, (dot(w, lj["d"]) * lj["d"][0], dot(w, lj["d"]) * lj["d"][1]))
    v = (-(across_i[0] + across_j[0]) / 2, -(across_i[1] + across_j[1]) / 2)
    return v, (abs(dot(w, li["d"])) + abs(dot(w, lj["d"]))) / 2


def ref_line_line(ai, aj, gi, gj, rotated, parallel="reject"):
    ta, tg = angle(ai["d"], aj["d"]), angle(gi["d"], gj["d"])
    par_a, par_g = ta < math.radians(10), tg < math.radians(10)
    if (par_a or par_g) and (parallel == "reject" or par_a != par_g):
        return 0.0
    s_theta = f(abs(ta - tg), math.radians(20), math.radians(20))
    if s_theta == 0:
        return 0.0
    if par_a:
        (va, la), (vg, lg) = ref_separation(ai, aj), ref_separation(gi, gj)
        if math.hypot(*va) < 3.0 or math.hypot(*vg) < 3.0:
            return 0.0
        delta = 0.5 * (math.sin(ta) * la + math.sin(tg) * lg)
        return math.sqrt(s_theta * ref_point_pair(va, vg, delta, rotated, False))
    cai, caj = ref_closest(ai, aj)
    cgi, cgj = ref_closest(gi, gj)
    lever = (math.dist(ai["ref"], cai) + math.dist(aj["ref"], caj) + math.dist(gi["ref"], cgi) + math.dist(gj["ref"], cgj)) / 4
    s_t = ref_point_pair(sub(cai, caj), sub(cgi, cgj), TAN * lever, rotated, False)
    return math.sqrt(s_theta * s_t)


def ref_point_line(pa, pg, la, lg, rotated):
    na, ng = ref_nearest(pa, la), ref_nearest(pg, lg)
    delta = TAN * 0.5 * (math.dist(la["ref"], na) + math.dist(lg["ref"], ng))
    va, vg = sub(pa, na), sub(pg, ng)
    c_along = abs(abs(dot(va, la["d"])) - abs(dot(vg, lg["d"])))
    c_across = abs(abs(crs(va, la["d"])) - abs(crs(vg, lg["d"])))
    r2 = math.sqrt(2)
    split = f(c_along, 2.0 / r2, 2.0 / r2) * f(c_across, 2.0 / r2 + delta, 2.0 / r2 + delta)
    return min(split, ref_point_pair(va, vg, delta, rotated, False))


def rot(yaw, x):
    c, s = math.cos(yaw), math.sin(yaw)
    return (c * x[0] - s * x[1], s * x[0] + c * x[1])


def primitive(s: PrimitiveSet, index: int, n_points: int, yaw: float | None):
    """('point', xy) or ('line', line dict) for a unified index, rotated by yaw if given."""
    r = (lambda x: rot(yaw, x)) if yaw is not None else (lambda x: x)
    if index < n_points:
        return "point", r(tuple(s.points_xy[index].tolist()))
    e = [r(tuple(p)) for p in s.line_endpoints[index - n_points].tolist()]
    return "line", make_line(e, int(s.line_kinds[index - n_points]))


def loop_affinity(ground, patches, assoc: Associations, prior: list[float] | None, parallel: str = "reject") -> torch.Tensor:
    m = assoc.size
    out = torch.zeros(len(patches), m, m, dtype=torch.float64)
    for p, patch in enumerate(patches):
        yaw = None if prior is None else prior[p]
        n_ap = assoc.n_aerial_points
        # A batch pads points, the unbatched patch does not: map the unified aerial index back.
        n_real = patch.points_xy.shape[0]
        items = []
        for i in range(m):
            if not bool(assoc.valid[p, i]):
                items.append(None)
                continue
            g, a = assoc.pairs[p, i].tolist()
            a_local = a if a < n_ap else a - n_ap + n_real
            kind, gp = primitive(ground, g, assoc.n_ground_points, yaw)
            _, ap = primitive(patch, a_local, n_real, None)
            c = float(assoc.cosine[p, i])
            q = min(max((c - 0.1) / 0.4, 0.0), 1.0)
            if yaw is not None and kind == "line":
                q = math.sqrt(f(angle(ap["d"], gp["d"]), math.radians(40), math.radians(40)) * q)
            items.append((kind, g, a, gp, ap, q))
        for i in range(m):
            if items[i] is None:
                continue
            out[p, i, i] = 1.0
            for j in range(i + 1, m):
                if items[j] is None:
                    continue
                ki, gi_idx, ai_idx, gi, ai, qi = items[i]
                kj, gj_idx, aj_idx, gj, aj, qj = items[j]
                if gi_idx == gj_idx or ai_idx == aj_idx:
                    continue
                rotated = yaw is not None
                if ki == kj == "point":
                    s = ref_point_pair(sub(ai, aj), sub(gi, gj), 0.0, rotated, True)
                elif ki == kj == "line":
                    s = ref_line_line(ai, aj, gi, gj, rotated, parallel)
                elif ki == "point":
                    s = ref_point_line(ai, gi, aj, gj, rotated)
                else:
                    s = ref_point_line(aj, gj, ai, gi, rotated)
                v = (s * qi * qj) ** (1 / 3)
                if v > 1e-4:
                    out[p, i, j] = out[p, j, i] = v
    return out


# ------------------------------------------------------------------------------------------
# Builders
# ------------------------------------------------------------------------------------------


def make_set(points, lines=(), kinds=(), point_desc=None, line_desc=None, dim: int = 8) -> PrimitiveSet:
    pts = torch.tensor(points, dtype=torch.float64).reshape(-1, 2)
    ln = torch.tensor(lines, dtype=torch.float64).reshape(-1, 2, 2)
    eye = torch.eye(dim, dtype=torch.float64)
    pd = point_desc if point_desc is not None else eye[torch.arange(pts.shape[0]) % dim]
    ld = line_desc if line_desc is not None else eye[(torch.arange(ln.shape[0]) + pts.shape[0]) % dim]
    return PrimitiveSet(
        points_xy=pts,
        point_descriptors=pd,
        point_segment_ids=torch.arange(pts.shape[0]),
        line_endpoints=ln,
        line_kinds=torch.tensor(list(kinds), dtype=torch.int64),
        line_descriptors=ld,
        line_segment_ids=torch.arange(ln.shape[0]),
    )


def transform(s: PrimitiveSet, yaw: float, t: tuple[float, float], noise: float = 0.0, gen=None) -> PrimitiveSet:
    c, sn = math.cos(yaw), math.sin(yaw)
    r = torch.tensor([[c, -sn], [sn, c]], dtype=torch.float64)
    tt = torch.tensor(t, dtype=torch.float64)
    jitter = (lambda x: x + noise * torch.randn(x.shape, generator=gen, dtype=torch.float64)) if noise else (lambda x: x)
    return PrimitiveSet(
        points_xy=jitter(s.points_xy @ r.T + tt),
        point_descriptors=s.point_descriptors,
        point_segment_ids=s.point_segment_ids,
        line_endpoints=jitter(s.line_endpoints @ r.T + tt),
        line_kinds=s.line_kinds,
        line_descriptors=s.line_descriptors,
        line_segment_ids=s.line_segment_ids,
    )


def identity_assoc(n_points: int, n_lines: int, cosine: float = 1.0) -> Associations:
    idx = torch.arange(n_points + n_lines)
    return Associations(
        pairs=torch.stack([idx, idx], dim=-1)[None],
        is_line=(idx >= n_points)[None],
        valid=torch.ones(1, n_points + n_lines, dtype=torch.bool),
        cosine=torch.full((1, n_points + n_lines), cosine, dtype=torch.float64),
        n_point_assoc=n_points,
        n_ground_points=n_points,
        n_aerial_points=n_points,
    )


def random_scene(gen: torch.Generator, n_points: int, n_lines: int, dim: int = 12, roads: bool = False) -> PrimitiveSet:
    """Random points and lines in a 40 m square; roads=True: lines along two perpendicular
    directions within a few degrees, like road borders."""
    e0 = torch.rand(n_lines, 2, generator=gen, dtype=torch.float64) * 40
    if roads:
        axis = torch.randint(0, 2, (n_lines,), generator=gen).double() * math.pi / 2
        ang = axis + math.radians(4.0) * torch.randn(n_lines, generator=gen, dtype=torch.float64)
    else:
        ang = torch.rand(n_lines, generator=gen, dtype=torch.float64) * math.pi
    length = 3 + 12 * torch.rand(n_lines, generator=gen, dtype=torch.float64)
    e1 = e0 + length[:, None] * torch.stack([ang.cos(), ang.sin()], 1)
    desc = lambda n: torch.nn.functional.normalize(torch.randn(n, dim, generator=gen, dtype=torch.float64), dim=1)  # noqa: E731
    return PrimitiveSet(
        points_xy=torch.rand(n_points, 2, generator=gen, dtype=torch.float64) * 40,
        point_descriptors=desc(n_points),
        point_segment_ids=torch.arange(n_points),
        line_endpoints=torch.stack([e0, e1], 1),
        line_kinds=torch.randint(0, 3, (n_lines,), generator=gen),
        line_descriptors=desc(n_lines),
        line_segment_ids=torch.arange(n_lines),
    )


def noisy_patch(ground: PrimitiveSet, gen: torch.Generator, n_keep_p: int, n_keep_l: int, n_extra: int) -> PrimitiveSet:
    """A transformed, jittered subset of the ground set plus random extra primitives, with
    descriptors close to the ground ones so cosines span the [0.1, 0.5] window."""
    yaw = float(torch.rand((), generator=gen)) * 2 * math.pi
    moved = transform(ground, yaw, (100.0, -20.0), noise=0.7, gen=gen)
    extra = random_scene(gen, n_extra, n_extra, ground.descriptor_dim)
    extra = transform(extra, 0.0, (100.0, -20.0))
    mix = lambda d: torch.nn.functional.normalize(d + 1.2 * torch.randn(d.shape, generator=gen, dtype=torch.float64), dim=1)  # noqa: E731
    return PrimitiveSet(
        points_xy=torch.cat([moved.points_xy[:n_keep_p], extra.points_xy]),
        point_descriptors=torch.cat([mix(moved.point_descriptors[:n_keep_p]), extra.point_descriptors]),
        point_segment_ids=torch.arange(n_keep_p + n_extra),
        line_endpoints=torch.cat([moved.line_endpoints[:n_keep_l], extra.line_endpoints]),
        line_kinds=torch.cat([moved.line_kinds[:n_keep_l], extra.line_kinds]),
        line_descriptors=torch.cat([mix(moved.line_descriptors[:n_keep_l]), extra.line_descriptors]),
        line_segment_ids=torch.arange(n_keep_l + n_extra),
    )


# ------------------------------------------------------------------------------------------
# Batched == loop
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("with_prior", [False, True])
def test_affinity_equals_loop(seed: int, with_prior: bool) -> None:
    gen = torch.Generator().manual_seed(seed)
    ground = random_scene(gen, 9, 9)
    patches = [noisy_patch(ground, gen, 7, 8, 3), noisy_patch(ground, gen, 4, 3, 2), noisy_patch(ground, gen, 9, 9, 0)]
    batch = stack_primitive_sets(patches)
    assoc = putative_associations(ground, batch, k_prim=3, direction="ground_to_aerial", min_line_length_m=2.0)
    prior = [float(x) for x in torch.rand(3, generator=gen, dtype=torch.float64) * 6] if with_prior else None
    prior_t = torch.tensor(prior, dtype=torch.float64) if prior is not None else None
    # Small blocks so that several row blocks, both types and the block seams are exercised.
    cfg = AffinityConfig(block_pairs=500, parallel_line_pairs="reject")
    dense = affinity_matrix(ground, batch, assoc, cfg, rotation_prior=prior_t)
    expected = loop_affinity(ground, patches, assoc, prior)
    assert (expected > 0).sum() > 3 * assoc.size  # the case is not trivially empty
    torch.testing.assert_close(dense, expected, atol=1e-9, rtol=0)
    sparse = affinity_matrix_sparse(ground, batch, assoc, cfg, rotation_prior=prior_t)
    torch.testing.assert_close(sparse.to_dense(), dense, atol=1e-15, rtol=0)
    # One large block gives the same matrix.
    torch.testing.assert_close(affinity_matrix(ground, batch, assoc, AffinityConfig(parallel_line_pairs="reject"), rotation_prior=prior_t), dense)
    # Padding rows / columns are zero, including the diagonal.
    pad = ~assoc.valid
    assert (dense[pad[:, :, None].expand_as(dense)] == 0).all()
    assert (dense.diagonal(dim1=1, dim2=2) == assoc.valid.double()).all()


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("with_prior", [False, True])
def test_parallel_separation_equals_loop(seed: int, with_prior: bool) -> None:
    gen = torch.Generator().manual_seed(10 + seed)
    ground = random_scene(gen, 3, 14, roads=True)
    patches, yaws = [], []
    for n_lines, n_extra in ((14, 2), (10, 3)):
        # noisy_patch draws its yaw first: read it from a copy of the generator state.
        yaws.append(float(torch.rand((), generator=torch.Generator().set_state(gen.get_state()))) * 2 * math.pi)
        patches.append(noisy_patch(ground, gen, 3, n_lines, n_extra))
    batch = stack_primitive_sets(patches)
    assoc = putative_associations(ground, batch, k_prim=3, direction="ground_to_aerial", min_line_length_m=2.0)
    # A prior near the true heading, so that line associations survive its direction test.
    prior = [y + 0.1 for y in yaws] if with_prior else None
    prior_t = torch.tensor(prior, dtype=torch.float64) if prior is not None else None
    cfg = AffinityConfig(block_pairs=500, parallel_line_pairs="separation")
    dense = affinity_matrix(ground, batch, assoc, cfg, rotation_prior=prior_t)
    expected = loop_affinity(ground, patches, assoc, prior, parallel="separation")
    torch.testing.assert_close(dense, expected, atol=1e-9, rtol=0)
    sparse = affinity_matrix_sparse(ground, batch, assoc, cfg, rotation_prior=prior_t)
    torch.testing.assert_close(sparse.to_dense(), dense, atol=1e-15, rtol=0)
    # The mode only adds near-parallel pairs: every 'reject' entry is unchanged, and the case
    # does exercise parallel pairs.
    reject = affinity_matrix(ground, batch, assoc, AffinityConfig(block_pairs=500, parallel_line_pairs="reject"), rotation_prior=prior_t)
    kept = reject > 0
    torch.testing.assert_close(dense[kept], reject[kept], atol=1e-12, rtol=0)
    assert int((dense > 0).sum()) >= int(kept.sum()) + 10  # >= 5 parallel pairs, both triangles


def without(s: PrimitiveSet, points: bool = False, lines: bool = False) -> PrimitiveSet:
    """The set with its points and / or its lines removed."""
    keep_p = slice(0, 0) if points else slice(None)
    keep_l = slice(0, 0) if lines else slice(None)
    return PrimitiveSet(
        points_xy=s.points_xy[keep_p],
        point_descriptors=s.point_descriptors[keep_p],
        point_segment_ids=s.point_segment_ids[keep_p],
        line_endpoints=s.line_endpoints[keep_l],
        line_kinds=s.line_kinds[keep_l],
        line_descriptors=s.line_descriptors[keep_l],
        line_segment_ids=s.line_segment_ids[keep_l],
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_entries_equal_torch_path(seed: int, dtype: torch.dtype) -> None:
    """The numba kernel (CPU) and the torch ops (other devices) give the same entries in the same
    order, with and without a rotation prior, in every scoring mode, on batches with padding,
    an empty patch and patches without lines or without points."""
    gen = torch.Generator().manual_seed(20 + seed)
    ground = random_scene(gen, 12, 16, roads=seed == 2)
    patches, yaws = [], []
    for n_keep_p, n_keep_l, n_extra in ((12, 16, 4), (8, 10, 6), (12, 16, 0), (5, 12, 3)):
        # noisy_patch draws its yaw first: read it from a copy of the generator state.
        yaws.append(float(torch.rand((), generator=torch.Generator().set_state(gen.get_state()))) * 2 * math.pi)
        patches.append(noisy_patch(ground, gen, n_keep_p, n_keep_l, n_extra))
    patches[1] = without(patches[1], lines=True)
    patches[3] = without(patches[3], points=True)
    patches.append(without(patches[0], points=True, lines=True))
    yaws.append(0.0)
    batch = stack_primitive_sets(patches).to(dtype=dtype)
    grounds = [ground, without(ground, points=True)] if seed == 0 else [ground]
    # Priors near the true headings (line associations keep their q) and random ones.
    random_yaws = torch.rand(len(patches), generator=gen, dtype=torch.float64) * 2 * math.pi
    priors = [None, torch.tensor(yaws, dtype=torch.float64) + 0.05, random_yaws]
    configs = [
        AffinityConfig(parallel_line_pairs="reject", block_pairs=700),
        AffinityConfig(parallel_line_pairs="separation"),
        AffinityConfig(parallel_line_pairs="separation", lever_arm_inflation=False, affinity_eps=0.0, block_pairs=3000),
    ]
    for g in grounds:
        assoc = putative_associations(g, batch, k_prim=3, direction="union", min_line_length_m=2.0)
        assert not assoc.valid.all()  # padding
        for cfg in configs:
            for prior in priors:
                gat = _gather(g, batch, assoc, cfg, prior)
                index, value = _entries(gat, cfg, compiled=False)
                index_c, value_c = _entries(gat, cfg, compiled=True)
                # Every kind of pair scores in every combination (0 pp, 1 pl, 2 ll).
                kinds = (index[:, 1:] >= assoc.n_point_assoc).sum(1)
                assert set(kinds.tolist()) == ({0, 1, 2} if assoc.n_ground_points else {2})
                assert torch.equal(index_c, index)
                assert value_c.dtype == value.dtype
                # float32: libm's exp and pow differ from torch's by an ulp on ~1 % of arguments.
                torch.testing.assert_close(value_c, value, rtol=1e-6 if dtype == torch.float32 else 1e-14, atol=0)
                # On the CPU the public entry point takes the compiled path.
                default = affinity_entries(g, batch, assoc, cfg, rotation_prior=prior)
                assert torch.equal(default.index, index_c) and torch.equal(default.value, value_c)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_gate_steps_equal_numpy(dtype: type) -> None:
    """The compiled gate's steps give numpy's definitions: the gather of a row primitive's table
    row by column (fancy indexing), the test of a row (the comparisons) and its passing columns
    (nonzero), for rows of every length around the mask's 8-byte words, with q = 0 and NaN
    values, rows where none and where all pass."""
    rng = np.random.default_rng(7)
    table = rng.uniform(0, 3, 60).astype(dtype)
    table[::9] = np.nan
    for n in (0, 1, 5, 7, 8, 9, 16, 17, 64, 65, 203):
        for lo, col_offset in ((0, 0), (3, 0), (11, 4)):
            hi, width = lo + n, lo + n + 5
            cols = rng.integers(0, 40, width - col_offset)
            out = np.full(width, -1.0, dtype)
            _gathered(out, table, 13, cols, col_offset, lo, hi)
            expected = np.full(width, -1.0, dtype)
            expected[lo:hi] = table[13 + cols[lo - col_offset : hi - col_offset]]
            np.testing.assert_array_equal(out, expected)  # NaN where NaN, nothing else written
        for passing in ("some", "none", "all"):
            q, a_gate, g_gate, a_gap, g_gap = rng.uniform(0, 3, (5, n)).astype(dtype)
            q[rng.random(n) < 0.2] = 0
            a_gate[rng.random(n) < 0.1] = np.nan
            g_gap[rng.random(n) < 0.1] = np.nan
            tol = {"some": 1.0, "none": -1.0, "all": np.inf}[passing]
            if passing == "all":
                q[:] = 1
                a_gate[:], g_gap[:] = 0, 0
            for with_gap in (False, True):
                mask = np.full(8 * ((n + 15) // 8), 1, np.uint8)  # stale bytes past n
                _passing(mask, q, a_gate, g_gate, a_gap, g_gap, dtype(tol), dtype(tol), with_gap)
                passed = (q != 0) & (np.abs(a_gate - g_gate) <= tol)
                if with_gap:
                    passed &= np.abs(a_gap - g_gap) <= tol
                np.testing.assert_array_equal(mask[:n], passed)
                columns = np.full(n + 8, -1, np.int64)
                count = _passed_columns(columns, mask, mask.view(np.uint64), 100, n)
                np.testing.assert_array_equal(columns[:count], 100 + np.flatnonzero(passed))
                if passing != "some":
                    assert count == (n if passing == "all" else 0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_gap_score_equals_point_pair_score(dtype: type) -> None:
    """The unrotated line-line s_t of the compiled kernel scores |gap| directly: bit for bit
    `_point_pair_score` of the vectors (gap, 0) (whose lengths are libm's hypot(gap, 0)), on
    random gaps around the eps_t window and on zeros, subnormals, huge, infinite and NaN ones."""
    k = _constants(AffinityConfig(), np.dtype(dtype))
    rng = np.random.default_rng(3)
    info = np.finfo(dtype)
    special = np.array([0.0, -0.0, info.smallest_subnormal, info.tiny, 1.0, 2.0, 3.0, info.max, np.inf, -np.inf, np.nan], dtype)
    a = np.concatenate([rng.uniform(0, 40, 400).astype(dtype), np.repeat(special, len(special))])
    g = np.concatenate([a[:400] + rng.uniform(-2.5, 2.5, 400).astype(dtype), np.tile(special, len(special))])
    deltas = rng.choice(np.array([0.0, 0.3, 7.0], dtype), len(a))
    for a_gap, g_gap, delta in zip(a, g, deltas):
        old = _point_pair_score(a_gap, k.zero, g_gap, k.zero, delta, k, False, False)
        with np.errstate(invalid="ignore"):  # inf - inf
            new = _kernel(abs(abs(a_gap) - abs(g_gap)), k.sigma_t + delta, k.eps_t, k)
        assert np.array(old, dtype).tobytes() == np.array(new, dtype).tobytes() or (math.isnan(old) and math.isnan(new))
    assert sum(_kernel(abs(x - y), k.sigma_t, k.eps_t, k) > 0 for x, y in zip(a[:400], g[:400])) > 100  # not all 0


def same_numbers(x: torch.Tensor, y: torch.Tensor) -> bool:
    """Equal shapes, dtypes and values, NaN where NaN (0.0 equals -0.0)."""
    return x.shape == y.shape and x.dtype == y.dtype and torch.equal(x.isnan(), y.isnan()) and torch.equal(
        x.nan_to_num(nan=0.0), y.nan_to_num(nan=0.0)
    )


def awkward_lines(gen: torch.Generator, n: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """(2, n, 2, 2) endpoints and (2, n) kinds of random lines of every kind with the pairs the
    closest points branch on: exactly parallel and antiparallel copies, lines that cross,
    collinear overlapping ones, shared endpoints, zero-length ones and one NaN line."""
    ends = torch.rand(2, n, 2, 2, generator=gen, dtype=torch.float64) * 40 - 20
    ends[:, 1:8] = ends[:, :7] + torch.tensor([3.0, -1.0], dtype=torch.float64)  # parallel
    ends[:, 8:12] = ends[:, 1:5].flip(2)  # antiparallel copies
    ends[:, 12:16, 0] = ends[:, 2:6, 1]  # shared endpoints
    ends[:, 16:20] = ends[:, 2:6, :1] + (ends[:, 2:6, 1:] - ends[:, 2:6, :1]) * torch.tensor([[0.5], [2.0]], dtype=torch.float64)
    ends[:, 20:23, 1] = ends[:, 20:23, 0]  # zero length
    ends[1, 23] = math.nan
    kinds = torch.randint(0, 3, (2, n), generator=gen)
    kinds[0, :4] = SEG
    return ends.to(dtype), kinds


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_line_pair_table_equals_torch(dtype: torch.dtype) -> None:
    """The numba line-pair table gives the torch path's numbers, in both modes, with and without
    the gap vector, for batches of lines, a flat set of lines and no lines at all."""
    gen = torch.Generator().manual_seed(5)
    ends, kinds = awkward_lines(gen, 60, dtype)
    for batch in ((ends, kinds), (ends[0], kinds[0]), (ends[:, :0], kinds[:, :0])):
        lines = _line_params(*batch)
        for with_vectors in (False, True):
            for parallel_below in (None, math.radians(10.0)):
                expected = _line_pair_table(lines.map_axis(-1), lines.map_axis(-2), with_vectors, parallel_below)
                table = _compiled_line_pair_table(lines, with_vectors, parallel_below)
                assert same_numbers(table, expected)
    # The case reaches every branch: lines that meet, endpoint candidates, parallel with an infinite line.
    lines = _line_params(ends, kinds)
    l_i, l_j = lines.map_axis(-1), lines.map_axis(-2)
    meet = _closest_params(l_i, l_j)[2]
    parallel = (l_i.dx * l_j.dx + l_i.dy * l_j.dy).abs() >= math.cos(math.radians(0.1))
    assert meet.any() and (~meet & ~parallel).any() and (parallel & ~meet & (l_i.lo.isinf() | l_j.lo.isinf())).any()


@pytest.mark.parametrize("seed", [0, 2])
def test_compiled_gather_equals_torch(seed: int) -> None:
    """`_gather` builds the same tables with the compiled line pairs as with the torch ops."""
    gen = torch.Generator().manual_seed(20 + seed)
    ground = random_scene(gen, 12, 16, roads=seed == 2)
    batch = stack_primitive_sets([noisy_patch(ground, gen, 12, 16, 4), noisy_patch(ground, gen, 8, 10, 6)])
    assoc = putative_associations(ground, batch, k_prim=3, direction="union", min_line_length_m=2.0)
    prior = torch.tensor([0.3, 2.0], dtype=torch.float64)
    for cfg in (AffinityConfig(parallel_line_pairs="reject"), AffinityConfig(parallel_line_pairs="separation")):
        for yaw in (None, prior):
            expected = _gather(ground, batch, assoc, cfg, yaw, compiled=False)
            gat = _gather(ground, batch, assoc, cfg, yaw, compiled=True)
            for name in expected.__dataclass_fields__:
                x, y = getattr(gat, name), getattr(expected, name)
                if isinstance(x, torch.Tensor):
                    assert same_numbers(x, y), name
                elif name != "cos_sin":
                    assert x == y, name


def eye_mask_gates(a_xy, g_xy, a_pl, g_pl, a_ll, g_ll, cfg: AffinityConfig) -> tuple[torch.Tensor, ...]:
    """`_gate_tables` as first written: self pairs by an identity mask, out-of-place ops."""
    def same_type(value, minimum):
        self_pair = torch.eye(value.shape[-1], dtype=torch.bool)
        return value.masked_fill((value < minimum) | self_pair, float("nan")).flatten()

    def distances(xy):
        return torch.hypot(xy[..., :, None, 0] - xy[..., None, :, 0], xy[..., :, None, 1] - xy[..., None, :, 1])

    def line_pairs(ll):
        min_angle = math.radians(cfg.min_line_angle_deg)
        if cfg.parallel_line_pairs == "reject":
            return same_type(ll[0], min_angle - _GATE_SLACK)
        scale = math.radians(cfg.epsilon_theta_deg) / cfg.epsilon_t_m
        too_close = ll[1] < cfg.min_point_separation_m - _GATE_SLACK
        parallel = torch.where(too_close, float("nan"), _PARALLEL_GATE_OFFSET + scale * ll[1])
        return same_type(torch.where(ll[0] < min_angle, parallel, ll[0]), float("-inf"))

    slack = cfg.min_point_separation_m - _GATE_SLACK
    return (same_type(distances(a_xy), slack), same_type(distances(g_xy), slack), torch.hypot(a_pl[0], a_pl[1]).flatten(),
            torch.hypot(g_pl[0], g_pl[1]).flatten(), line_pairs(a_ll), line_pairs(g_ll))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gate_tables_equal_eye_mask_definition(dtype: torch.dtype) -> None:
    """The gates (diagonal filled in place) equal the identity-mask definition, NaN tables included,
    and leave the tables untouched."""
    gen = torch.Generator().manual_seed(8)
    a_xy, g_xy = torch.rand(3, 7, 2, generator=gen, dtype=dtype) * 10, torch.rand(5, 2, generator=gen, dtype=dtype) * 10
    a_pl, g_pl = torch.randn(3, 3, 7, 6, generator=gen, dtype=dtype), torch.randn(3, 5, 4, generator=gen, dtype=dtype)
    a_ll = torch.rand(3, 3, 6, 6, generator=gen, dtype=dtype) * torch.tensor([0.5, 8.0, 1.0], dtype=dtype)[:, None, None, None]
    g_ll = torch.rand(3, 4, 4, generator=gen, dtype=dtype) * torch.tensor([0.5, 8.0, 1.0], dtype=dtype)[:, None, None]
    a_ll[:, 0, 1, 2] = math.nan
    tables = (a_xy, g_xy, a_pl, g_pl, a_ll, g_ll)
    copies = [t.clone() for t in tables]
    for mode in ("reject", "separation"):
        cfg = AffinityConfig(parallel_line_pairs=mode)
        for got, expected in zip(_gate_tables(*tables, cfg), eye_mask_gates(*tables, cfg)):
            assert same_numbers(got, expected)
    assert all(same_numbers(t, c) for t, c in zip(tables, copies))


def test_entries_to_sparse_equals_coalesce() -> None:
    """`AffinityEntries.to_sparse` builds what coalesce() makes of both triangles and the unit
    diagonal: the same indices and values, flagged coalesced; also without entries and with m = 0."""
    gen = torch.Generator().manual_seed(4)
    n_patches, m = 3, 9
    upper = torch.triu(torch.ones(m, m, dtype=torch.bool), 1).nonzero()
    index = torch.cat([torch.full((len(upper), 1), p) for p in range(n_patches)]), upper.repeat(n_patches, 1)
    index = torch.cat(index, 1)[torch.randperm(n_patches * len(upper), generator=gen)[:50]]  # any order
    cases = [
        AffinityEntries(index, torch.rand(50, generator=gen, dtype=torch.float64), torch.rand(n_patches, m, generator=gen) > 0.3),
        AffinityEntries(index[:0], torch.zeros(0), torch.rand(n_patches, m, generator=gen) > 0.3),
        AffinityEntries(index[:0], torch.zeros(0), torch.zeros(n_patches, 0, dtype=torch.bool)),
    ]
    for entries in cases:
        upper, diag = entries.index, entries.valid.nonzero()
        idx = torch.cat([upper, upper[:, [0, 2, 1]], torch.stack([diag[:, 0], diag[:, 1], diag[:, 1]], 1)])
        val = torch.cat([entries.value, entries.value, entries.value.new_ones(diag.shape[0])])
        expected = torch.sparse_coo_tensor(idx.T, val, entries.shape, check_invariants=True).coalesce()
        got = entries.to_sparse()
        assert got.is_coalesced() and got.shape == expected.shape and got.dtype == expected.dtype
        assert torch.equal(got.indices(), expected.indices()) and torch.equal(got.values(), expected.values())


def test_closest_points_equal_loop() -> None:
    gen = torch.Generator().manual_seed(3)
    n = 400
    e1 = torch.rand(n, 2, 2, generator=gen, dtype=torch.float64) * 20
    e2 = torch.rand(n, 2, 2, generator=gen, dtype=torch.float64) * 20
    # Some exactly parallel pairs, with and without infinite lines.
    e2[:40] = e1[:40] + torch.tensor([3.0, -1.0], dtype=torch.float64)
    k1 = torch.randint(0, 3, (n,), generator=gen)
    k2 = torch.randint(0, 3, (n,), generator=gen)
    c1, c2 = closest_points_between_lines(e1, k1, e2, k2)
    for i in range(n):
        r1, r2 = ref_closest(make_line(e1[i].tolist(), int(k1[i])), make_line(e2[i].tolist(), int(k2[i])))
        assert torch.linalg.vector_norm(c1[i] - c2[i]).item() == pytest.approx(math.dist(r1, r2), abs=1e-9)
        if i >= 40:  # parallel segments can tie between equally close endpoint pairs
            torch.testing.assert_close(c1[i], torch.tensor(r1, dtype=torch.float64), atol=1e-9, rtol=0)
            torch.testing.assert_close(c2[i], torch.tensor(r2, dtype=torch.float64), atol=1e-9, rtol=0)
    x = torch.rand(n, 2, generator=gen, dtype=torch.float64) * 20
    near = nearest_point_on_line(x, e1, k1)
    for i in range(n):
        ref = ref_nearest(tuple(x[i].tolist()), make_line(e1[i].tolist(), int(k1[i])))
        torch.testing.assert_close(near[i], torch.tensor(ref, dtype=torch.float64), atol=1e-12, rtol=0)


# ------------------------------------------------------------------------------------------
# Closed-form cases
# ------------------------------------------------------------------------------------------


def lines_pair(a_lines, g_lines, kinds, cos: float = 1.0) -> float:
    """M_01 of two line associations (aerial line k <-> ground line k)."""
    aerial = make_set([], a_lines, kinds)
    ground = make_set([], g_lines, kinds)
    m = affinity_matrix(ground, stack_primitive_sets([aerial]), identity_assoc(0, 2, cos), CFG)
    return float(m[0, 0, 1])


def test_kernel_boundary() -> None:
    c = torch.tensor([0.0, 1.0, 2.0, 2.0000001], dtype=torch.float64)
    expected = torch.tensor([1.0, math.exp(-1 / 8), math.exp(-0.5), 0.0], dtype=torch.float64)
    torch.testing.assert_close(kernel(c, 2.0, 2.0), expected)


def test_corner_segments_meet_at_the_corner() -> None:
    e1 = torch.tensor([[0.0, 0.0], [10.0, 0.0]], dtype=torch.float64)
    e2 = torch.tensor([[0.0, 0.0], [0.0, 10.0]], dtype=torch.float64)
    c1, c2 = closest_points_between_lines(e1, torch.tensor(SEG), e2, torch.tensor(SEG))
    assert c1.tolist() == [0.0, 0.0] and c2.tolist() == [0.0, 0.0]
    # A rigidly moved copy: s_theta = s_t = 1 and unit unary scores give M = 1.
    corner = [[[0, 0], [10, 0]], [[0, 0], [0, 10]]]
    moved = transform(make_set([], corner, [SEG, SEG]), 1.1, (5.0, 7.0)).line_endpoints.tolist()
    assert lines_pair(corner, moved, [SEG, SEG]) == pytest.approx(1.0, abs=1e-12)


def test_segments_stopping_short_compare_their_gap() -> None:
    # The vertical segment stops 2 m above the horizontal one: closest points (5, 0) and (5, 2).
    c1, c2 = closest_points_between_lines(
        torch.tensor([[0.0, 0.0], [10.0, 0.0]]), torch.tensor(SEG), torch.tensor([[5.0, 2.0], [5.0, 10.0]]), torch.tensor(SEG)
    )
    assert c1.tolist() == [5.0, 0.0] and c2.tolist() == [5.0, 2.0]
    aerial = [[[0, 0], [10, 0]], [[5, 2], [5, 10]]]
    assert lines_pair(aerial, aerial, [SEG, SEG]) == pytest.approx(1.0)  # same gap
    # Ground gap 3 m: c = 1, sigma inflated by tan(20) * mean lever (0 + 4 + 0 + 3.5) / 4.
    ground = [[[0, 0], [10, 0]], [[5, 3], [5, 10]]]
    delta = TAN * (4.0 + 3.5) / 4
    expected_s = math.sqrt(math.exp(-1.0 / (2 * (2 + delta) ** 2)))
    assert lines_pair(aerial, ground, [SEG, SEG]) == pytest.approx(expected_s ** (1 / 3), abs=1e-12)
    # Ground gap 5 m: c = 3 > eps_t, inconsistent.
    assert lines_pair(aerial, [[[0, 0], [10, 0]], [[5, 5], [5, 10]]], [SEG, SEG]) == 0.0


def test_ray_closest_points() -> None:
    seg = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
    # A ray starting 2 m above the segment and pointing away from it: gap at its start.
    c1, c2 = closest_points_between_lines(seg, torch.tensor(SEG), torch.tensor([[5.0, 2.0], [5.0, 10.0]]), torch.tensor(RAY))
    assert c1.tolist() == [5.0, 0.0] and c2.tolist() == [5.0, 2.0]
    # The same ray pointing towards the segment crosses it.
    c1, c2 = closest_points_between_lines(seg, torch.tensor(SEG), torch.tensor([[5.0, 2.0], [5.0, -10.0]]), torch.tensor(RAY))
    assert c1.tolist() == [5.0, 0.0] and c2.tolist() == [5.0, 0.0]
    # A ray ending before the segment's extension: endpoint fallback to (10, 0) and (13, 0)?
    c1, c2 = closest_points_between_lines(seg, torch.tensor(SEG), torch.tensor([[13.0, 0.5], [20.0, 7.5]]), torch.tensor(RAY))
    assert c1.tolist() == [10.0, 0.0] and c2.tolist() == [13.0, 0.5]
    # Infinite lines always meet when not parallel.
    c1, c2 = closest_points_between_lines(seg, torch.tensor(INF), torch.tensor([[13.0, 0.5], [20.0, 7.5]]), torch.tensor(INF))
    torch.testing.assert_close(c1, c2)
    torch.testing.assert_close(c1, torch.tensor([12.5, 0.0]))


def test_parallel_lines() -> None:
    e1, e2 = torch.tensor([[0.0, 0.0], [10.0, 0.0]]), torch.tensor([[5.0, 3.0], [15.0, 3.0]])
    c1, c2 = closest_points_between_lines(e1, torch.tensor(SEG), e2, torch.tensor(SEG))
    assert torch.linalg.vector_norm(c1 - c2).item() == pytest.approx(3.0)
    # With an infinite line, its reference point (midpoint) anchors the pair.
    c1, c2 = closest_points_between_lines(e1, torch.tensor(INF), e2, torch.tensor(SEG))
    assert c1.tolist() == [5.0, 0.0] and c2.tolist() == [5.0, 3.0]
    # Reference mode: parallel (< 10 deg) same-map line pairs are never consistent, even when identical.
    par = [[[0, 0], [10, 0]], [[0, 5], [10, 5.5]]]
    assert lines_pair(par, par, [SEG, SEG]) == 0.0


def parallel_pair(a_lines, g_lines, prior: float | None = None) -> float:
    """M_01 of two segment associations in 'separation' mode."""
    aerial, ground = make_set([], a_lines, [SEG, SEG]), make_set([], g_lines, [SEG, SEG])
    cfg = AffinityConfig(parallel_line_pairs="separation")
    yaw = None if prior is None else torch.tensor([prior], dtype=torch.float64)
    m = affinity_matrix(ground, stack_primitive_sets([aerial]), identity_assoc(0, 2), cfg, rotation_prior=yaw)
    return float(m[0, 0, 1])


def moved(lines, yaw: float, t: tuple[float, float]):
    """Lines [[p0, p1], ...] rotated by yaw, then translated by t."""
    return [[[rot(yaw, p)[0] + t[0], rot(yaw, p)[1] + t[1]] for p in ln] for ln in lines]


def test_parallel_pairs_score_their_separation() -> None:
    ground = [[[0, 0], [10, 0]], [[0, 5], [10, 5]]]
    # A rigid copy, and one with the second line reversed (lines are sign-less): full score.
    aerial = moved(ground, 0.7, (30.0, -4.0))
    assert parallel_pair(aerial, ground) == pytest.approx(1.0)
    assert parallel_pair([aerial[0], aerial[1][::-1]], ground) == pytest.approx(1.0)
    # Shifted along the lines: the separation (of infinite lines) is unchanged.
    assert parallel_pair(aerial, [ground[0], [[6, 5], [16, 5]]]) == pytest.approx(1.0)
    # Separation 6 m instead of 5 m, exactly parallel (no lever inflation): s_theta = 1,
    # s_t = f(1; 2, 2), M = cbrt(sqrt(s_t)).
    wider = moved([[[0, 0], [10, 0]], [[0, 6], [10, 6]]], 0.7, (30.0, -4.0))
    assert parallel_pair(wider, ground) == pytest.approx(math.exp(-1 / 8) ** (1 / 6))
    # 7.5 m against 5 m is past eps_t = 2 m; 2.5 m separations fall under the 3 m minimum.
    far = moved([[[0, 0], [10, 0]], [[0, 7.5], [10, 7.5]]], 0.7, (30.0, -4.0))
    assert parallel_pair(far, ground) == 0.0
    close = [[[0, 0], [10, 0]], [[0, 2.5], [10, 2.5]]]
    assert parallel_pair(close, close) == 0.0
    # Parallel in one map only (5 deg vs 15 deg): the angle kernel alone would accept it.
    tilt = lambda deg: [[0, 5], [10, 5 + 10 * math.tan(math.radians(deg))]]  # noqa: E731
    assert parallel_pair([ground[0], tilt(15.0)], [ground[0], tilt(5.0)]) == 0.0
    assert parallel_pair([ground[0], tilt(5.0)], [ground[0], tilt(5.0)]) > 0.9
    # The default ('reject') still zeroes them.
    assert lines_pair(ground, ground, [SEG, SEG]) == 0.0


def test_parallel_pairs_with_rotation_prior_compare_signed_offsets() -> None:
    ground = [[[0, 0], [10, 0]], [[0, 5], [10, 5]]]
    # The aerial pair is the ground pair turned by 180 deg: the second line lies on the other side.
    aerial = moved(ground, math.pi, (40.0, 10.0))
    assert parallel_pair(aerial, ground) == pytest.approx(1.0)  # free rotation: unsigned
    assert parallel_pair(aerial, ground, prior=math.pi) == pytest.approx(1.0)
    assert parallel_pair(aerial, ground, prior=0.0) == 0.0  # offsets (0, 5) vs (0, -5)


def test_point_line_along_across() -> None:
    line = [[[0, 0], [10, 0]]]

    def score(p_aerial, p_ground) -> float:
        aerial, ground = make_set([p_aerial], line, [SEG]), make_set([p_ground], line, [SEG])
        return float(affinity_matrix(ground, stack_primitive_sets([aerial]), identity_assoc(1, 1), CFG)[0, 0, 1])

    # Across offsets 3 vs 3.5, N is the midpoint (no lever): split term f(0.5; 2/sqrt2) wins.
    assert score([5, 3], [5, 3.5]) == pytest.approx(math.exp(-0.25 / 4) ** (1 / 3), abs=1e-12)
    # Beyond the segment end: along offsets 3 vs 2 (c = 1, f(1; sqrt2)), lever 5 m each.
    assert score([13, 0], [12, 0]) == pytest.approx(math.exp(-0.25) ** (1 / 3), abs=1e-12)
    # Along offset too different: 4 vs 2 > eps / sqrt(2).
    assert score([14, 0], [12, 0]) == 0.0


def test_point_pairs_closer_than_3m_are_zero() -> None:
    pts = [[0, 0], [2.5, 0], [10, 0]]
    s = make_set(pts)
    m = affinity_matrix(s, stack_primitive_sets([s]), identity_assoc(3, 0), CFG)[0]
    assert m[0, 1] == 0 and m[1, 0] == 0
    assert m[0, 2] == pytest.approx(1.0) and m[1, 2] == pytest.approx(1.0)


def test_one_to_one_conflicts_are_zero() -> None:
    s = make_set([[0, 0], [10, 0], [0, 10]])
    # (g0, a0), (g0, a1), (g1, a1), (g2, a2): pairs sharing g0 or a1 conflict.
    pairs = torch.tensor([[[0, 0], [0, 1], [1, 1], [2, 2]]])
    assoc = Associations(
        pairs=pairs,
        is_line=torch.zeros(1, 4, dtype=torch.bool),
        valid=torch.ones(1, 4, dtype=torch.bool),
        cosine=torch.ones(1, 4, dtype=torch.float64),
        n_point_assoc=4,
        n_ground_points=3,
        n_aerial_points=3,
    )
    m = affinity_matrix(s, stack_primitive_sets([s]), assoc, CFG)[0]
    assert m[0, 1] == 0 and m[1, 2] == 0
    assert m[0, 2] == pytest.approx(1.0) and m[0, 3] == pytest.approx(1.0) and m[2, 3] == pytest.approx(1.0)


def test_unary_cosine_window() -> None:
    s = make_set([[0, 0], [10, 0], [0, 10], [10, 10]])
    assoc = identity_assoc(4, 0)
    assoc = Associations(**{**assoc.__dict__, "cosine": torch.tensor([[0.05, 0.1, 0.3, 0.7]], dtype=torch.float64)})
    q = unary_scores(s, stack_primitive_sets([s]), assoc, CFG)
    torch.testing.assert_close(q, torch.tensor([[0.0, 0.0, 0.5, 1.0]], dtype=torch.float64))
    m = affinity_matrix(s, stack_primitive_sets([s]), assoc, CFG)[0]
    assert (m[0, 1:] == 0).all() and (m[1, 2:] == 0).all()  # q <= 0.1 kills the association
    assert m[2, 3] == pytest.approx(0.5 ** (1 / 3))


def structured_scene() -> PrimitiveSet:
    """Well-separated points and lines 15 deg apart in direction: every true pair is consistent."""
    points = [[6.0 * i, 11.0 * ((i * 7) % 5)] for i in range(8)]
    lines, kinds = [], []
    for k in range(7):
        a = math.radians(5 + 25 * k)
        o = [3.0 * k, -4.0 * k]
        lines.append([o, [o[0] + 8 * math.cos(a), o[1] + 8 * math.sin(a)]])
        kinds.append([SEG, RAY, INF][k % 3])
    return make_set(points, lines, kinds, dim=16)


def test_rigid_copy_true_associations_form_a_clique() -> None:
    ground = structured_scene()
    aerial = transform(ground, 2.0, (300.0, 120.0))
    n = 8 + 7
    # True associations plus shuffled (false) ones in each block.
    pairs = [[i, i] for i in range(8)] + [[i, (i + 3) % 8] for i in range(8)]
    pairs += [[8 + i, 8 + i] for i in range(7)] + [[8 + i, 8 + (i + 2) % 7] for i in range(7)]
    valid = torch.ones(1, len(pairs), dtype=torch.bool)
    assoc = Associations(
        pairs=torch.tensor([pairs]),
        is_line=torch.tensor([[False] * 16 + [True] * 14]),
        valid=valid,
        cosine=torch.full((1, len(pairs)), 0.8, dtype=torch.float64),
        n_point_assoc=16,
        n_ground_points=8,
        n_aerial_points=8,
    )
    m = affinity_matrix(ground, stack_primitive_sets([aerial]), assoc, CFG)[0]
    true = torch.tensor([i < 8 or 16 <= i < 23 for i in range(len(pairs))])
    sub_true = m[true][:, true]
    assert sub_true.shape == (n, n)
    assert (sub_true > 0.99).all()  # a clique of near-unit weights
    # The false associations are inconsistent with the true set for most pairs.
    assert m[true][:, ~true].mean() < 0.3 * sub_true.mean()


def test_known_rotation_rejects_wrong_heading() -> None:
    ground = structured_scene()
    yaw = 0.5
    aerial = stack_primitive_sets([transform(ground, yaw, (50.0, -30.0))] * 2)
    idx = torch.arange(15)
    assoc = Associations(
        pairs=torch.stack([idx, idx], -1)[None].expand(2, 15, 2),
        is_line=(idx >= 8)[None].expand(2, 15),
        valid=torch.ones(2, 15, dtype=torch.bool),
        cosine=torch.ones(2, 15, dtype=torch.float64),
        n_point_assoc=8,
        n_ground_points=8,
        n_aerial_points=8,
    )
    # Patch 0 gets the correct prior; patch 1 a prior 60 deg off.
    prior = torch.tensor([yaw, yaw - math.radians(60)], dtype=torch.float64)
    m = affinity_matrix(ground, aerial, assoc, CFG, rotation_prior=prior)
    off = ~torch.eye(15, dtype=torch.bool)
    assert (m[0][off] > 0.99).all()
    assert (m[1][off] > 0).float().mean() < 0.1
    q = unary_scores(ground, aerial, assoc, CFG, rotation_prior=prior)
    assert (q[1, 8:] == 0).all() and (q[0] == 1).all()  # line heading 60 deg off > 40 deg
    # Without the prior both patches accept everything (rotation-invariant scores).
    free = affinity_matrix(ground, aerial, assoc, CFG)
    assert (free[:, off] > 0.99).all()


def test_auto_switches_to_sparse() -> None:
    s = structured_scene()
    assoc = identity_assoc(8, 7)
    batch = stack_primitive_sets([s])
    dense = affinity(s, batch, assoc, CFG)
    assert not dense.is_sparse
    sparse = affinity(s, batch, assoc, AffinityConfig(dense_max_m=10))
    assert sparse.is_sparse
    torch.testing.assert_close(sparse.to_dense(), dense)

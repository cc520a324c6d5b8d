"""Loop-closure candidates, their pairwise consistency and CLIPPER inlier selection."""

from __future__ import annotations

import math
from unittest import mock

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.backend import consistency
from meridian_torch.backend.candidates import LoopClosureCandidates, candidates_from_hypotheses
from meridian_torch.backend.consistency import (
    consistency_affinity,
    consistency_scores,
    pair_errors,
    select_inliers,
    select_inliers_in_windows,
    sparse_affinity,
)
from meridian_torch.backend.consistency_kernels import ball_heading_pairs
from meridian_torch.config import BackendConfig
from meridian_torch.geometry.se2 import se2_inverse, se2_matrix
from meridian_torch.geometry.se3 import pose_from_xyz_yaw
from meridian_torch.matching.hypotheses import Hypotheses
from meridian_torch.types import GroundSubmap, PrimitiveSet


def _se2(x: float, y: float, yaw: float) -> torch.Tensor:
    return se2_matrix(torch.tensor(yaw, dtype=torch.float64), torch.tensor([x, y], dtype=torch.float64))


def make_candidates(
    odom: list, world: list, path: list, submap: list | None = None, quality: list | None = None
):
    n = len(odom)
    return LoopClosureCandidates(
        submap_index=torch.tensor(submap if submap is not None else list(range(n))),
        patch_index=torch.zeros(n, dtype=torch.int64),
        time=torch.tensor(path, dtype=torch.float64),
        path_length_m=torch.tensor(path, dtype=torch.float64),
        T_odom_base=torch.stack([_se2(*p) for p in odom]),
        T_world_base=torch.stack([_se2(*p) for p in world]),
        probability=torch.ones(n, dtype=torch.float64),
        quality=torch.tensor(quality if quality is not None else [1.0] * n, dtype=torch.float64),
        n_associations=torch.full((n,), 10),
    )


T_WORLD_ODOM = (30.0, -12.0, 0.7)


def _world(odom_pose: tuple, dx: float = 0.0, dyaw_deg: float = 0.0) -> tuple:
    T = _se2(*T_WORLD_ODOM) @ _se2(*odom_pose)
    return (
        float(T[0, 2]) + dx,
        float(T[1, 2]),
        math.atan2(float(T[1, 0]), float(T[0, 0])) + math.radians(dyaw_deg),
    )


CFG = BackendConfig()


def test_consistent_pair_scores_one() -> None:
    odom = [(0.0, 0.0, 0.0), (10.0, 3.0, 0.4)]
    c = make_candidates(odom, [_world(p) for p in odom], [0.0, 10.5])
    s = consistency_scores(c, CFG)
    assert s[0, 1] == pytest.approx(1.0) and s[1, 0] == pytest.approx(1.0)
    assert s[0, 0] == 0.0


def test_translation_error_against_path_length() -> None:
    odom = [(0.0, 0.0, 0.0), (10.0, 0.0, 0.0)]
    world = [_world(odom[0]), _world(odom[1], dx=3.0)]  # 3 m off
    near = consistency_scores(make_candidates(odom, world, [0.0, 0.0]), CFG)
    assert near[0, 1] == 0.0  # 3 m > sigma_t(0) = 2 m
    far = consistency_scores(make_candidates(odom, world, [0.0, 100.0]), CFG)
    sigma = 2.0 + 0.05 * 100.0  # 7 m at 100 m of path
    assert far[0, 1] == pytest.approx(math.sqrt(math.exp(-9.0 / (2 * sigma**2))))
    ablation = BackendConfig(path_length_scaling=False)
    assert consistency_scores(make_candidates(odom, world, [0.0, 100.0]), ablation)[0, 1] == 0.0


def test_yaw_error_and_same_submap() -> None:
    odom = [(0.0, 0.0, 0.0), (0.0, 0.0, 0.0)]
    world = [_world(odom[0]), _world(odom[1], dyaw_deg=4.0)]
    s = consistency_scores(make_candidates(odom, world, [0.0, 0.0]), CFG)
    assert s[0, 1] == pytest.approx(math.sqrt(math.exp(-16.0 / 50.0)))
    world[1] = _world(odom[1], dyaw_deg=6.0)  # beyond 5 deg
    assert consistency_scores(make_candidates(odom, world, [0.0, 0.0]), CFG)[0, 1] == 0.0
    same = make_candidates(odom, [_world(odom[0])] * 2, [0.0, 0.0], submap=[3, 3])
    assert consistency_scores(same, CFG)[0, 1] == 0.0


def test_affinity_fuses_quality_geometrically() -> None:
    odom = [(0.0, 0.0, 0.0), (5.0, 1.0, 0.2), (9.0, 4.0, 0.1)]
    c = make_candidates(odom, [_world(p) for p in odom], [0.0, 5.0, 10.0], quality=[1.0, 0.5, 1e-13])
    M = consistency_affinity(c, CFG)
    assert torch.allclose(M.diagonal(), torch.ones(3, dtype=torch.float64))
    assert M[0, 1] == pytest.approx(0.5 ** (1 / 3))
    assert M[0, 2] == 0.0  # cbrt(1e-13) < affinity_eps


def _slow_scores(c: LoopClosureCandidates, cfg: BackendConfig) -> torch.Tensor:
    n = len(c)
    s = torch.zeros(n, n, dtype=torch.float64)
    for i in range(n):
        for j in range(i + 1, n):
            if c.submap_index[i] == c.submap_index[j]:
                continue
            odom_rel = se2_inverse(c.T_odom_base[i]) @ c.T_odom_base[j]
            cv_rel = se2_inverse(c.T_world_base[i]) @ c.T_world_base[j]
            E = se2_inverse(odom_rel) @ cv_rel
            e_yaw = abs(math.atan2(float(E[1, 0]), float(E[0, 0])))
            e_t = float(E[:2, 2].norm())
            length = abs(float(c.path_length_m[j] - c.path_length_m[i]))
            sy = math.radians(cfg.sigma_yaw_deg + cfg.sigma_yaw_deg_per_m * length)
            stt = cfg.sigma_t_m + cfg.sigma_t_m_per_m * length
            if e_yaw < sy and e_t < stt:
                s[i, j] = s[j, i] = math.sqrt(
                    math.exp(-(e_yaw**2) / (2 * sy**2)) * math.exp(-(e_t**2) / (2 * stt**2))
                )
    return s


def test_batched_scores_match_a_loop_over_pairs() -> None:
    rng = np.random.default_rng(0)
    n = 30
    odom = [tuple(v) for v in np.c_[rng.uniform(-50, 50, (n, 2)), rng.uniform(-3, 3, n)]]
    # a mix of exactly consistent, slightly noisy and wrong measurements, a few sharing a submap
    world = [
        _world(p, dx=float(rng.choice([0.0, 1.0, 2.5, 20.0])), dyaw_deg=float(rng.normal(0, 2))) for p in odom
    ]
    c = make_candidates(
        odom, world, list(np.sort(rng.uniform(0, 200, n))), submap=list(rng.integers(0, 20, n))
    )
    s = consistency_scores(c, CFG)
    assert torch.allclose(s, _slow_scores(c, CFG), atol=1e-12)
    assert (s > 0).sum() > 10 and (s == 0).sum() > 10  # both outcomes occur


@settings(max_examples=40, deadline=None)
@given(
    st.tuples(*[st.floats(-100, 100)] * 2, st.floats(-math.pi, math.pi)),
    st.tuples(*[st.floats(-100, 100)] * 2, st.floats(-math.pi, math.pi)),
    st.tuples(*[st.floats(-100, 100)] * 2, st.floats(-math.pi, math.pi)),
)
def test_errors_are_invariant_to_the_world_frame(a, b, world_frame) -> None:
    # Moving every world measurement by one rigid transform changes nothing; the closed-form
    # errors equal |yaw(E)| and |xy(E)| of E = odom_rel^-1 cv_rel.
    odom = [a, b]
    world = [_world(a, dx=1.5, dyaw_deg=3.0), _world(b)]
    c = make_candidates(odom, world, [0.0, 50.0])
    e = pair_errors(c, CFG)
    moved = LoopClosureCandidates(**{**c.__dict__, "T_world_base": _se2(*world_frame) @ c.T_world_base})
    e2 = pair_errors(moved, CFG)
    assert torch.allclose(e.translation_error, e2.translation_error, atol=1e-9)
    assert torch.allclose(e.yaw_error, e2.yaw_error, atol=1e-9)
    E = se2_inverse(se2_inverse(c.T_odom_base[0]) @ c.T_odom_base[1]) @ (
        se2_inverse(c.T_world_base[0]) @ c.T_world_base[1]
    )
    assert float(e.translation_error[0, 1]) == pytest.approx(float(E[:2, 2].norm()), abs=1e-9)
    assert float(e.yaw_error[0, 1]) == pytest.approx(
        abs(math.atan2(float(E[1, 0]), float(E[0, 0]))), abs=1e-9
    )


def _pool(seed: int = 0):
    """12 submaps along a path: one correct candidate each (submap 5's shifted 15 m), 3 random wrong ones."""
    rng = np.random.default_rng(seed)
    odom, world, path, submap = [], [], [], []
    for i in range(12):
        p = (8.0 * i, 2.0 * math.sin(i), 0.1 * i)
        for k in range(4):
            odom.append(p)
            path.append(8.0 * i)
            submap.append(i)
            if k == 0:
                world.append(_world(p, dx=15.0 if i == 5 else float(rng.normal(0, 0.3))))
            else:
                world.append(
                    (float(rng.uniform(-200, 200)), float(rng.uniform(-200, 200)), float(rng.uniform(-3, 3)))
                )
    return make_candidates(odom, world, path, submap=submap)


def test_clipper_rejects_the_corrupted_and_wrong_closures() -> None:
    c = _pool()
    sel = select_inliers(c, CFG, torch.Generator().manual_seed(0))
    expected = torch.zeros(len(c), dtype=torch.bool)
    expected[[4 * i for i in range(12) if i != 5]] = True
    assert torch.equal(sel.inliers, expected)
    assert sel.score > 10.0  # density of an 11-clique of affinities near 1
    # Chunked solving (forced with tiny chunks) finds the same set.
    chunked = select_inliers(c, BackendConfig(max_clipper_candidates=10), torch.Generator().manual_seed(0))
    assert torch.equal(chunked.inliers, expected)


def test_windowed_selection_is_select_inliers_up_to_the_limit_and_bounded_beyond(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    c = _pool(3)
    whole = select_inliers(c, CFG, torch.Generator().manual_seed(0))
    same = select_inliers_in_windows(c, CFG, torch.Generator().manual_seed(0))
    assert torch.equal(same.inliers, whole.inliers) and same.score == whole.score
    assert all(torch.equal(a, b) for a, b in zip(same.edges, whole.edges))

    # Beyond the limit: shuffled input, windows of whole consecutive submaps, each graph bounded.
    shuffled = c.select(torch.randperm(len(c), generator=torch.Generator().manual_seed(1)))
    solved: list[LoopClosureCandidates] = []
    real = consistency.select_inliers

    def recording(candidates, *args, **kwargs):
        solved.append(candidates)
        return real(candidates, *args, **kwargs)

    monkeypatch.setattr(consistency, "select_inliers", recording)
    limit = 10
    windowed = select_inliers_in_windows(shuffled, BackendConfig(max_clipper_candidates=limit),
                                         torch.Generator().manual_seed(0))
    *windows, pooled = solved
    assert len(windows) == len(c) // limit + 1
    spans = [sorted(set(w.submap_index.tolist())) for w in windows]
    assert sorted(s for span in spans for s in span) == list(range(12)), "each submap in exactly one window"
    assert all(span == list(range(span[0], span[-1] + 1)) for span in spans), "windows of consecutive submaps"
    assert all(len(w) <= limit + 4 for w in windows)  # the limit, plus at most one submap's candidates
    assert len(pooled) <= 12 and windowed.edges is None
    expected = torch.zeros(len(c), dtype=torch.bool)
    expected[[4 * i for i in range(12) if i != 5]] = True
    assert torch.equal(windowed.inliers, expected[torch.randperm(len(c), generator=torch.Generator().manual_seed(1))])


def test_candidates_from_hypotheses() -> None:
    T_odom_base = pose_from_xyz_yaw(np.array([3.0, 4.0, 1.5]), np.array(0.3))
    submap = GroundSubmap(
        index=7,
        time=12.5,
        T_odom_base=T_odom_base,
        path_length_m=40.0,
        primitives=PrimitiveSet.empty(4),
        frame_descriptors=torch.ones(1, 4),
    )
    theta = torch.tensor([[0.1, 0.2, 0.0], [0.5, 0.0, 0.0]])
    t = torch.tensor([[[1.0, 2.0], [3.0, 4.0], [0.0, 0.0]], [[5.0, 6.0], [0.0, 0.0], [0.0, 0.0]]])
    valid = torch.tensor([[True, True, False], [True, False, False]])
    assoc = torch.zeros(2, 3, 6, dtype=torch.bool)
    assoc[0, 0, :5] = True
    assoc[0, 1, :2] = True  # too few associations: dropped, but still counts for the quality ratio
    assoc[1, 0, :3] = True
    hyps = Hypotheses(
        T_world_odom=se2_matrix(theta, t),
        theta=theta,
        t=t,
        probability=torch.tensor([[0.2, 0.4, 0.0], [0.1, 0.0, 0.0]]),
        association_mask=assoc,
        objective=torch.ones(2, 3),
        valid=valid,
        pairs=torch.zeros(2, 6, 2, dtype=torch.int64),
    )
    c = candidates_from_hypotheses(hyps, submap, torch.tensor([11, 4]), min_associations=3, quality_scope="patch")
    assert c.patch_index.tolist() == [11, 4]
    assert c.quality.tolist() == pytest.approx([0.5, 1.0])
    # Relative to the submap's best over both patches: patch 4's best is a quarter of patch 11's.
    across = candidates_from_hypotheses(hyps, submap, torch.tensor([11, 4]), min_associations=3, quality_scope="submap")
    assert across.quality.tolist() == pytest.approx([0.5, 0.25])
    assert torch.equal(across.T_world_base, c.T_world_base)
    assert c.submap_index.tolist() == [7, 7] and c.path_length_m.tolist() == [40.0, 40.0]
    expected = se2_matrix(theta[0, 0].double(), t[0, 0].double()) @ _se2(3.0, 4.0, 0.3)
    assert torch.allclose(c.T_world_base[0], expected, atol=1e-6)


def test_pruned_solve_equals_the_full_dense_solve() -> None:
    from meridian_torch.matching.clipper import solve_clipper

    # Many wrong candidates over a small area, so that some of them agree with each other by chance.
    rng = np.random.default_rng(4)
    odom, world, path, submap = [], [], [], []
    for i in range(15):
        p = (10.0 * i, 0.0, 0.05 * i)
        for k in range(30):
            odom.append(p)
            path.append(10.0 * i)
            submap.append(i)
            world.append(
                _world(p, dx=float(rng.normal(0, 0.5)))
                if k == 0
                else (float(rng.uniform(0, 60)), float(rng.uniform(0, 60)), float(rng.uniform(-0.5, 0.5)))
            )
    c = make_candidates(odom, world, path, submap=submap, quality=list(rng.uniform(0.2, 1.0, len(odom))))
    M = consistency_affinity(c, CFG)
    assert int((M > 0).sum()) > len(c) + 100  # plenty of chance edges
    full = solve_clipper(M, generator=torch.Generator().manual_seed(0), cfg=CFG.clipper)
    sel = select_inliers(c, CFG, torch.Generator().manual_seed(0))
    assert torch.equal(sel.inliers, full.inliers[0])
    assert sel.inliers[::30].all() and sel.count == 15


def test_a_failed_clipper_solve_falls_back_to_the_greedy_clique(monkeypatch) -> None:
    from meridian_torch.matching.clipper import ClipperResult

    def empty_solve(n, edges, *args, **kwargs):
        dtype = edges[2].dtype
        z = torch.zeros(1, dtype=dtype)
        return ClipperResult(
            inliers=torch.zeros(1, n, dtype=torch.bool),
            u=torch.zeros(1, n, dtype=dtype),
            score=z,
            objective=z,
            iterations=torch.zeros(1, dtype=torch.int64),
            penalty_updates=torch.zeros(1, dtype=torch.int64),
            converged=torch.ones(1, dtype=torch.bool),
        )

    monkeypatch.setattr(consistency, "solve_clipper_sparse", empty_solve)
    c = _pool()
    sel = select_inliers(c, CFG)
    expected = torch.zeros(len(c), dtype=torch.bool)
    expected[[4 * i for i in range(12) if i != 5]] = True
    assert torch.equal(sel.inliers, expected) and sel.score > 10.0


def _sparse_equal_to_dense(c: LoopClosureCandidates, cfg: BackendConfig):
    """The sparse edges of `c`, after checking they rebuild the dense affinity: the same edges, the
    same values up to rounding (vectorised and scalar math kernels may differ in the last bit)."""
    dense = consistency_affinity(c, cfg)
    i, j, v = sparse_affinity(c, cfg)
    rebuilt = torch.zeros_like(dense)
    rebuilt[i, j] = v
    rebuilt = rebuilt + rebuilt.T
    rebuilt.diagonal().fill_(1.0)
    assert torch.equal(rebuilt > 0, dense > 0) and bool((i < j).all())
    torch.testing.assert_close(rebuilt, dense, rtol=0.0, atol=1e-12)
    return i, j, v


def test_known_edges_of_a_prefix_give_the_same_graph_and_inliers() -> None:
    c = _pool(seed=5)
    _sparse_equal_to_dense(c, CFG)
    n_known = 21
    prefix = select_inliers(c.select(torch.arange(n_known)), CFG)
    grown = select_inliers(c, CFG, torch.Generator().manual_seed(0), known_edges=(n_known, prefix.edges))
    fresh = select_inliers(c, CFG, torch.Generator().manual_seed(0))
    assert torch.equal(grown.inliers, fresh.inliers)

    def key(e):
        return sorted(zip(e[0].tolist(), e[1].tolist(), e[2].tolist()))

    assert key(grown.edges) == key(fresh.edges)


def _near_gate_pool(rng: np.random.Generator, n_submaps: int, per_submap: int) -> LoopClosureCandidates:
    """Submaps along a winding path; candidates scattered around the true world pose at the scale of
    the gates (up to 3 sigma in x-y and yaw), so many pairs sit near them, and a third spread over
    600 m (so both the radius query and the every-pair block of `sparse_affinity` are used); the
    pool order is shuffled so the earlier-indexed candidate of a pair is from either submap."""
    odom, world, path, submap = [], [], [], []
    x = y = yaw = length = 0.0
    for s in range(n_submaps):
        step = float(rng.uniform(5.0, 60.0))
        yaw += float(rng.normal(0.0, 0.5))
        x, y, length = x + step * math.cos(yaw), y + step * math.sin(yaw), length + step
        sigma_t = 2.0 + 0.05 * length
        for _ in range(per_submap):
            odom.append((x, y, yaw))
            path.append(length)
            submap.append(s)
            if rng.random() < 1 / 3:
                world.append((float(rng.uniform(-300, 300)), float(rng.uniform(-300, 300)), float(rng.uniform(-3, 3))))
                continue
            dx, dy = rng.normal(0.0, sigma_t, 2)
            T = _world((x, y, yaw), dx=float(dx), dyaw_deg=float(rng.normal(0.0, 8.0)))
            world.append((T[0], T[1] + float(dy), T[2]))
    order = rng.permutation(len(odom))
    c = make_candidates(odom, world, path, submap=submap, quality=rng.uniform(0.05, 1.0, len(odom)).tolist())
    return c.select(torch.from_numpy(order))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scaling=st.booleans(), fuse=st.booleans(), tiny_chunks=st.booleans())
def test_sparse_affinity_equals_the_dense_matrix(seed: int, scaling: bool, fuse: bool, tiny_chunks: bool) -> None:
    rng = np.random.default_rng(seed)
    c = _near_gate_pool(rng, n_submaps=int(rng.integers(2, 9)), per_submap=int(rng.integers(1, 12)))
    cfg = BackendConfig(path_length_scaling=scaling, fuse_quality=fuse)
    with (mock.patch.object(consistency, "_CHUNK_PAIRS", 7 if tiny_chunks else consistency._CHUNK_PAIRS),
          mock.patch.object(consistency, "_CHUNK_QUERIES", 3 if tiny_chunks else consistency._CHUNK_QUERIES)):
        i, j, v = _sparse_equal_to_dense(c, cfg)
    # a prefix's edges plus the new pairs are the whole graph
    first_new = int(rng.integers(0, len(c) + 1))
    head = sparse_affinity(c.select(torch.arange(first_new)), cfg)
    tail = sparse_affinity(c, cfg, first_new=first_new)
    assert bool((tail[1] >= first_new).all())
    # the same edges; values to rounding (vectorised and scalar kernels may differ in the last bit,
    # depending on how a batch falls into SIMD lanes)
    joined = sorted(zip(*(torch.cat([a, b]).tolist() for a, b in zip(head, tail))))
    whole = sorted(zip(i.tolist(), j.tolist(), v.tolist()))
    assert [e[:2] for e in joined] == [e[:2] for e in whole]
    np.testing.assert_allclose([e[2] for e in joined], [e[2] for e in whole], rtol=0, atol=1e-12)


def _tree_pairs(points, heading, centres, radius, centre_heading, max_gap):
    """`ball_heading_pairs`' plain definition: scipy's radius query, then torch's heading test."""
    from scipy.spatial import cKDTree

    from meridian_torch.geometry.se2 import wrap_angle

    hits = cKDTree(points).query_ball_point(centres, radius, return_sorted=True) if len(centres) else []
    centre = np.array([c for c, h in enumerate(hits) for _ in h], dtype=np.int64)
    point = np.array([p for h in hits for p in h], dtype=np.int64)
    gap = wrap_angle(torch.from_numpy(heading[point] - centre_heading[centre])).abs().numpy()
    near = gap < max_gap[centre]
    return centre[near], point[near]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 300), k=st.integers(0, 60), spread=st.sampled_from([1.0, 50.0, 1e4]))
def test_ball_heading_pairs_equal_the_tree_query_and_heading_test(seed: int, n: int, k: int, spread: float) -> None:
    rng = np.random.default_rng(seed)
    # integer grids put points exactly on radii (3-4-5 triangles) and headings exactly on gaps
    points = np.round(rng.uniform(0, spread, (n, 2))) if rng.random() < 0.5 else rng.uniform(0, spread, (n, 2))
    centres = points[rng.integers(0, n, k)] + np.round(rng.normal(0, 3, (k, 2))) if n and rng.random() < 0.5 \
        else rng.uniform(-5, spread + 5, (k, 2))
    radius = np.where(rng.random(k) < 0.3, np.round(rng.uniform(0, 6, k)), rng.uniform(0, spread / 3, k))
    heading = rng.uniform(-2 * np.pi, 2 * np.pi, n)
    centre_heading = rng.uniform(-2 * np.pi, 2 * np.pi, k)
    if n and k:
        heading[: n // 4] = centre_heading[rng.integers(0, k, n // 4)] + rng.choice([np.pi, -np.pi, 2 * np.pi, 0.25], n // 4)
    max_gap = rng.choice([0.25, 0.1, 1.0, 3.5], k)
    got = ball_heading_pairs(points, heading, centres, radius, centre_heading, max_gap)
    want = _tree_pairs(points, heading, centres, radius, centre_heading, max_gap)
    for g, w in zip(got, want):
        assert g.dtype == np.int64
        np.testing.assert_array_equal(g, w)


def test_ball_heading_pairs_skip_what_is_not_finite() -> None:
    points = np.array([[0.0, 0.0], [np.nan, 1.0], [1.0, np.inf], [2.0, 0.0]])
    centres = np.array([[0.0, 0.0], [np.nan, 0.0], [1.0, 0.0]])
    ones = np.ones(3)
    centre, point = ball_heading_pairs(points, np.zeros(4), centres, ones * 5, np.zeros(3), ones)
    assert centre.tolist() == [0, 0, 2, 2] and point.tolist() == [0, 3, 0, 3]
    for empty in (np.zeros((0, 2)), np.full((2, 2), np.nan)):
        centre, point = ball_heading_pairs(empty, np.zeros(len(empty)), centres, ones, np.zeros(3), ones)
        assert len(centre) == len(point) == 0


def _tree_submap_edges(c, features, heading, cfg, mine, others):
    """The earlier `_submap_edges`: a scipy tree per heading bin, its hits filtered in torch."""
    queries, query_xy, query_radius, query_sigma_yaw, wide, n_bins = consistency._queries(c, cfg, mine, others)
    mine_bin, query_bin = (consistency._heading_bin(heading[x], n_bins) for x in (mine, queries))
    parts = []
    for b in range(n_bins):
        members = mine[mine_bin == b]
        near_bin = (query_bin - b) % n_bins
        searching = torch.nonzero((near_bin <= 1) | (near_bin == n_bins - 1) | (n_bins == 1)).flatten()
        if len(members) == 0 or len(searching) == 0:
            continue
        for k in range(0, len(searching), consistency._CHUNK_QUERIES):
            q = searching[k : k + consistency._CHUNK_QUERIES]
            centre, point = (torch.from_numpy(x) for x in _tree_pairs(
                c.T_world_base[members, :2, 2].numpy(), heading[members].numpy(), query_xy[q].numpy(),
                query_radius[q].numpy(), heading[queries[q]].numpy(), query_sigma_yaw[q].numpy()))
            parts.append(consistency._pair_edges(features, cfg, members[point], queries[q][centre]))
    return consistency._cat_edges([*parts, consistency._block_edges(features, cfg, mine, others[wide])])


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scaling=st.booleans(), fuse=st.booleans(), tiny_chunks=st.booleans())
def test_sparse_affinity_equals_the_tree_query_bitwise(seed: int, scaling: bool, fuse: bool, tiny_chunks: bool) -> None:
    rng = np.random.default_rng(seed)
    c = _near_gate_pool(rng, n_submaps=int(rng.integers(2, 9)), per_submap=int(rng.integers(1, 40)))
    cfg = BackendConfig(path_length_scaling=scaling, fuse_quality=fuse)
    first_new = int(rng.integers(0, len(c) + 1))
    with mock.patch.object(consistency, "_CHUNK_QUERIES", 3 if tiny_chunks else consistency._CHUNK_QUERIES):
        got = sparse_affinity(c, cfg, first_new=first_new)
        with mock.patch.object(consistency, "_submap_edges", _tree_submap_edges):
            want = sparse_affinity(c, cfg, first_new=first_new)
    for g, w in zip(got, want):
        assert torch.equal(g, w)


@pytest.mark.parametrize("split", [False, True])
def test_submap_groups_equal_unique_rows(split: bool) -> None:
    rng = np.random.default_rng(3)
    c = _near_gate_pool(rng, n_submaps=6, per_submap=5)
    if split:  # one candidate of a submap with another odometry pose: its own group
        T = c.T_odom_base.clone()
        T[4, 0, 2] += 1.0
        c = LoopClosureCandidates(**{**c.__dict__, "T_odom_base": T})
    keys, group = consistency._submap_groups(c)
    T = c.T_odom_base
    key = torch.stack(
        [c.submap_index.to(torch.float64), c.path_length_m, T[:, 0, 2], T[:, 1, 2], T[:, 0, 0], T[:, 1, 0]], dim=1
    )
    want_keys, want_group = torch.unique(key, dim=0, return_inverse=True)
    assert torch.equal(keys, want_keys) and torch.equal(group, want_group)
    assert len(keys) == 6 + split
    empty_keys, empty_group = consistency._submap_groups(LoopClosureCandidates.empty())
    assert empty_keys.shape == (0, 6) and len(empty_group) == 0

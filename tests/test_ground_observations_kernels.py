"""The compiled grouped-cloud kernels (`mapping.cloud_kernels`) against slow all-pairs loops per
group, the outlier mask and the occluded-point clearance built on them against the former
KD-tree computations (bitwise), the runs' means against NumPy's reduceat (bitwise), and the
tracker's occluded-voxel test against a loop over all pairs and its sorted merge against
np.insert."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from meridian_torch.mapping.cloud_kernels import (
    group_any_within,
    group_dbscan_labels,
    group_knn_distances,
    merge_sorted_rows,
    run_means,
    voxels_reached,
)
from meridian_torch.mapping.ground_observations import (
    group_any_point_within,
    group_outlier_mask,
    separate_groups,
    voxel_hash,
    voxel_unhash,
)
from meridian_torch.mapping.ground_tracking import _COLUMN_OFFSETS


def _cloud(rng: np.random.Generator, sizes: list[int], dims: int) -> tuple[np.ndarray, np.ndarray]:
    """Groups of blobs on a coarse lattice (duplicate points, zero distances) and continuous
    points, some far out (long searches), in overlapping space."""
    clouds = []
    for size in sizes:
        kind = rng.integers(3)
        if kind == 0:  # lattice: many duplicates
            p = rng.integers(-3, 4, (size, dims)) * 0.25
        elif kind == 1:  # a flat blob, like ground
            p = rng.normal(size=(size, dims)) * np.r_[2.0, 1.0, 0.05][:dims]
        else:  # a blob with far points
            p = rng.normal(size=(size, dims)) * 0.5
            far = rng.random(size) < 0.1
            p[far] += rng.normal(size=(int(far.sum()), dims)) * 20.0
        clouds.append(p + rng.normal(size=dims))
    points = np.concatenate(clouds) if clouds else np.zeros((0, dims))
    return np.ascontiguousarray(points), np.repeat(np.arange(len(sizes)), sizes)


def _starts(groups: np.ndarray, n_groups: int) -> np.ndarray:
    return np.searchsorted(groups, np.arange(n_groups + 1))  # empty groups give empty runs


def _dist2(p: np.ndarray) -> np.ndarray:
    """All-pairs squared distances in cKDTree's order of operations (x, then y, then z)."""
    d2 = np.zeros((len(p), len(p)))
    for a in range(p.shape[1]):
        d = p[:, None, a] - p[None, :, a]
        d2 = d2 + d * d
    return d2


# ------------------------------------------------------------------------------------ k-NN

_SIZES = st.lists(st.sampled_from([0, 1, 2, 5, 11, 40, 49, 120, 300]), min_size=0, max_size=5)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), _SIZES, st.integers(0, 12), st.sampled_from([2, 3]))
def test_group_knn_distances_match_all_pairs(seed, sizes, k, dims):
    rng = np.random.default_rng(seed)
    points, groups = _cloud(rng, sizes, dims)
    dist = group_knn_distances(points, _starts(groups, len(sizes)), k)
    assert dist.shape == (len(points), k)
    for g in range(len(sizes)):
        p = points[groups == g]
        expected = np.full((len(p), k), np.inf)
        if len(p):
            d = np.sqrt(np.sort(_dist2(p), axis=1))[:, 1 : k + 1]  # drop the point itself
            expected[:, : d.shape[1]] = d
        assert np.array_equal(dist[groups == g], expected)  # bitwise


def test_group_knn_distances_of_nothing():
    assert group_knn_distances(np.zeros((0, 3)), np.array([0]), 4).shape == (0, 4)
    assert group_knn_distances(np.zeros((0, 2)), np.array([0, 0, 0]), 4).shape == (0, 4)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), _SIZES, st.integers(1, 12), st.floats(0.0, 2.0), st.sampled_from([2, 3]))
def test_group_outlier_mask_equals_kd_tree_mask(seed, sizes, neighbours, std_ratio, dims):
    # the former computation: one KD-tree over the groups moved apart (unsorted groups here)
    rng = np.random.default_rng(seed)
    points, groups = _cloud(rng, sizes, dims)
    perm = rng.permutation(len(points))
    points, groups = points[perm], groups[perm]
    keep = group_outlier_mask(points, groups, neighbours, std_ratio)
    expected = np.ones(len(points), dtype=bool)
    if len(points) >= 2:
        shifted = separate_groups(points, groups, 1e6)
        dist = cKDTree(shifted).query(shifted, k=neighbours + 1, distance_upper_bound=5e5)[0][:, 1:]
        found = np.isfinite(dist)
        mean_d = np.where(found, dist, 0.0).sum(axis=1) / np.maximum(found.sum(axis=1), 1)
        has = found.any(axis=1)
        for g in np.unique(groups[has]):
            m = has & (groups == g)
            expected[m] = mean_d[m] <= mean_d[m].mean() + std_ratio * mean_d[m].std()
    assert np.array_equal(keep, expected)


# ---------------------------------------------------------------------------------- DBSCAN


def _dbscan_labels(p: np.ndarray, w: np.ndarray, eps: float, min_points: float) -> np.ndarray:
    """Weighted DBSCAN by all pairs, with the kernel's rules: border points take the nearest core
    point within eps (ties: lowest row); labels in the order of each cluster's first core row."""
    d2 = _dist2(p)
    near = d2 <= eps * eps
    core = (near * w[None]).sum(axis=1) >= min_points
    label = np.full(len(p), -1)
    n_labels = 0
    for i in np.flatnonzero(core):
        if label[i] >= 0:
            continue
        label[i], stack = n_labels, [i]
        while stack:
            j = stack.pop()
            for q in np.flatnonzero(near[j] & core & (label < 0)):
                label[q] = n_labels
                stack.append(q)
        n_labels += 1
    for i in np.flatnonzero(~core):
        cand = np.flatnonzero(near[i] & core)
        if len(cand):
            label[i] = label[cand[np.argmin(d2[i, cand])]]  # argmin: the first (lowest) of ties
    return label


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), _SIZES, st.integers(1, 12), st.sampled_from([2, 3]))
def test_group_dbscan_labels_match_all_pairs(seed, sizes, min_points, dims):
    rng = np.random.default_rng(seed)
    points, groups = _cloud(rng, sizes, dims)
    weight = rng.integers(1, 4, len(points)).astype(np.float64)  # integers: exact weight sums
    eps = 0.6
    label = group_dbscan_labels(points, weight, _starts(groups, len(sizes)), eps, float(min_points))
    offset = 0
    for g in range(len(sizes)):
        m = groups == g
        expected = _dbscan_labels(points[m], weight[m], eps, min_points)
        expected[expected >= 0] += offset  # labels count on over the groups
        assert np.array_equal(label[m], expected)
        offset = max(offset, label[m].max(initial=-1) + 1)


def test_group_dbscan_labels_of_nothing_and_lone_points():
    assert len(group_dbscan_labels(np.zeros((0, 3)), np.zeros(0), np.array([0]), 0.5, 3.0)) == 0
    points = np.array([[0.0, 0.0], [10.0, 0.0]])
    label = group_dbscan_labels(points, np.array([3.0, 1.0]), np.array([0, 1, 2]), 0.5, 3.0)
    assert label.tolist() == [0, -1]  # a point heavy enough is a cluster of its own


def test_group_dbscan_border_tie_goes_to_the_lowest_row():
    # X is exactly eps from a core point of each of two clusters and is not core itself
    a1, a, x, b, b1 = [-0.9, 0.0], [0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [2.9, 0.0]
    weight = {tuple(a1): 4.0, tuple(a): 1.0, tuple(x): 1.0, tuple(b): 1.0, tuple(b1): 4.0}
    for rows, x_cluster in (([a1, a, x, b, b1], 0), ([b1, b, x, a, a1], 0), ([a1, b, x, a, b1], 1)):
        points = np.array(rows)
        w = np.array([weight[tuple(r)] for r in rows])
        label = group_dbscan_labels(points, w, np.array([0, 5]), 1.0, 5.0)
        assert label[rows.index(x)] == x_cluster
        assert np.array_equal(label, _dbscan_labels(points, w, 1.0, 5.0))


# ------------------------------------------------------------------- occluded voxels reached


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 120), st.integers(0, 150), st.sampled_from([0.05, 0.1, 0.2]))
def test_voxels_reached_match_all_pairs(seed, n_points, n_voxels, radius):
    voxel = 0.1
    rng = np.random.default_rng(seed)
    raw = rng.normal(size=(n_points, 3)) * 0.3 + 500.0
    raw[: n_points // 3] = np.round(raw[: n_points // 3] / 0.05) * 0.05  # on voxel faces and centres
    keys, first = np.unique(voxel_hash(raw, voxel), return_index=True)
    points = raw[first]
    near = rng.normal(size=(n_voxels, 3)) * 0.3 + 500.0
    voxel_keys = np.unique(voxel_hash(near, voxel))
    centres = voxel_unhash(voxel_keys, voxel)
    reached = voxels_reached(voxel_keys, centres, keys, points, _COLUMN_OFFSETS, radius)
    # all pairs: points in the 27 voxels around, NumPy's norm
    point_index = np.floor(points / voxel).astype(np.int64)
    voxel_index = np.floor(centres / voxel).astype(np.int64)
    expected = np.zeros(len(voxel_keys), dtype=bool)
    for v in range(len(voxel_keys)):
        around = (np.abs(point_index - voxel_index[v]) <= 1).all(axis=1)
        expected[v] = bool((np.linalg.norm(points[around] - centres[v], axis=1) <= radius).any())
    assert np.array_equal(reached, expected)


def test_voxels_reached_at_exactly_the_radius_from_either_side():
    voxel = 0.5  # binary-exact centres and distances
    point = np.array([[0.5, 0.25, 0.25]])  # voxel (1, 0, 0), 0.25 from the centre of voxel (0, 0, 0)
    cloud_keys = voxel_hash(point, voxel)
    lone = voxel_hash(np.array([[0.25, 0.25, 0.25]]), voxel)
    many = np.unique(voxel_hash(np.array([[0.25, 0.25, 0.25], [2.0, 2.0, 2.0], [-1.0, 0.0, 0.0]]), voxel))
    for voxel_keys in (lone, many):  # searched from the voxels, then from the cloud
        centres = voxel_unhash(voxel_keys, voxel)
        reached = voxels_reached(voxel_keys, centres, cloud_keys, point, _COLUMN_OFFSETS, 0.25)
        assert reached.tolist() == [bool(k == lone[0]) for k in voxel_keys]
        assert not voxels_reached(voxel_keys, centres, cloud_keys, point, _COLUMN_OFFSETS, 0.2499).any()


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 50), st.integers(0, 50), st.integers(0, 3))
def test_merge_sorted_rows_equals_insert_at_searchsorted(seed, n, m, columns):
    rng = np.random.default_rng(seed)
    keys = np.sort(rng.integers(0, 40, n))  # duplicates and keys shared with the new ones
    new_keys = np.sort(rng.integers(0, 40, m))
    rows, new_rows = rng.normal(size=(n, columns)), rng.normal(size=(m, columns))
    merged_keys, merged_rows = merge_sorted_rows(keys, rows, new_keys, new_rows)
    pos = np.searchsorted(keys, new_keys)
    assert np.array_equal(merged_keys, np.insert(keys, pos, new_keys))
    assert np.array_equal(merged_rows, np.insert(rows, pos, new_rows, axis=0))


# ----------------------------------------------------------------------------------- runs' means


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 400), st.integers(1, 4),
       st.sampled_from([0.0, 0.003, 0.05, 0.5, 1.0]))
def test_run_means_equal_reduceat_of_the_gathered_rows(seed, n, columns, run_start_rate):
    # runs of 1 to 400 rows: every branch of NumPy's pairwise sum (< 8, <= 128, halved above)
    rng = np.random.default_rng(seed)
    # magnitudes far apart (the order of the sums shows in the rounding), signed zeros, repeats
    values = rng.normal(size=(n, columns)) * 10.0 ** rng.integers(-8, 9, (n, columns))
    values[rng.random((n, columns)) < 0.1] = -0.0
    order = rng.permutation(n)
    first = rng.random(n) < run_start_rate
    first[:1] = True
    means, heads, counts = run_means(values, order, first)
    start = np.flatnonzero(first)
    expected = np.add.reduceat(values[order], start, axis=0) / np.diff(np.r_[start, n])[:, None] if n else \
        np.zeros((0, columns))
    assert means.shape == expected.shape
    assert np.array_equal(means.view(np.int64), expected.view(np.int64))  # bitwise, -0.0 included
    assert np.array_equal(heads, order[start])
    assert np.array_equal(counts, np.diff(np.r_[start, n]))


# ----------------------------------------------------------------------------- any within


def _tree_within(queries: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """The former clearance expression: cKDTree's neighbour within distance_upper_bound."""
    if len(queries) == 0 or len(points) == 0:
        return np.zeros(len(queries), dtype=bool)
    return np.isfinite(cKDTree(points).query(queries, distance_upper_bound=radius)[0])


def _clearance_clouds(rng: np.random.Generator, sizes: list[tuple[int, int]], dims: int, radius: float,
                      step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per group (queries, points): queries on a lattice of `step` (a fraction of the radius: many
    pairs exactly or nearly at the radius) over a wider box than the points, some far out; points
    on the lattice, or just inside / at / outside the radius of a query, or continuous."""
    queries, points = [], []
    for n_q, n_p in sizes:
        offset = rng.normal(size=dims) * 100.0
        q = rng.integers(-12, 13, (n_q, dims)) * step
        far = rng.random(n_q) < 0.1
        q[far] += rng.normal(size=(int(far.sum()), dims)) * 50.0
        kind = rng.integers(3)
        if kind == 0 or n_q == 0:
            p = rng.integers(-8, 9, (n_p, dims)) * step
        elif kind == 1:  # on the sphere of a query, up to a few ulps in or out
            u = rng.normal(size=(n_p, dims))
            u /= np.linalg.norm(u, axis=1, keepdims=True)
            p = q[rng.integers(n_q, size=n_p)] + u * radius * (1.0 + rng.integers(-3, 4, (n_p, 1)) * 1e-16)
        else:
            p = rng.normal(size=(n_p, dims)) * 8.0 * step
        queries.append(q + offset)
        points.append(p + offset)
    q_groups = np.repeat(np.arange(len(sizes)), [n for n, _ in sizes])
    p_groups = np.repeat(np.arange(len(sizes)), [n for _, n in sizes])
    return (np.concatenate(queries) if queries else np.zeros((0, dims)), q_groups,
            np.concatenate(points) if points else np.zeros((0, dims)), p_groups)


_PAIR_SIZES = st.lists(st.tuples(st.sampled_from([0, 1, 3, 60, 200]), st.sampled_from([0, 1, 2, 48, 49, 300])),
                       min_size=0, max_size=4)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), _PAIR_SIZES, st.sampled_from([2, 3]), st.sampled_from([0.1, 0.3, 1 / 3, 0.07, 0.5]),
       st.sampled_from([1.0, 0.5, 0.25, 0.2, 1 / 3, 0.6]))
def test_group_any_within_equals_kd_tree(seed, sizes, dims, radius, step):
    rng = np.random.default_rng(seed)
    queries, q_groups, points, p_groups = _clearance_clouds(rng, sizes, dims, radius, step * radius)
    q_starts, p_starts = _starts(q_groups, len(sizes)), _starts(p_groups, len(sizes))
    # each group on its own coordinates (lattice distances exactly at the radius)
    within = group_any_within(queries, q_starts, points, p_starts, radius)
    for g in range(len(sizes)):
        expected = _tree_within(queries[q_groups == g], points[p_groups == g], radius)
        assert np.array_equal(within[q_groups == g], expected)
    # the clearance of frame_observations: one tree over the groups moved apart
    both = separate_groups(np.concatenate([queries, points]), np.concatenate([q_groups, p_groups]), 1e6)
    n = len(queries)
    within = group_any_within(both[:n], q_starts, both[n:], p_starts, radius)
    assert np.array_equal(within, _tree_within(both[:n], both[n:], radius))
    # the same through `group_any_point_within` (the clearance's and the submap artefact test's
    # entry), its groups in any order
    qp, pp = rng.permutation(n), rng.permutation(len(points))
    got = group_any_point_within(queries[qp], q_groups[qp], points[pp], p_groups[pp], radius)
    assert np.array_equal(got, within[qp])


def test_group_any_within_is_strict_on_the_squared_radius():
    # found iff 0 + dx*dx + dy*dy (+ dz*dz) < radius * radius, both rounded as cKDTree does
    for radius in (0.5, 0.1, 0.3):
        below = np.nextafter(radius, 0.0)
        for dims in (2, 3):
            pts = np.zeros((60, dims))  # a grid-searched group: more than 48 points
            pts[:, 0] = 10.0 + np.arange(60)
            pts[0, 0] = radius  # exactly at the radius
            pts[1, :2] = [0.6 * radius, 0.8 * radius]  # at the radius up to rounding
            queries = np.zeros((1, dims))
            for rows in ([0], [1], [0, 1]):
                p = pts[np.r_[rows, 2:60]]
                got = group_any_within(queries, np.array([0, 1]), p, np.array([0, len(p)]), radius)
                assert got.tolist() == _tree_within(queries, p, radius).tolist()
            pts[0, 0] = below
            got = group_any_within(queries, np.array([0, 1]), pts, np.array([0, 60]), radius)
            assert got.tolist() == [True] == _tree_within(queries, pts, radius).tolist()
    # 0.1 * 0.1 rounds to above 0.01: a point at 0.1 is outside, as for the tree
    p = np.array([[0.1, 0.0]])
    assert group_any_within(np.zeros((1, 2)), np.array([0, 1]), p, np.array([0, 1]), 0.1).tolist() == [False]
    # pairs where sqrt(d2) < radius or the sum from z to x would decide otherwise (radius 0.1)
    cases = [([-1.091, -1.355, 0.225], [-1.1538675917658108, -1.288678549012366, 0.2656094945112867], True),
             ([0.869, 0.461, 0.488], [0.9634315653086254, 0.49321613820662685, 0.4946932736694637], True),
             ([0.069, 0.208, 0.205], [0.05228941021916782, 0.1966491756039631, 0.10706167770118234], False)]
    for point, query, inside in cases:
        q = np.array([query])
        for p in (np.array([point]), np.r_[[point], np.arange(180.0).reshape(60, 3) + 5.0]):  # brute, grid
            got = group_any_within(q, np.array([0, 1]), p, np.array([0, len(p)]), 0.1)
            assert got.tolist() == [inside] == _tree_within(q, p, 0.1).tolist()


@pytest.mark.parametrize("dims", [2, 3])
def test_group_any_within_finds_points_just_inside_across_cell_borders(dims):
    # a point just inside the radius of each of many queries, in all directions and at all
    # offsets to the grid's cells: none may be missed (the searched cells reach far enough)
    rng = np.random.default_rng(dims)
    radius = 0.1
    n = 40000
    queries = rng.uniform(0.0, 50.0, (n, dims)) + 1e6
    u = rng.normal(size=(n, dims))
    u[np.arange(n // 2), rng.integers(dims, size=n // 2)] *= 1e3  # half nearly along an axis
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    points = queries + u * radius * (1.0 - 1e-9)
    d2 = np.zeros(len(points))
    for a in range(dims):  # cKDTree's order
        d2 = d2 + (points[:, a] - queries[:, a]) ** 2
    q, p = queries[d2 < radius * radius], points[d2 < radius * radius]
    assert len(q) > 0.99 * n
    got = group_any_within(q, np.array([0, len(q)]), p, np.array([0, len(p)]), radius)
    assert got.all() and np.array_equal(got, _tree_within(q, p, radius))


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([2, 3]), st.sampled_from([0.0, -0.3, np.inf, np.nan, 1e-200, 1e3]),
       st.sampled_from([1, 10, 100]))
def test_group_any_within_odd_radii_and_queries(seed, dims, radius, n_points):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n_points, dims))
    queries = rng.normal(size=(30, dims)) * 2.0
    queries[:4] = points[0]  # on a point
    queries[4, 0], queries[5, 1], queries[6, :] = np.nan, np.inf, -np.inf  # the tree refuses these
    queries[7] = 1e300
    got = group_any_within(queries, np.array([0, 30]), points, np.array([0, n_points]), radius)
    assert not got[4:7].any()
    finite = np.r_[0:4, 7:30]
    with np.errstate(over="ignore"):
        assert np.array_equal(got[finite], _tree_within(queries[finite], points, radius))


def test_group_any_within_of_nothing():
    assert len(group_any_within(np.zeros((0, 3)), np.array([0]), np.zeros((0, 3)), np.array([0]), 0.1)) == 0
    got = group_any_within(np.zeros((2, 3)), np.array([0, 1, 2]), np.zeros((1, 3)), np.array([0, 0, 1]), 0.1)
    assert got.tolist() == [False, True]  # the first group has no points

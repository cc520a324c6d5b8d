"""Per-frame ground observations: grouped point-cloud ops against slow loops and brute-force
references, back-projection of a known plane, the image-edge band and the occluded points."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from meridian_torch.config import CloudCleanupConfig, GroundObservationConfig
from meridian_torch.geometry.se3 import pose_from_xyz_yaw
from meridian_torch.io.camera import CameraModel
from meridian_torch.mapping import ground_observations
from meridian_torch.mapping.ground_observations import (
    _nonzero,
    edge_band,
    erode_masks,
    frame_observations,
    group_key_runs,
    group_largest_cluster,
    group_outlier_mask,
    group_voxel_downsample,
    group_voxel_runs,
    pixel_stride,
    separate_groups,
    voxel_hash,
    voxel_unhash,
)

# optical frame (x right, y down, z forward) -> base (x forward, y left, z up), level camera
R_BASE_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _camera(width: int = 160, height: int = 90, height_m: float = 1.2) -> CameraModel:
    T = np.eye(4)
    T[:3, :3] = R_BASE_CAMERA
    T[2, 3] = height_m
    f = width / 2.0
    return CameraModel(width, height, f, f, (width - 1) / 2, (height - 1) / 2, 1000.0, T)


def _ground_depth(camera: CameraModel) -> np.ndarray:
    """Depth of the plane z_base = 0 seen by the level camera (0 above the horizon)."""
    v = np.arange(camera.height, dtype=np.float64)[:, None] * np.ones((1, camera.width))
    down = (v - camera.cy) / camera.fy  # ray (x, y, 1) hits y * z = height
    depth = np.where(down > 1e-6, camera.T_base_camera[2, 3] / np.maximum(down, 1e-9), 0.0)
    return depth.astype(np.float32)


# ------------------------------------------------------------------------------ voxel keys


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-5000, 5000, allow_nan=False)] * 3), min_size=1, max_size=30),
       st.sampled_from([0.1, 0.25, 1.0]))
def test_voxel_hash_roundtrip(points, voxel):
    p = np.array(points)
    centres = voxel_unhash(voxel_hash(p, voxel), voxel)
    assert np.all(np.abs(centres - p) <= voxel / 2 + 1e-6 * (1 + np.abs(p)))
    # equal keys <=> same voxel index
    idx = np.floor(p / voxel).astype(np.int64)
    same_idx = (idx[:, None] == idx[None]).all(-1)
    keys = voxel_hash(p, voxel)
    assert np.array_equal(keys[:, None] == keys[None], same_idx)


def test_voxel_hash_rejects_out_of_range():
    with pytest.raises(ValueError):
        voxel_hash(np.array([[2e6, 0.0, 0.0]]), 1.0)


# --------------------------------------------------------------- grouped ops vs slow loops


def _random_groups(rng, n_groups=5, n=400):
    groups = np.sort(rng.integers(0, n_groups, n))
    points = rng.normal(size=(n, 3)) * 2.0 + groups[:, None] * 0.7  # groups overlap in space
    return points, groups


def test_group_voxel_downsample_matches_loop():
    rng = np.random.default_rng(0)
    points, groups = _random_groups(rng)
    out, out_groups = group_voxel_downsample(points, groups, 0.5)
    for g in np.unique(groups):
        p = points[groups == g]
        keys = voxel_hash(p, 0.5)
        expected = np.array(sorted((k, *p[keys == k].mean(axis=0)) for k in np.unique(keys)))[:, 1:]
        got = out[out_groups == g]
        got = got[np.argsort(voxel_hash(got, 0.5))]
        np.testing.assert_allclose(got, expected, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 300), st.integers(1, 8), st.sampled_from([2, 3]),
       st.sampled_from([0.05, 0.1, 0.5]), st.sampled_from([1.0, 100.0, 2e5]))
def test_group_voxel_runs_equal_the_sort_of_voxel_keys(seed, n, n_groups, dims, voxel, spread_voxels):
    rng = np.random.default_rng(seed)
    groups = np.sort(rng.integers(0, n_groups, n)) * int(rng.integers(1, 4))  # gaps between group ids
    points = rng.normal(size=(n, dims)) * spread_voxels * voxel
    points[rng.random(n) < 0.2] = points[0] if n else 0.0  # duplicates
    points[: n // 4] = np.floor(points[: n // 4] / voxel) * voxel  # exactly on voxel faces
    if rng.random() < 0.5:  # groups unsorted
        groups = rng.permutation(groups)
    order, first = group_voxel_runs(points, groups, voxel)
    expected_order, expected_first = group_key_runs(voxel_hash(points, voxel), groups)
    assert np.array_equal(order, expected_order)
    assert np.array_equal(first, expected_first)


def test_group_voxel_runs_of_ranges_beyond_one_key():
    # 1.8e6 voxels along each axis and 4 groups: more than 2^62 (group, voxel) keys, the fallback sort
    rng = np.random.default_rng(0)
    points = rng.uniform(-9e5, 9e5, (500, 3))
    points[:2] = [[-9e5] * 3, [9e5 - 1] * 3]
    groups = rng.integers(0, 4, 500)
    order, first = group_voxel_runs(points, groups, 1.0)
    expected_order, expected_first = group_key_runs(voxel_hash(points, 1.0), groups)
    assert np.array_equal(order, expected_order) and np.array_equal(first, expected_first)


def test_group_voxel_runs_rejects_out_of_range():
    with pytest.raises(ValueError):
        group_voxel_runs(np.array([[0.0, 0.0, 0.0], [2e6, 0.0, 0.0]]), np.zeros(2, np.int64), 1.0)


def test_group_outlier_mask_matches_loop():
    rng = np.random.default_rng(1)
    points, groups = _random_groups(rng)
    keep = group_outlier_mask(points, groups, 10, 1.0)
    for g in np.unique(groups):
        p = points[groups == g]
        d, _ = cKDTree(p).query(p, k=11)
        mean_d = d[:, 1:].mean(axis=1)
        expected = mean_d <= mean_d.mean() + mean_d.std()
        assert np.array_equal(keep[groups == g], expected)
    assert 0 < keep.sum() < len(keep)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 6), st.integers(1, 120), st.sampled_from([2, 3]))
def test_separate_groups_matches_loop(seed, n_groups, n, dims):
    rng = np.random.default_rng(seed)
    groups = rng.integers(0, n_groups, n)  # unsorted, some groups possibly empty
    points = rng.normal(size=(n, dims)) * 30.0 + 1000.0
    gap = 5.0
    shifted = separate_groups(points, groups, gap)
    lo = np.zeros((n_groups, dims))
    for g in np.unique(groups):
        lo[g] = points[groups == g].min(axis=0)
    local = points - lo[groups]
    expected = local.copy()
    expected[:, 0] += groups * (local.max() + gap)
    assert np.array_equal(shifted, expected)
    # groups at least `gap` apart along x
    for g, h in zip(np.unique(groups)[:-1], np.unique(groups)[1:]):
        assert shifted[groups == h, 0].min() - shifted[groups == g, 0].max() >= gap


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(st.integers(1, 60), min_size=1, max_size=6),
       st.integers(1, 12), st.floats(0.0, 2.0))
def test_group_outlier_mask_matches_brute_force(seed, sizes, neighbours, std_ratio):
    # groups of any size, also smaller than `neighbours` + 1 and single points (kept)
    rng = np.random.default_rng(seed)
    groups = np.repeat(np.arange(len(sizes)), sizes)
    points = rng.normal(size=(len(groups), 3)) * rng.uniform(0.1, 3.0, (len(groups), 1)) + groups[:, None] * 0.3
    keep = group_outlier_mask(points, groups, neighbours, std_ratio)
    for g in range(len(sizes)):
        p = points[groups == g]
        if len(p) < 2:
            assert keep[groups == g].all()
            continue
        d = np.sort(np.linalg.norm(p[:, None] - p[None], axis=-1), axis=1)[:, 1 : neighbours + 1]
        mean_d = d.mean(axis=1)
        assert np.array_equal(keep[groups == g], mean_d <= mean_d.mean() + std_ratio * mean_d.std())


def _naive_dbscan_largest(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    n = len(points)
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    nb = d <= eps
    core = nb.sum(1) >= min_points
    label = -np.ones(n, dtype=int)
    c = 0
    for i in range(n):
        if not core[i] or label[i] >= 0:
            continue
        stack = [i]
        label[i] = c
        while stack:
            j = stack.pop()
            for k in np.flatnonzero(nb[j]):
                if label[k] < 0:
                    label[k] = c
                    if core[k]:
                        stack.append(k)
        c += 1
    if c == 0:
        return np.zeros(n, dtype=bool)
    sizes = np.bincount(label[label >= 0])
    return label == np.argmax(sizes)


def test_group_largest_cluster_matches_naive_dbscan_on_grid_points():
    # points at the centres of the eps/4 cells: the binning is then exact
    rng = np.random.default_rng(2)
    eps, cell = 1.0, 0.25
    groups, clouds = [], []
    for g in range(3):
        blobs = [rng.integers(-4, 4, size=(rng.integers(15, 60), 3)) + off
                 for off in ([0, 0, 0], [12 + g, 0, 0], [0, 15, 0])]
        cells = np.unique(np.concatenate(blobs), axis=0)
        cells = np.concatenate([cells, [[40, 40, 40]]])  # an isolated noise point
        clouds.append((cells + 0.5) * cell)
        groups.append(np.full(len(cells), g))
    points, groups = np.concatenate(clouds), np.concatenate(groups)
    keep, has = group_largest_cluster(points, groups, eps, 10)
    assert has.all()
    for g in range(3):
        expected = _naive_dbscan_largest(points[groups == g], eps, 10)
        assert np.array_equal(keep[groups == g], expected)


def _dbscan_clusters(points: np.ndarray, eps: float, min_points: int) -> tuple[list[set[int]], np.ndarray]:
    """Brute-force DBSCAN: the clusters (point index sets, border points in every cluster they
    touch) and the core mask."""
    nb = np.linalg.norm(points[:, None] - points[None], axis=-1) <= eps
    core = nb.sum(1) >= min_points
    clusters, seen = [], np.zeros(len(points), dtype=bool)
    for i in np.flatnonzero(core):
        if seen[i]:
            continue
        members, stack = {int(i)}, [int(i)]
        seen[i] = True
        while stack:
            j = stack.pop()
            for k in np.flatnonzero(nb[j] & core & ~seen):
                seen[k] = True
                members.add(int(k))
                stack.append(int(k))
        clusters.append(members | {int(k) for k in np.flatnonzero(nb[list(members)].any(0))})
    return clusters, core


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 4), st.integers(3, 12))
def test_group_largest_cluster_matches_brute_force_dbscan(seed, n_groups, min_points):
    # points at eps/4 cell centres, several points per cell (weights), blobs and noise; compared
    # where DBSCAN's answer is unique (no border point between clusters, no tie for the largest)
    rng = np.random.default_rng(seed)
    eps, cell = 1.0, 0.25
    clouds, groups = [], []
    for g in range(n_groups):
        blobs = [rng.integers(-3, 4, size=(rng.integers(1, 50), 3)) + rng.integers(-12, 13, 3)
                 for _ in range(rng.integers(1, 4))]
        cells = np.concatenate(blobs)  # repeated cells: several points in one cell
        clouds.append((cells + 0.5) * cell)
        groups.append(np.full(len(cells), g))
    points, groups = np.concatenate(clouds), np.concatenate(groups)
    order = rng.permutation(len(points))
    points, groups = points[order], groups[order]
    keep, has = group_largest_cluster(points, groups, eps, min_points)
    for g in range(n_groups):
        clusters, _ = _dbscan_clusters(points[groups == g], eps, min_points)
        in_many = sum((np.bincount(list(c), minlength=int((groups == g).sum())) for c in clusters),
                      np.zeros((groups == g).sum(), dtype=int))
        sizes = sorted((len(c) for c in clusters), reverse=True)
        assume(in_many.max(initial=0) <= 1 and (len(sizes) < 2 or sizes[0] > sizes[1]))
        assert has[g] == bool(clusters)
        expected = np.zeros((groups == g).sum(), dtype=bool)
        if clusters:
            expected[list(max(clusters, key=len))] = True
        assert np.array_equal(keep[groups == g], expected)


def test_group_largest_cluster_reports_groups_without_cluster():
    points = np.array([[0.0, 0, 0], [5.0, 0, 0], [0.0, 0, 0.05], [0.02, 0, 0]])
    keep, has = group_largest_cluster(points, np.array([0, 0, 1, 1]), 0.5, 3)
    assert not has.any() and not keep.any()


# ---------------------------------------------------------------------------- image ops


def test_edge_band_matches_loop():
    rng = np.random.default_rng(3)
    valid = np.ones((40, 70), dtype=bool)
    valid[:12] = False  # sky
    valid[20:25, 30:50] = rng.random((5, 20)) > 0.5
    frac, max_frac = 0.05, 0.2
    band = edge_band(valid, frac, max_frac)
    e, cap = frac * 70, max_frac * 70
    expected = np.zeros_like(valid)
    for r in range(40):
        cols = np.flatnonzero(valid[r])
        if len(cols):
            for c in range(70):
                expected[r, c] |= c < min(cols[0] + e, cap) or c >= max(cols[-1] - e, 70 - cap)
    for c in range(70):
        rows = np.flatnonzero(valid[:, c])
        if len(rows):
            for r in range(40):
                expected[r, c] |= r < min(rows[0] + e, cap) or r >= max(rows[-1] - e, 40 - cap)
    assert np.array_equal(band, expected)
    assert band[12:14].all() and not band[14:35, 20].any()  # hugs the valid region's top edge, capped


def test_erode_masks_keeps_image_border_and_shrinks_inner_edges():
    m = np.zeros((2, 30, 40), dtype=bool)
    m[0, :, :20] = True  # touches the left, top and bottom image borders
    m[1, 10:20, 25:35] = True
    out = erode_masks(m, 3)
    assert out[0, 0, 0] and out[0, 29, 0] and not out[0, 15, 19] and out[0, 15, 16]
    assert out[1].sum() == 4 * 4 and out[1, 13:17, 28:32].all()


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(st.integers(0, 7), min_size=1, max_size=3), st.floats(0.0, 1.0))
def test_nonzero_matches_numpy(seed, shape, density):
    a = np.random.default_rng(seed).random(shape) < density
    expected, got = np.nonzero(a), _nonzero(a)
    assert len(got) == len(expected)
    assert all(x.dtype == y.dtype and np.array_equal(x, y) for x, y in zip(got, expected))


def test_pixel_stride_scales_with_width():
    cfg = GroundObservationConfig()
    assert [pixel_stride(cfg, w) for w in (1280, 1241, 640, 480, 128)] == [4, 3, 2, 1, 1]
    assert pixel_stride(GroundObservationConfig(pixel_stride=3), 480) == 3


# ---------------------------------------------------------------------- frame observations


@settings(max_examples=15, deadline=None)
@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-np.pi, np.pi), st.floats(0.8, 2.0))
def test_backprojected_ground_plane_lies_on_the_plane(x, y, yaw, height):
    camera = _camera(height_m=height)
    depth = _ground_depth(camera)
    T_odom_base = pose_from_xyz_yaw(np.array([x, y, 0.0]), np.array(yaw))
    T_odom_camera = T_odom_base @ camera.T_base_camera
    masks = torch.zeros(1, camera.height, camera.width, dtype=torch.bool)
    masks[0, camera.height // 2 + 1 :] = True
    cfg = GroundObservationConfig(pixel_stride=1, cleanup=CloudCleanupConfig(dbscan_eps_m=0.6))
    obs = frame_observations(masks, torch.ones(1, 4) / 2, depth, T_odom_camera, 0.0, camera, cfg)
    assert len(obs) == 1
    pts = np.concatenate([obs.points, obs.occluded])
    assert np.abs(pts[:, 2]).max() < 1e-4  # on the odom plane z = 0
    ahead = (pts[:, :2] - [x, y]) @ [np.cos(yaw), np.sin(yaw)]
    assert ahead.min() > 0 and ahead.max() <= cfg.max_depth_m + 0.1
    # the far band (depth > 9 m) is occluded, not real
    real_ahead = (obs.points[:, :2] - [x, y]) @ [np.cos(yaw), np.sin(yaw)]
    assert real_ahead.max() <= cfg.occlusion_max_depth_m + 0.15


def test_backprojection_of_fronto_parallel_plane():
    camera = _camera(120, 80)
    depth = np.full((80, 120), 4.0, dtype=np.float32)
    masks = np.zeros((2, 80, 120), dtype=bool)
    masks[0, 20:60, 30:90] = True  # inside the view
    masks[1, :, :10] = True  # along the left image edge
    cfg = GroundObservationConfig(pixel_stride=2)
    obs = frame_observations(torch.from_numpy(masks), torch.eye(2), depth, np.eye(4), 1.5, camera, cfg)
    assert obs.time == 1.5 and list(obs.mask_index) == [0, 1]
    inner = obs.points[obs.point_obs == 0]
    assert np.allclose(inner[:, 2], 4.0, atol=1e-9)
    # x = (u - cx) z / fx: the eroded mask spans columns 33..86 (7x7 ellipse)
    u = inner[:, 0] * camera.fx / 4.0 + camera.cx
    assert u.min() > 32 and u.max() < 87 and not len(obs.occluded[obs.occluded_obs == 0])
    # the edge mask: its image-edge band pixels are occluded, real points stay clear of them
    occ = obs.occluded[obs.occluded_obs == 1]
    u_occ = occ[:, 0] * camera.fx / 4.0 + camera.cx
    v_occ = occ[:, 1] * camera.fy / 4.0 + camera.cy
    e = 0.02 * 120  # band width in pixels (+ half a 0.1 m voxel = 1.5 px at 4 m)
    assert len(occ) and np.all((u_occ < e + 1.6) | (v_occ < e + 1.6) | (v_occ > 79 - e - 1.6))
    real = obs.points[obs.point_obs == 1]
    assert cKDTree(occ).query(real)[0].min() > cfg.occluded_clearance_m


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(-50, 50), st.floats(-np.pi, np.pi), st.sampled_from([0.1, 0.3]))
def test_clearance_kernel_gives_the_kd_tree_observations(seed, x, yaw, clearance):
    # the former clearance: one KD-tree over the occluded points of all masks moved apart
    def kd_tree_within(queries, query_starts, points, point_starts, radius):
        return np.isfinite(cKDTree(points).query(queries, distance_upper_bound=radius)[0])

    rng = np.random.default_rng(seed)
    camera = _camera()
    depth = _ground_depth(camera) * (1.0 + 0.02 * rng.random((camera.height, camera.width))).astype(np.float32)
    edges = np.sort(rng.choice(np.arange(1, camera.width), 5, replace=False))
    masks = np.zeros((6, camera.height, camera.width), dtype=bool)
    for m, (u0, u1) in enumerate(zip(np.r_[0, edges], np.r_[edges, camera.width])):  # strips to the edges
        masks[m, camera.height // 2 + 1 :, u0:u1] = True
    T_odom_camera = pose_from_xyz_yaw(np.array([x, 0.0, 0.0]), np.array(yaw)) @ camera.T_base_camera
    cfg = GroundObservationConfig(pixel_stride=1, occluded_clearance_m=clearance,
                                  cleanup=CloudCleanupConfig(dbscan_eps_m=0.6))
    obs = frame_observations(masks, torch.eye(6), depth, T_odom_camera, 0.0, camera, cfg)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ground_observations, "group_any_within", kd_tree_within)
        expected = frame_observations(masks, torch.eye(6), depth, T_odom_camera, 0.0, camera, cfg)
    for field in ("points", "point_obs", "occluded", "occluded_obs", "mask_index"):
        assert np.array_equal(getattr(obs, field), getattr(expected, field))
    assert torch.equal(obs.descriptors, expected.descriptors)
    unclear = frame_observations(masks, torch.eye(6), depth, T_odom_camera, 0.0, camera,
                                 cfg.model_copy(update={"occluded_clearance_m": 0.0}))
    assert len(obs.points) < len(unclear.points)  # the clearance deleted points


def test_mask_without_depth_gives_no_observation():
    camera = _camera(60, 40)
    depth = np.zeros((40, 60), dtype=np.float32)
    depth[20:] = 3.0
    masks = np.zeros((2, 40, 60), dtype=bool)
    masks[0, :15] = True  # sky
    masks[1, 22:] = True
    obs = frame_observations(masks, torch.eye(2), depth, np.eye(4), 0.0, camera, GroundObservationConfig())
    assert list(obs.mask_index) == [1] and len(obs) == 1

"""The coarse global search: planted submaps are found, batched volumes equal slow loops, seeds repeat."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.config.matching import CoarseSearchConfig
from meridian_torch.matching.place_recognition import (
    build_coarse_map,
    chain_scores,
    coarse,
    patch_priors,
    submap_scores,
)
from meridian_torch.matching.place_recognition.coarse import _cell_owners, _map_grid, _rasterise
from meridian_torch.types import PrimitiveBatch, PrimitiveSet
from tests.numerics import reassociation_tolerance

CFG = CoarseSearchConfig(cell_m=2.0, radius_m=20.0, yaws=12, classes=1, blur_cells=1.0)
D = 4


def _random_map(seed: int, side: int = 6, patch_m: float = 40.0, n_points: int = 30, n_lines: int = 20):
    """A side x side grid of patches (50 % overlap) of random points and lines: the decoys."""
    gen = torch.Generator().manual_seed(seed)
    step = patch_m / 2
    corners = torch.stack(torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij"), -1).reshape(-1, 2)
    lo = corners.double() * step
    bounds = torch.stack([lo[:, 0], lo[:, 0] + patch_m, lo[:, 1], lo[:, 1] + patch_m], -1)
    p = len(bounds)
    points = lo[:, None].float() + torch.rand(p, n_points, 2, generator=gen) * patch_m
    start = lo[:, None].float() + torch.rand(p, n_lines, 2, generator=gen) * patch_m
    angle = torch.rand(p, n_lines, generator=gen) * 2 * math.pi
    length = 4 + 8 * torch.rand(p, n_lines, generator=gen)
    end = start + length[..., None] * torch.stack([angle.cos(), angle.sin()], -1)
    batch = PrimitiveBatch(
        points_xy=points,
        point_descriptors=torch.nn.functional.normalize(torch.rand(p, n_points, D, generator=gen), dim=-1),
        point_valid=torch.ones(p, n_points, dtype=torch.bool),
        line_endpoints=torch.stack([start, end], -2),
        line_kinds=torch.zeros(p, n_lines, dtype=torch.int64),
        line_descriptors=torch.nn.functional.normalize(torch.rand(p, n_lines, D, generator=gen), dim=-1),
        line_valid=torch.ones(p, n_lines, dtype=torch.bool),
    )
    return batch, bounds


def _planted_submap(batch: PrimitiveBatch, centre_world: torch.Tensor, yaw: float, t_world_odom: torch.Tensor,
                    radius_m: float) -> PrimitiveSet:
    """The map's primitives within radius_m of centre_world, in the odom frame of T_world_odom(yaw, t)."""
    pts, pdesc = batch.points_xy[batch.point_valid], batch.point_descriptors[batch.point_valid]
    lines, ldesc = batch.line_endpoints[batch.line_valid], batch.line_descriptors[batch.line_valid]
    near_p = (pts - centre_world).norm(dim=-1) < radius_m
    near_l = (lines.mean(-2) - centre_world).norm(dim=-1) < radius_m
    c, s = math.cos(yaw), math.sin(yaw)
    R = torch.tensor([[c, -s], [s, c]])
    to_odom = lambda x: (x - t_world_odom) @ R  # noqa: E731  R^T (x - t) for row vectors
    n_p, n_l = int(near_p.sum()), int(near_l.sum())
    return PrimitiveSet(
        points_xy=to_odom(pts[near_p]), point_descriptors=pdesc[near_p], point_segment_ids=torch.arange(n_p),
        line_endpoints=to_odom(lines[near_l]), line_kinds=torch.zeros(n_l, dtype=torch.int64),
        line_descriptors=ldesc[near_l], line_segment_ids=torch.arange(n_l),
    )


def _odom_centre(centre_world: torch.Tensor, yaw: float, t_world_odom: torch.Tensor) -> torch.Tensor:
    c, s = math.cos(yaw), math.sin(yaw)
    return (centre_world - t_world_odom) @ torch.tensor([[c, -s], [s, c]])


def test_a_planted_submap_is_found_at_its_patch_and_yaw_among_random_decoys() -> None:
    batch, bounds = _random_map(0)
    cmap = build_coarse_map(batch, bounds, CFG)
    for k, (cx, cy) in enumerate([(31.0, 47.0), (75.0, 62.0), (58.0, 29.0)]):
        yaw = (3 + 4 * k) * 2 * math.pi / CFG.yaws  # on the yaw grid
        t = torch.tensor([13.0 * k - 7.0, 5.0])
        centre = torch.tensor([cx, cy])
        ground = _planted_submap(batch, centre, yaw, t, CFG.radius_m)
        priors = patch_priors(cmap, submap_scores(cmap, ground, _odom_centre(centre, yaw, t), CFG), CFG)
        inside = (bounds[:, 0] <= cx) & (cx <= bounds[:, 1]) & (bounds[:, 2] <= cy) & (cy <= bounds[:, 3])
        best = int(priors.score.argmax())
        assert inside[best], (k, best)
        assert abs(math.remainder(float(priors.yaw[best]) - yaw, 2 * math.pi)) < 1e-4
        assert (priors.centre_xy[best] - centre.double()).norm() <= CFG.cell_m * 1.5


def _slow_pearson(cmap, grid, ground, centre_odom, cfg, yaw_index: int, row: int, col: int) -> float:
    """Pearson correlation inside the disk around cell (row, col) of the map's blurred class grids
    `grid` (C, H, W), from the rasters directly."""
    r = int(math.ceil(cfg.radius_m / cfg.cell_m))
    yaw = yaw_index * 2 * math.pi / cfg.yaws
    c, s = math.cos(yaw), math.sin(yaw)
    from meridian_torch.matching.place_recognition.coarse import (
        _blur,
        _channels,
        _n_channels,
        _primitive_points,
    )

    xy, cls, angle = _primitive_points(ground.points_xy, ground.point_descriptors, ground.line_endpoints,
                                ground.line_descriptors, cmap.class_centres, cfg.cell_m / 2)
    xy = (xy - centre_odom.float()) @ torch.tensor([[c, s], [-s, c]])
    half = (r + 0.5) * cfg.cell_m
    n_channels = _n_channels(len(cmap.class_centres), cfg)
    kernel = _blur(_rasterise(xy, _channels(cls, angle + yaw, cfg), (-half, -half), cfg.cell_m, (2 * r + 1,) * 2,
                              n_channels),
                   cfg.blur_cells).double()
    window = torch.nn.functional.pad(grid.double(), (r, r, r, r))[:, row : row + 2 * r + 1, col : col + 2 * r + 1]
    u = torch.arange(-r, r + 1)
    disk = ((u[:, None] ** 2 + u[None] ** 2) <= r * r).expand_as(kernel)
    a, g = window[disk], kernel[disk]
    a, g = a - a.mean(), g - g.mean()
    if a.square().sum() < cfg.min_window_energy:
        return 0.0
    return float((a * g).sum() / (a.norm() * g.norm()))


@pytest.mark.parametrize("cfg", [CFG, CFG.model_copy(update={"classes": 2, "orientation_bins": 3})])
@pytest.mark.parametrize("tile", [None, 48])  # the size the map picks (one tile here), and many small tiles
def test_batched_scores_equal_a_slow_loop_over_cells_and_yaws(cfg: CoarseSearchConfig, tile, monkeypatch) -> None:
    if tile is not None:
        monkeypatch.setattr(coarse, "_tile_size", lambda *args: tile)
    batch, bounds = _random_map(1, side=4)
    cmap = build_coarse_map(batch, bounds, cfg)
    grid, _ = _map_grid(batch, bounds.double(), cmap.class_centres, cfg)
    centre = torch.tensor([40.0, 40.0])
    ground = _planted_submap(batch, centre, 0.7, torch.tensor([3.0, -2.0]), cfg.radius_m)
    centre_odom = _odom_centre(centre, 0.7, torch.tensor([3.0, -2.0]))
    volume = submap_scores(cmap, ground, centre_odom, cfg)
    reused = torch.full_like(volume, float("nan"))  # a buffer of an earlier submap: every cell is rewritten
    assert submap_scores(cmap, ground, centre_odom, cfg, out=reused) is reused and torch.equal(reused, volume)
    h, w = cmap.shape
    side = 2 * math.ceil(cfg.radius_m / cfg.cell_m) + 1
    valid = cmap.tile_size - side + 1
    assert (tile is None) or math.prod(cmap.tile_layout) == math.ceil(h / valid) * math.ceil(w / valid) > 1
    # the FFT's rounding: sums over a tile, relative to the correlation's scale
    tol = reassociation_tolerance(torch.float32, cmap.tile_size**2, side * side)
    gen = torch.Generator().manual_seed(3)
    # random cells, and cells on both sides of every tile border
    cells = [tuple(int(torch.randint(n, (1,), generator=gen)) for n in (h, w)) for _ in range(12)]
    cells += [(min(edge, h - 1), min(edge, w - 1)) for k in range(1, max(cmap.tile_layout) + 1)
              for edge in (k * valid - 1, k * valid)]
    for row, col in cells:
        k = int(torch.randint(cfg.yaws, (1,), generator=gen))
        slow = _slow_pearson(cmap, grid, ground, centre_odom, cfg, k, row, col)
        assert abs(float(volume[k, row, col]) - slow) <= tol, (k, row, col)


def test_patch_priors_equal_a_loop_over_patches() -> None:
    batch, bounds = _random_map(2, side=4)
    cmap = build_coarse_map(batch, bounds, CFG)
    volume = torch.rand((CFG.yaws, *cmap.shape), generator=torch.Generator().manual_seed(0))
    priors = patch_priors(cmap, volume, CFG)
    best, best_yaw = volume.amax(0).reshape(-1), volume.argmax(0).reshape(-1)
    for p in range(cmap.n_patches):
        cells = torch.nonzero(cmap.cell_patch == p).flatten()
        cell = cells[best[cells].argmax()]
        assert float(priors.score[p]) == float(best[cell])
        assert float(priors.yaw[p]) == float(best_yaw[cell]) * 2 * math.pi / CFG.yaws or math.isclose(
            float(priors.yaw[p]), float(best_yaw[cell]) * 2 * math.pi / CFG.yaws, rel_tol=1e-6)
        row, col = divmod(int(cell), cmap.shape[1])
        assert float(priors.centre_xy[p, 0]) == cmap.origin_xy[0] + (col + 0.5) * cmap.cell_m
        assert float(priors.centre_xy[p, 1]) == cmap.origin_xy[1] + (row + 0.5) * cmap.cell_m
        centre = ((bounds[p, 0] + bounds[p, 1]) / 2, (bounds[p, 2] + bounds[p, 3]) / 2)
        assert bounds[p, 0] <= priors.centre_xy[p, 0] <= bounds[p, 1] and centre is not None


def test_chain_step_equals_a_loop_of_shifts_per_yaw() -> None:
    cfg = CoarseSearchConfig(cell_m=2.0, radius_m=10.0, yaws=4, chain_decay=0.5, chain_slack_m=0.0)
    batch, bounds = _random_map(3, side=3)
    cmap = build_coarse_map(batch, bounds, cfg)
    gen = torch.Generator().manual_seed(1)
    previous = torch.rand((4, *cmap.shape), generator=gen)
    scores = torch.rand((4, *cmap.shape), generator=gen)
    step = torch.tensor([6.0, -4.0])  # whole cells at every yaw of a 90 degree grid
    chain = chain_scores(previous, scores, step, cmap, cfg)
    pooled = torch.maximum(previous, torch.maximum(previous.roll(1, 0), previous.roll(-1, 0)))
    h, w = cmap.shape
    for k in range(4):
        c, s = round(math.cos(k * math.pi / 2)), round(math.sin(k * math.pi / 2))
        dx, dy = int((c * step[0] - s * step[1]) / 2), int((s * step[0] + c * step[1]) / 2)
        moved = torch.zeros(h, w)
        for row in range(h):
            for col in range(w):
                if 0 <= row - dy < h and 0 <= col - dx < w:
                    moved[row, col] = pooled[k, row - dy, col - dx]
        assert torch.equal(chain[k], scores[k] + 0.5 * moved)


def _reference_chain(previous: torch.Tensor, scores: torch.Tensor, step: torch.Tensor, cmap, cfg) -> torch.Tensor:
    """The chain step as first written: max_pool2d over the slack, two rolls over the yaws, one
    affine_grid / grid_sample over every yaw."""
    k = math.ceil(cfg.chain_slack_m / cfg.cell_m)
    pooled = torch.nn.functional.max_pool2d(previous[None], 2 * k + 1, stride=1, padding=k)[0]
    pooled = torch.maximum(pooled, torch.maximum(pooled.roll(1, 0), pooled.roll(-1, 0)))
    yaws = torch.arange(cfg.yaws, dtype=torch.float32) * (2 * math.pi / cfg.yaws)
    shift_x = torch.cos(yaws) * step[0] - torch.sin(yaws) * step[1]
    shift_y = torch.sin(yaws) * step[0] + torch.cos(yaws) * step[1]
    h, w = cmap.shape
    theta = torch.zeros(cfg.yaws, 2, 3)
    theta[:, 0, 0] = theta[:, 1, 1] = 1.0
    theta[:, 0, 2] = -shift_x / cfg.cell_m * 2 / w
    theta[:, 1, 2] = -shift_y / cfg.cell_m * 2 / h
    grid = torch.nn.functional.affine_grid(theta, [cfg.yaws, 1, h, w], align_corners=False)
    moved = torch.nn.functional.grid_sample(pooled[:, None], grid, mode="nearest", padding_mode="zeros",
                                            align_corners=False)[:, 0]
    return scores + cfg.chain_decay * moved


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 5), st.sampled_from([0.0, 2.0, 3.0, 4.0]), st.floats(-30.0, 30.0), st.floats(-30.0, 30.0),
       st.booleans(), st.integers(0, 2**31 - 1))
def test_chain_step_equals_pooling_and_sampling_the_whole_volume(
    yaws: int, slack_m: float, dx: float, dy: float, half_cells: bool, seed: int
) -> None:
    """The compiled chain step gives bitwise the volume of max_pool2d, rolls and a full grid_sample,
    also for shifts of half cells (where nearest rounding ties), in place over the previous volume
    or the scores, with the yaws split over 1-3 threads."""
    cfg = CoarseSearchConfig(cell_m=2.0, radius_m=10.0, yaws=yaws, chain_decay=0.7, chain_slack_m=slack_m)
    batch, bounds = _random_map(3, side=3)
    cmap = build_coarse_map(batch, bounds, cfg)
    gen = torch.Generator().manual_seed(seed)
    previous = torch.rand((yaws, *cmap.shape), generator=gen)
    previous[previous < 0.2] = 0.0  # ties in the maxima
    scores = torch.rand((yaws, *cmap.shape), generator=gen)
    step = torch.tensor([round(dx) + 1.0, round(dy) - 1.0]) if half_cells else torch.tensor([dx, dy])
    expected = _reference_chain(previous, scores, step, cmap, cfg)
    threads = torch.get_num_threads()
    try:
        for n in (1, 2, 3):  # yaw ranges side by side, each overwriting planes its neighbours read
            torch.set_num_threads(n)
            assert torch.equal(chain_scores(previous, scores, step, cmap, cfg), expected)
            in_place = previous.clone()
            assert torch.equal(chain_scores(in_place, scores, step, cmap, cfg, out=in_place), expected)
            into_scores = scores.clone()
            assert torch.equal(chain_scores(previous, into_scores, step, cmap, cfg, out=into_scores), expected)
    finally:
        torch.set_num_threads(threads)


def test_patch_priors_take_the_first_yaw_of_a_tie() -> None:
    batch, bounds = _random_map(2, side=3)
    cmap = build_coarse_map(batch, bounds, CFG)
    volume = torch.zeros((CFG.yaws, *cmap.shape))
    volume[[2, 5, 7]] = 1.0  # every cell's best value at yaws 2, 5 and 7
    priors = patch_priors(cmap, volume, CFG)
    on_map = torch.isfinite(priors.score)
    assert on_map.any() and torch.equal(priors.yaw[on_map], torch.full((int(on_map.sum()),), 2 * 2 * math.pi / CFG.yaws))


def test_chaining_finds_a_submap_too_poor_to_be_found_alone() -> None:
    # Each submap keeps a random 10 % of its primitives: alone they are ambiguous, a chain of 6 is not.
    cfg = CFG.model_copy(update={"chain_decay": 1.0})
    batch, bounds = _random_map(4)
    cmap = build_coarse_map(batch, bounds, cfg)
    yaw, t = 4 * 2 * math.pi / cfg.yaws, torch.tensor([-20.0, 9.0])
    gen = torch.Generator().manual_seed(0)
    chain, previous, alone_right = None, None, 0

    def best_xy(volume: torch.Tensor) -> torch.Tensor:
        row, col = divmod(int(volume.amax(0).argmax()), cmap.shape[1])
        return torch.tensor([cmap.origin_xy[0] + (col + 0.5) * cfg.cell_m, cmap.origin_xy[1] + (row + 0.5) * cfg.cell_m])

    for k in range(6):
        centre = torch.tensor([30.0 + 8.0 * k, 35.0 + 4.0 * k])
        full = _planted_submap(batch, centre, yaw, t, cfg.radius_m)
        keep_p = torch.rand(len(full.points_xy), generator=gen) < 0.1
        keep_l = torch.rand(len(full.line_endpoints), generator=gen) < 0.1
        ground = PrimitiveSet(full.points_xy[keep_p], full.point_descriptors[keep_p], full.point_segment_ids[keep_p],
                              full.line_endpoints[keep_l], full.line_kinds[keep_l], full.line_descriptors[keep_l],
                              full.line_segment_ids[keep_l])
        centre_odom = _odom_centre(centre, yaw, t)
        single = submap_scores(cmap, ground, centre_odom, cfg)
        step = centre_odom - previous if previous is not None else torch.zeros(2)
        chain, previous = chain_scores(chain, single, step, cmap, cfg), centre_odom
        alone_right += int((best_xy(single) - centre).norm() <= 2 * cfg.cell_m)
    assert alone_right <= 3  # the scene is hard for single submaps ...
    assert (best_xy(chain) - centre).norm() <= 2 * cfg.cell_m  # ... and the chain finds the last one


def test_seeded_runs_are_identical() -> None:
    cfg = CFG.model_copy(update={"classes": 3, "seed": 5})
    batch, bounds = _random_map(5, side=3)
    runs = []
    for _ in range(2):
        cmap = build_coarse_map(batch, bounds, cfg)
        ground = _planted_submap(batch, torch.tensor([30.0, 30.0]), 0.3, torch.zeros(2), cfg.radius_m)
        volume = submap_scores(cmap, ground, _odom_centre(torch.tensor([30.0, 30.0]), 0.3, torch.zeros(2)), cfg)
        runs.append((cmap.class_centres, cmap.tile_spectra, volume))
    for a, b in zip(*runs):
        assert torch.equal(a, b)


def test_cells_go_to_the_nearest_containing_patch() -> None:
    """Block by block among overlapping patches equals a loop over every cell and patch: the
    nearest containing centre, the lowest index on ties (a 50 % overlap grid has many), -1 off the map."""
    _, bounds = _random_map(3, side=7)
    bounds = bounds[torch.randperm(len(bounds), generator=torch.Generator().manual_seed(0))]  # ties by index, not by order
    origin, cell_m, (h, w) = (-13.0, -9.0), 2.0, (80, 90)  # blocks cross patch edges; cells off the map
    owner = _cell_owners(origin, cell_m, (h, w), bounds).view(h, w)
    centres = torch.stack([(bounds[:, 0] + bounds[:, 1]) / 2, (bounds[:, 2] + bounds[:, 3]) / 2], -1)
    for row in range(0, h, 3):
        for col in range(0, w, 3):
            x, y = origin[0] + (col + 0.5) * cell_m, origin[1] + (row + 0.5) * cell_m
            best, best_d = -1, math.inf
            for p in range(len(bounds)):
                if bounds[p, 0] <= x <= bounds[p, 1] and bounds[p, 2] <= y <= bounds[p, 3]:
                    d = math.hypot(x - float(centres[p, 0]), y - float(centres[p, 1]))
                    if d < best_d:
                        best, best_d = p, d
            assert int(owner[row, col]) == best, (row, col)

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.config.matching import VerificationConfig
from meridian_torch.geometry.se2 import se2_matrix
from meridian_torch.matching.hypotheses import Hypotheses
from meridian_torch.matching.verification import (
    _chunked_alignment,
    alignment_score,
    chance_alignment,
    line_pieces,
    piece_closeness,
    reweight_hypotheses,
    segments_near_points,
)
from meridian_torch.types import LineKind, PrimitiveSet, stack_primitive_sets


def _set(points: torch.Tensor, lines: torch.Tensor) -> PrimitiveSet:
    d = 4
    return PrimitiveSet(
        points_xy=points,
        point_descriptors=torch.nn.functional.normalize(torch.ones(len(points), d, dtype=points.dtype), dim=-1),
        point_segment_ids=torch.arange(len(points)),
        line_endpoints=lines,
        line_kinds=torch.full((len(lines),), int(LineKind.SEGMENT)),
        line_descriptors=torch.nn.functional.normalize(torch.ones(len(lines), d, dtype=lines.dtype), dim=-1),
        line_segment_ids=torch.arange(len(lines)),
    )


def _transform(T: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    return xy @ T[:2, :2].T + T[:2, 2]


def _random_set(gen: torch.Generator, n_points: int, n_lines: int) -> PrimitiveSet:
    points = torch.rand(n_points, 2, generator=gen, dtype=torch.float64) * 40
    start = torch.rand(n_lines, 2, generator=gen, dtype=torch.float64) * 40
    angle = torch.rand(n_lines, generator=gen, dtype=torch.float64) * 2 * math.pi
    length = 2 + torch.rand(n_lines, generator=gen, dtype=torch.float64) * 10
    end = start + length[:, None] * torch.stack([angle.cos(), angle.sin()], -1)
    return _set(points, torch.stack([start, end], 1))


def _loop_alignment(T: torch.Tensor, ground: PrimitiveSet, aerial: PrimitiveSet, cfg: VerificationConfig) -> float:
    """One pose, plain loops: the definition in the module docstring."""
    total = 0.0
    pieces = []
    for (a, b) in ground.line_endpoints:
        k = math.ceil(float((b - a).norm()) / cfg.line_piece_m)
        pieces += [(a + (b - a) * j / k, a + (b - a) * (j + 1) / k) for j in range(k)]
    for (a, b) in pieces:
        a_w, b_w = _transform(T, a[None])[0], _transform(T, b[None])[0]
        mid, u = (a_w + b_w) / 2, (b_w - a_w) / (b_w - a_w).norm()
        best = 0.0  # closeness of the best near-parallel aerial line
        for (c, d) in aerial.line_endpoints:
            v = (d - c) / (d - c).norm()
            t = float(((mid - c) @ (d - c)) / ((d - c) @ (d - c)))
            closest = c + min(max(t, 0.0), 1.0) * (d - c)
            if abs(float(u @ v)) >= math.cos(math.radians(cfg.line_angle_deg)):
                best = max(best, 1.0 - float((mid - closest).norm()) ** 2 / cfg.line_distance_m**2)
        total += float((b - a).norm()) * best
    for p in ground.points_xy:
        p_w = _transform(T, p[None])[0]
        best = max([1.0 - float((p_w - q).norm()) ** 2 / cfg.point_distance_m**2 for q in aerial.points_xy] + [0.0])
        total += cfg.point_weight_m * best
    return total


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0.01, 30.0), min_size=1, max_size=6), st.floats(0.5, 5.0))
def test_line_pieces_tile_each_line_in_equal_pieces(lengths: list[float], piece_m: float) -> None:
    gen = torch.Generator().manual_seed(len(lengths))
    start = torch.rand(len(lengths), 2, generator=gen, dtype=torch.float64) * 100
    angle = torch.rand(len(lengths), generator=gen, dtype=torch.float64) * 2 * math.pi
    end = start + torch.tensor(lengths, dtype=torch.float64)[:, None] * torch.stack([angle.cos(), angle.sin()], -1)
    pieces = line_pieces(torch.stack([start, end], 1), piece_m)
    i = 0
    for n, length in enumerate((end - start).norm(dim=-1).tolist()):
        k = math.ceil(length / piece_m)
        mine = pieces[i : i + k]
        i += k
        torch.testing.assert_close(mine[0, 0], start[n])
        torch.testing.assert_close(mine[-1, 1], end[n])
        torch.testing.assert_close(mine[1:, 0], mine[:-1, 1])  # contiguous
        piece_len = (mine[:, 1] - mine[:, 0]).norm(dim=-1)
        assert bool((piece_len <= piece_m + 1e-9).all())
        torch.testing.assert_close(piece_len, torch.full_like(piece_len, length / k))
    assert i == len(pieces)


@pytest.mark.parametrize("compiled", [True, False])
def test_alignment_score_equals_a_per_pose_loop_with_padding(compiled: bool) -> None:
    # On the CPU one compiled pass over every pose (float64), elsewhere torch's ops: both the definition.
    gen = torch.Generator().manual_seed(3)
    cfg = VerificationConfig(line_distance_m=3.0, line_angle_deg=30.0, point_distance_m=4.0, line_piece_m=3.0)
    ground = _random_set(gen, 6, 9)
    patches = [_random_set(gen, n_p, n_l) for n_p, n_l in [(8, 15), (2, 4), (0, 7)]]  # unequal sizes: padding
    # Poses near the identity, so that some primitives do land on others.
    theta = (torch.rand(3, 5, generator=gen, dtype=torch.float64) - 0.5) * 0.3
    t = (torch.rand(3, 5, 2, generator=gen, dtype=torch.float64) - 0.5) * 4
    T = se2_matrix(theta, t)
    score = alignment_score(T, ground, stack_primitive_sets(patches), cfg, compiled=compiled)
    expected = torch.tensor([[_loop_alignment(T[p, h], ground, patches[p], cfg) for h in range(5)] for p in range(3)],
                            dtype=torch.float64)
    assert expected.max() > 0  # the case exercises both outcomes
    torch.testing.assert_close(score, expected)


@settings(max_examples=25, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-100, 100), st.floats(-100, 100))
def test_true_pose_aligns_the_whole_submap_and_a_shift_does_not(yaw: float, tx: float, ty: float) -> None:
    cfg = VerificationConfig()
    ground = _set(torch.tensor([[0.0, 0.0], [12.0, 3.0]], dtype=torch.float64),
                  torch.tensor([[[0.0, 5.0], [10.0, 5.0]], [[-4.0, -2.0], [-4.0, 8.0]]], dtype=torch.float64))
    T = se2_matrix(torch.tensor(yaw, dtype=torch.float64), torch.tensor([tx, ty], dtype=torch.float64))
    aerial = _set(_transform(T, ground.points_xy), _transform(T, ground.line_endpoints.reshape(-1, 2)).reshape(-1, 2, 2))
    shift = se2_matrix(torch.tensor(0.0, dtype=torch.float64), torch.tensor([3.0, 3.0], dtype=torch.float64))
    poses = torch.stack([T, shift @ T])[None]  # (1, 2, 3, 3)
    score = alignment_score(poses, ground, stack_primitive_sets([aerial]), cfg)
    assert score[0, 0].item() == pytest.approx(10.0 + 10.0 + 2 * cfg.point_weight_m)
    assert score[0, 1].item() < score[0, 0].item()


def _hypotheses(T: torch.Tensor, probability: torch.Tensor, valid: torch.Tensor) -> Hypotheses:
    P, H = probability.shape
    return Hypotheses(
        T_world_odom=T,
        theta=torch.atan2(T[..., 1, 0], T[..., 0, 0]),
        t=T[..., :2, 2],
        probability=probability,
        association_mask=torch.zeros(P, H, 3, dtype=torch.bool),
        objective=torch.arange(P * H, dtype=T.dtype).reshape(P, H),
        valid=valid,
        pairs=torch.zeros(P, 3, 2, dtype=torch.int64),
    )


def _loop_chance(ground: PrimitiveSet, aerial: PrimitiveSet, cfg: VerificationConfig) -> float:
    """The chance poses written out: the ground box centre at the aerial box centre and at the
    four diagonal offsets, at every yaw; the mean of the loop alignment."""
    g = torch.cat([ground.points_xy, ground.line_endpoints.reshape(-1, 2)])
    a = torch.cat([aerial.points_xy, aerial.line_endpoints.reshape(-1, 2)])
    g_centre, a_centre = (g.min(0).values + g.max(0).values) / 2, (a.min(0).values + a.max(0).values) / 2
    scores = []
    for k in range(cfg.chance_yaws):
        yaw = torch.tensor(2 * math.pi * k / cfg.chance_yaws, dtype=torch.float64)
        for dx, dy in ((0, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)):
            R = se2_matrix(yaw, torch.zeros(2, dtype=torch.float64))[:2, :2]
            target = a_centre + cfg.chance_offset_m * torch.tensor([dx, dy], dtype=torch.float64)
            scores.append(_loop_alignment(se2_matrix(yaw, target - R @ g_centre), ground, aerial, cfg))
    return sum(scores) / len(scores)


def test_chance_alignment_is_the_mean_over_its_poses_and_per_patch() -> None:
    gen = torch.Generator().manual_seed(11)
    cfg = VerificationConfig(chance_yaws=5, line_distance_m=3.0, line_angle_deg=30.0)
    ground = _random_set(gen, 5, 10)
    patches = [_random_set(gen, n_p, n_l) for n_p, n_l in ((6, 40), (3, 4), (0, 25))]
    chance = chance_alignment(ground, stack_primitive_sets(patches), cfg)
    expected = torch.tensor([_loop_chance(ground, p, cfg) for p in patches], dtype=torch.float64)
    assert chance.min() > 0
    torch.testing.assert_close(chance, expected)
    alone = chance_alignment(ground, stack_primitive_sets(patches[1:2]), cfg)  # no padding, no neighbours
    torch.testing.assert_close(alone, chance[1:2])
    # Lines everywhere align more by chance than a few; an empty submap aligns nothing.
    assert chance[0] > chance[1]
    empty = _set(torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, 2, 2, dtype=torch.float64))
    assert chance_alignment(empty, stack_primitive_sets(patches), cfg).tolist() == [0.0, 0.0, 0.0]
    assert chance_alignment(ground, stack_primitive_sets([empty, empty]), cfg).tolist() == [0.0, 0.0]


def test_reweighting_ranks_by_alignment_beyond_chance() -> None:
    cfg = VerificationConfig()
    ground = _set(torch.tensor([[5.0, 3.0]], dtype=torch.float64),
                  torch.tensor([[[0.0, 0.0], [10.0, 0.0]]], dtype=torch.float64))
    aerial = _set(torch.tensor([[5.0, 23.0]], dtype=torch.float64),
                  torch.tensor([[[-20.0, 20.0], [30.0, 20.0]], [[0.0, 0.0], [0.0, 10.0]]], dtype=torch.float64))
    # Four poses: the heaviest lays the submap nowhere, the lightest exactly on the patch.
    ty = torch.tensor([[0.0, 20.5, 20.0, 0.0]], dtype=torch.float64)
    T = se2_matrix(torch.zeros(1, 4, dtype=torch.float64), torch.stack([torch.zeros_like(ty), ty], -1))
    mass = torch.tensor([[0.5, 0.2, 0.1, 0.0]], dtype=torch.float64)
    valid = torch.tensor([[True, True, True, False]])
    batch = stack_primitive_sets([aerial])
    out = reweight_hypotheses(_hypotheses(T, mass, valid), ground, batch, cfg, 3)
    assert out.t[0, :, 1].tolist() == [20.0, 20.5, 0.0]
    chance = chance_alignment(ground, batch, cfg).item()
    whole = 10.0 + cfg.point_weight_m
    on_point = 1 - 0.5**2 / cfg.point_distance_m**2
    aligned = [whole, 10.0 * (1 - 0.5**2 / cfg.line_distance_m**2) + cfg.point_weight_m * on_point]
    assert 0 < chance < aligned[1]
    expected = [(a - chance) / whole for a in aligned] + [0.0]
    torch.testing.assert_close(out.probability[0], torch.tensor(expected, dtype=torch.float64))
    assert out.objective[0].tolist() == [2.0, 1.0, 0.0]  # every field follows the new order


def test_reweighting_keeps_the_mass_order_when_nothing_aligns_and_checks_the_count() -> None:
    cfg = VerificationConfig()
    ground = _set(torch.zeros(0, 2, dtype=torch.float64), torch.tensor([[[0.0, 0.0], [10.0, 0.0]]], dtype=torch.float64))
    aerial = _set(torch.tensor([[500.0, 500.0]], dtype=torch.float64), torch.zeros(0, 2, 2, dtype=torch.float64))
    T = se2_matrix(torch.zeros(1, 3, dtype=torch.float64), torch.zeros(1, 3, 2, dtype=torch.float64))
    mass = torch.tensor([[0.3, 0.6, 0.1]], dtype=torch.float64)
    h = _hypotheses(T, mass, torch.ones(1, 3, dtype=torch.bool))
    out = reweight_hypotheses(h, ground, stack_primitive_sets([aerial]), cfg, 3)
    assert out.objective[0].tolist() == [1.0, 0.0, 2.0]  # heaviest first
    assert out.probability[0].tolist() == [0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="n_hypotheses"):
        reweight_hypotheses(h, ground, stack_primitive_sets([aerial]), cfg, 4)


def test_torch_alignment_does_not_depend_on_the_chunk_size() -> None:
    # Other devices score a few patches at a time, by size, without unused padding: sizes differ,
    # one patch has no points. The compiled CPU pass scores all at once: the same to rounding.
    gen = torch.Generator().manual_seed(5)
    ground = _random_set(gen, 4, 6)
    aerial = stack_primitive_sets([_random_set(gen, n_p, n_l) for n_p, n_l in ((5, 8), (0, 3), (9, 2), (2, 12))])
    T = se2_matrix((torch.rand(4, 6, generator=gen, dtype=torch.float64) - 0.5) * 0.2,
                   (torch.rand(4, 6, 2, generator=gen, dtype=torch.float64) - 0.5) * 6)
    runs = [_chunked_alignment(T, ground, aerial, VerificationConfig(line_distance_m=4.0, chunk_pairs=c))
            for c in (1, 6 * 14 * 12 * 2, 10**6)]  # one patch, about two, all per chunk
    compiled = alignment_score(T, ground, aerial, VerificationConfig(line_distance_m=4.0), compiled=True)
    assert (runs[-1] > 0).sum() > 4
    for other in runs[1:] + [compiled]:
        torch.testing.assert_close(runs[0], other)


def test_compiled_alignment_follows_the_torch_ops_in_float32() -> None:
    # Poses near real map coordinates (hundreds of metres) in float32: the compiled pass works in
    # float64, torch's ops in float32, so they agree to float32 rounding of the coordinates.
    gen = torch.Generator().manual_seed(8)
    cfg = VerificationConfig()
    ground = _random_set(gen, 7, 12)
    patches = [_random_set(gen, n_p, n_l) for n_p, n_l in ((9, 30), (0, 14), (5, 0), (12, 25))]
    offset = torch.tensor([412.0, -236.0], dtype=torch.float64)
    for ps in patches:
        ps.points_xy.add_(offset)
        ps.line_endpoints.add_(offset)
    T = se2_matrix((torch.rand(4, 20, generator=gen, dtype=torch.float64) - 0.5) * 0.3,
                   offset + (torch.rand(4, 20, 2, generator=gen, dtype=torch.float64) - 0.5) * 6)
    aerial = stack_primitive_sets(patches).to(dtype=torch.float32)
    T32, ground32 = T.to(torch.float32), ground.to(dtype=torch.float32)
    compiled = alignment_score(T32, ground32, aerial, cfg, compiled=True)
    reference = alignment_score(T32, ground32, aerial, cfg, compiled=False)
    assert compiled.dtype == torch.float32 and (reference > 1.0).sum() > 10
    torch.testing.assert_close(compiled, reference, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize(("radius", "dtype", "offset"), [
    (0.4, torch.float64, 0.0), (1.5, torch.float64, -123.4), (6.0, torch.float64, 0.0), (1.5, torch.float32, 7531.7),
])
def test_segments_near_points_finds_every_close_pair_once(radius: float, dtype: torch.dtype, offset: float) -> None:
    # float32 far from the origin: rounding may put a sample a cell below its patch's lowest one.
    gen = torch.Generator().manual_seed(3)
    ends = (torch.rand(3, 12, 2, 2, generator=gen, dtype=torch.float64) * 30 + offset).to(dtype)
    ends[0, 1, 1] = ends[0, 1, 0]  # a degenerate segment
    points = (torch.rand(3, 40, 2, generator=gen, dtype=torch.float64) * 36 - 3 + offset).to(dtype)
    points[1, :12] = ends[1, :, 0] + 0.7 * radius  # points at about the radius
    valid = torch.rand(3, 12, generator=gen) > 0.2
    valid[2] = False  # a patch without segments
    query, segment = segments_near_points(points, ends, valid, radius)
    found = set(zip(query.tolist(), segment.tolist()))
    assert len(found) == len(query)  # each pair at most once
    n_close = 0
    for p in range(3):  # the obvious loop: every valid segment closer than radius to a point
        for q in range(40):
            for m in range(12):
                a, b = ends[p, m, 0], ends[p, m, 1]
                t = float(((points[p, q] - a) @ (b - a)) / (b - a).square().sum().clamp_min(1e-12))
                distance = float((a + min(max(t, 0.0), 1.0) * (b - a) - points[p, q]).norm())
                if valid[p, m] and distance < radius * (1 - 1e-4):  # float32 slack
                    assert (p * 40 + q, p * 12 + m) in found
                    n_close += 1
    assert n_close > 0
    assert all(valid.reshape(-1)[s] and s // 12 == q // 40 for q, s in found)  # same patch, valid only


def test_segments_near_points_where_rounding_moves_the_lowest_sample_a_cell_down() -> None:
    # float32: (x - (x - 2.25)) / 2.25 < 1 for this lowest x, so its neighbour cells reach below
    # one cell under it (a grid index of -1 once crashed the bincount).
    x = -510.2839660644531
    ends = torch.tensor([[[[x, x], [x + 10.0, x + 3.0]]]], dtype=torch.float32)
    query, segment = segments_near_points(ends[:, :, 0], ends, torch.ones(1, 1, dtype=torch.bool), 1.5)
    assert query.tolist() == [0] and segment.tolist() == [0]


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


@pytest.mark.parametrize(("dtype", "offset", "angle_deg"), [
    (torch.float32, 0.0, 10.0), (torch.float32, 7531.7, 25.0), (torch.float64, -123.4, 10.0), (torch.float32, 0.0, 3.0),  # 3: float32(cos) < cos
])
def test_piece_closeness_compiled_is_bitwise_the_torch_expressions(
    dtype: torch.dtype, offset: float, angle_deg: float
) -> None:
    gen = torch.Generator().manual_seed(11)
    cfg = VerificationConfig(line_distance_m=1.5, line_angle_deg=angle_deg)
    ends = (torch.rand(4, 30, 2, 2, generator=gen, dtype=torch.float64) * 20 + offset).to(dtype)
    ends[0, 1, 1] = ends[0, 1, 0]  # a degenerate segment (no direction)
    ends[0, 2] = ends[0, 3]  # two equal segments
    valid = torch.rand(4, 30, generator=gen) > 0.2
    valid[3] = False  # a patch without segments
    mid = (torch.rand(4, 200, 2, generator=gen, dtype=torch.float64) * 22 - 1 + offset).to(dtype)
    mid[1, :30] = ends[1, :, 0] + 0.3  # pieces near segment ends
    u_line = _unit(ends[:, :, 1] - ends[:, :, 0])
    # Directions near the lines' directions, so that both sides of the angle test occur.
    near = torch.randint(0, 30, (4, 200), generator=gen)
    turn = (torch.rand(4, 200, generator=gen, dtype=torch.float64) - 0.5) * math.radians(4 * angle_deg)
    base = u_line.gather(1, near[..., None].expand(-1, -1, 2)).to(torch.float64)
    u_piece = torch.stack([base[..., 0] * turn.cos() - base[..., 1] * turn.sin(),
                           base[..., 0] * turn.sin() + base[..., 1] * turn.cos()], -1).to(dtype)
    # Exactly at the tolerance (and one step inside) against an axis-aligned line.
    ends[2, 0] = torch.tensor([[offset, offset], [offset + 10.0, offset]], dtype=dtype)
    u_line[2, 0] = torch.tensor([1.0, 0.0], dtype=dtype)
    c = torch.tensor(math.cos(math.radians(angle_deg)), dtype=dtype)
    for q, cos in enumerate((c, torch.nextafter(c, torch.zeros_like(c)))):
        mid[2, q] = torch.tensor([offset + 5.0, offset + 0.5], dtype=dtype)
        u_piece[2, q] = torch.stack([cos, torch.zeros_like(cos) + 0.1])
    mid[0, 0, 0] = math.nan  # a non-finite piece counts nothing
    compiled = piece_closeness(mid, u_piece, ends, u_line, valid, cfg, compiled=True)
    expected = piece_closeness(mid, u_piece, ends, u_line, valid, cfg, compiled=False)
    assert compiled.dtype == dtype and compiled.shape == (4, 200)
    assert torch.equal(compiled, expected)
    assert 0 < int((compiled > 0).sum()) < compiled.numel() - 200  # both outcomes, not only in patch 3
    assert compiled[2, 0] > 0 and compiled[2, 1] == 0  # the angle boundary: inclusive
    empty = mid[:, :0]
    assert piece_closeness(empty, empty, ends, u_line, valid, cfg, compiled=True).shape == (4, 0)
    no_lines = piece_closeness(mid, u_piece, ends[:, :0], u_line[:, :0], valid[:, :0], cfg, compiled=True)
    assert torch.equal(no_lines, torch.zeros(4, 200, dtype=dtype))

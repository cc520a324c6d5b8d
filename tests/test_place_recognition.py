from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.config.matching import PlaceRecognitionConfig
from meridian_torch.matching.place_recognition import (
    disk_overlap,
    fuses_global,
    rank_fusion,
    reads_global_descriptors,
    select_patches,
    stack_similarity,
)


def test_stack_similarity_is_max_cosine_over_valid_frames() -> None:
    gen = torch.Generator().manual_seed(0)
    frames = torch.randn(3, 4, 8, generator=gen)
    valid = torch.tensor([[True, True, False, False], [True, True, True, True], [False] * 4])
    patches = torch.randn(5, 8, generator=gen)
    sim = stack_similarity(frames, valid, patches)
    for s in range(3):
        for p in range(5):
            cos = [torch.nn.functional.cosine_similarity(frames[s, f], patches[p], dim=0)
                   for f in range(4) if valid[s, f]]
            expected = max(cos) if cos else torch.tensor(float("-inf"))
            assert torch.allclose(sim[s, p], torch.as_tensor(expected), atol=1e-6)


def test_stack_similarity_without_frames_ranks_no_patch() -> None:
    sim = stack_similarity(torch.zeros(2, 0, 8), torch.zeros(2, 0, dtype=torch.bool), torch.randn(5, 8))
    assert sim.shape == (2, 5) and torch.isneginf(sim).all()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.lists(st.sampled_from([0.0, 0.5, 1.0, 2.0, -1.0, math.inf, -math.inf, math.nan]), min_size=4,
                         max_size=4), min_size=1, max_size=3),
       st.floats(0.5, 100.0))
def test_rank_fusion_equals_a_loop_over_patches(rows: list[list[float]], k: float) -> None:
    """Each ranking adds 1 / (k + rank) for its finite scores, rank 1 the best, ties to the lower index."""
    scores = [torch.tensor([row], dtype=torch.float64) for row in rows]
    fused = rank_fusion(scores, k)[0]
    for p in range(4):
        total, ranked = 0.0, False
        for row in rows:
            if not math.isfinite(row[p]):
                continue
            rank = 1 + sum(1 for q in range(4) if math.isfinite(row[q]) and (row[q] > row[p] or (row[q] == row[p] and q < p)))
            total += 1.0 / (k + rank)
            ranked = True
        assert (fused[p].item() == pytest.approx(total, rel=1e-12)) if ranked else fused[p].item() == -math.inf


def test_coarse_mode_fused_with_similarity_takes_the_patches_both_rankings_favour() -> None:
    cfg = PlaceRecognitionConfig(mode="coarse", k_coarse=2)
    coarse = torch.tensor([[0.9, 0.8, 0.7, 0.6, 0.1]])
    # patch 0: 1st by the coarse search, 2nd by the descriptors; patch 1: 2nd and last; patch 4:
    # last by the coarse search, 1st by the descriptors (1/65 + 1/61 > 1/62 + 1/65)
    similarity = torch.tensor([[0.5, 0.1, 0.2, 0.3, 0.9]])
    idx, valid = select_patches(cfg, 1, 5, coarse_scores=coarse)
    assert idx[0].tolist() == [0, 1] and valid.all()
    idx, valid = select_patches(cfg, 1, 5, coarse_scores=coarse, similarity=similarity)
    assert idx[0].tolist() == [0, 4] and valid.all()
    # a submap without frame descriptors (similarity all -inf) falls back to the coarse ranking
    idx, _ = select_patches(cfg, 1, 5, coarse_scores=coarse, similarity=torch.full((1, 5), -math.inf))
    assert idx[0].tolist() == [0, 1]


def test_fusion_is_on_for_neural_global_descriptors_in_coarse_mode_only() -> None:
    auto = PlaceRecognitionConfig(mode="auto", exhaustive_max_patches=10)
    # 'auto' on a small map is exhaustive: nothing to fuse, no descriptors read
    assert not fuses_global(auto, 10, "anyloc") and not reads_global_descriptors(auto, 10, "anyloc")
    assert fuses_global(auto, 11, "anyloc") and fuses_global(auto, 11, "gem")
    assert not fuses_global(auto, 11, "classical") and not fuses_global(auto, 11, None)
    always = PlaceRecognitionConfig(mode="coarse", global_fusion="always")
    never = PlaceRecognitionConfig(mode="coarse", global_fusion="never")
    assert fuses_global(always, 5, "classical") and not fuses_global(never, 5, "anyloc")
    assert reads_global_descriptors(PlaceRecognitionConfig(mode="global"), 5, "classical")
    assert not fuses_global(PlaceRecognitionConfig(mode="global", global_fusion="always"), 5, "anyloc")


def test_global_mode_takes_the_top_k_and_flags_missing() -> None:
    sim = torch.tensor([[0.1, 0.9, 0.5, float("-inf")], [float("-inf")] * 4])
    idx, valid = select_patches(PlaceRecognitionConfig(mode="global", k_global=3), 2, 4, similarity=sim)
    assert idx[0].tolist() == [1, 2, 0] and valid[0].all()
    assert not valid[1].any()


def test_exhaustive_mode_lists_every_patch() -> None:
    idx, valid = select_patches(PlaceRecognitionConfig(mode="exhaustive"), 3, 7)
    assert idx.shape == (3, 7) and valid.all() and idx[2].tolist() == list(range(7))


def test_auto_mode_is_exhaustive_on_small_maps_and_coarse_on_large_ones() -> None:
    cfg = PlaceRecognitionConfig(mode="auto", k_coarse=2, exhaustive_max_patches=4)
    scores = torch.tensor([[0.1, 0.9, 0.5, 0.3, float("-inf")]])
    idx, valid = select_patches(cfg, 1, 4, coarse_scores=scores[:, :4])
    assert idx[0].tolist() == [0, 1, 2, 3] and valid.all()
    idx, valid = select_patches(cfg, 1, 5, coarse_scores=scores)
    assert idx[0].tolist() == [1, 2] and valid.all()
    with pytest.raises(ValueError, match="coarse"):
        select_patches(cfg, 1, 5)


def test_global_mode_takes_the_top_k_by_similarity() -> None:
    cfg = PlaceRecognitionConfig(mode="global", k_global=2)
    idx, valid = select_patches(cfg, 1, 5, similarity=torch.tensor([[0.1, 0.9, 0.5, 0.3, 0.2]]))
    assert idx[0].tolist() == [1, 2] and valid.all()
    with pytest.raises(ValueError, match="similarity"):
        select_patches(cfg, 1, 5)


@settings(max_examples=30, deadline=None)
@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(1, 30))
def test_disk_overlap_matches_the_exact_area_for_a_half_plane(cx: float, cy: float, r: float) -> None:
    # A box far larger than the disk, cut at x = cx: exactly half the disk is inside.
    box = torch.tensor([[cx, cx + 1e4, cy - 1e4, cy + 1e4]], dtype=torch.float64)
    frac = disk_overlap(torch.tensor([[cx, cy]], dtype=torch.float64), r, box)
    assert abs(float(frac) - 0.5) < 0.03
    inside = torch.tensor([[cx - 1e4, cx + 1e4, cy - 1e4, cy + 1e4]], dtype=torch.float64)
    assert float(disk_overlap(torch.tensor([[cx, cy]], dtype=torch.float64), r, inside)) == pytest.approx(1.0)


@pytest.mark.parametrize("budget", [1, 3 * 32 * 5, 1 << 20])  # one disk, three disks, all disks per chunk
def test_disk_overlap_in_chunks_counts_every_sample_like_a_plain_loop(budget: int, monkeypatch) -> None:
    monkeypatch.setattr("meridian_torch.matching.place_recognition.descriptors._OVERLAP_ELEMENTS", budget)
    g = torch.Generator().manual_seed(3)
    centres = torch.rand(7, 2, generator=g, dtype=torch.float64) * 100
    lo = torch.rand(5, 2, generator=g, dtype=torch.float64) * 100
    boxes = torch.stack([lo[:, 0], lo[:, 0] + 40, lo[:, 1], lo[:, 1] + 25], dim=1)
    radius = 12.0
    frac = disk_overlap(centres, radius, boxes)
    # The documented estimate: the centres of a 32 x 32 grid over the disk's square that lie in the disk.
    axis = [(k + 0.5) / 32 * 2 - 1 for k in range(32)]
    samples = [(u * radius, v * radius) for v in axis for u in axis if u * u + v * v <= 1.0]
    for s, (cx, cy) in enumerate(centres.tolist()):
        for p, (x0, x1, y0, y1) in enumerate(boxes.tolist()):
            inside = sum(x0 <= cx + dx <= x1 and y0 <= cy + dy <= y1 for dx, dy in samples)
            assert float(frac[s, p]) == inside / len(samples)
    assert disk_overlap(centres[:0], radius, boxes).shape == (0, 5)


def test_near_mode_picks_the_patches_around_the_prediction() -> None:
    # A 3 x 3 grid of 60 m patches at a 30 m stride; the prediction sits in the top-right corner.
    bounds = torch.tensor([[30.0 * i, 30.0 * i + 60, 30.0 * j, 30.0 * j + 60] for j in range(3) for i in range(3)])
    cfg = PlaceRecognitionConfig(mode="near", near_radius_m=10.0, near_patches=2)
    idx, valid = select_patches(cfg, 1, 9, predicted_xy=torch.tensor([[110.0, 110.0]]), patch_bounds_xy=bounds)
    assert idx[0, 0].item() == 8 and valid[0, 0]  # only the last patch contains the whole disk
    far = select_patches(cfg, 1, 9, predicted_xy=torch.tensor([[500.0, 500.0]]), patch_bounds_xy=bounds)
    assert not far[1].any()
    assert math.isclose(float(disk_overlap(torch.tensor([[110.0, 110.0]]), 10.0, bounds[8:9])), 1.0)

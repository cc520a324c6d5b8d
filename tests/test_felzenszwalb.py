"""The compiled Felzenszwalb segmentation against scikit-image's: the same labels, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from skimage.segmentation import felzenszwalb as skimage_felzenszwalb

from meridian_torch.perception.classical.felzenszwalb import (
    _NO_TIES,
    _OTHER_TIES,
    _ZERO_TIES,
    _edge_costs,
    _sort_costs,
    felzenszwalb,
)


def _assert_same_labels(image: np.ndarray, scale: float, sigma: float, min_size: int) -> None:
    expected = skimage_felzenszwalb(image, scale=scale, sigma=sigma, min_size=min_size)
    labels = felzenszwalb(image, scale=scale, sigma=sigma, min_size=min_size)
    assert labels.dtype == np.int64 and labels.shape == expected.shape
    assert np.array_equal(labels, expected), f"{int((labels != expected).sum())} pixels differ"


def _image(kind: str, height: int, width: int, channels: int, seed: int) -> np.ndarray:
    """Random float images; 'levels' and 'blocks' have many exactly equal edge costs (ties)."""
    rng = np.random.default_rng(seed)
    if kind == "noise":
        return rng.random((height, width, channels))
    if kind == "levels":  # three grey levels per channel, float32 like the segmenter's Lab/100
        return (rng.integers(0, 3, (height, width, channels)) / 2).astype(np.float32)
    # Flat 5x5 blocks: large zero-cost regions, and equal costs along every block border.
    blocks = rng.integers(0, 4, (height // 5 + 1, width // 5 + 1, channels)) / 3
    return np.repeat(np.repeat(blocks, 5, axis=0), 5, axis=1)[:height, :width]


@settings(max_examples=40, deadline=None)
@given(
    kind=st.sampled_from(["noise", "levels", "blocks"]),
    height=st.integers(1, 30),
    width=st.integers(1, 30),
    channels=st.integers(1, 3),
    seed=st.integers(0, 2**32 - 1),
    scale=st.sampled_from([0.1, 1.0, 30.0, 300.0, 5000.0]),
    sigma=st.sampled_from([0.0, 0.5, 0.8, 2.0]),
    min_size=st.sampled_from([0, 1, 3, 20, 100]),
)
def test_labels_equal_skimage_on_random_images(kind, height, width, channels, seed, scale, sigma, min_size):
    _assert_same_labels(_image(kind, height, width, channels, seed), scale, sigma, min_size)


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 17, 3), (17, 1, 3), (2, 2, 3), (2, 2, 1), (1, 2, 2)])
@pytest.mark.parametrize("min_size", [0, 2, 5])
def test_labels_equal_skimage_on_tiny_images(shape, min_size):
    _assert_same_labels(np.random.default_rng(1).random(shape), 1.0, 0.5, min_size)


def test_labels_equal_skimage_on_flat_and_grey_images():
    """All-zero costs (one constant image), a 2-D grey image, and a smooth segmenter-sized image."""
    _assert_same_labels(np.full((20, 30, 3), 0.25), 10.0, 0.8, 5)
    rng = np.random.default_rng(2)
    _assert_same_labels(rng.random((25, 40)), 50.0, 0.8, 10)
    yy, xx = np.mgrid[0:90, 0:160] / 40.0
    smooth = np.stack([np.sin(xx + yy), np.cos(2 * xx), np.sin(3 * yy) * xx], axis=-1)
    image = (smooth + 0.05 * rng.standard_normal(smooth.shape)).astype(np.float32)
    for scale, sigma, min_size in [(55.5, 0.67, 28), (5.0, 0.3, 4), (500.0, 1.5, 60)]:
        _assert_same_labels(image, scale, sigma, min_size)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("scale", [1e-44, 1.0, 30.0])
def test_zero_cost_ties_take_the_radix_order_only_when_it_cannot_matter(seed, scale):
    """A row of runs of equal pixels: ties only at cost 0 (one row has no shared neighbours), so
    the radix order is used, unless scale / n rounds to 0 in float32: zero-cost edges then need
    not merge, min_size pairs pixels in edge order, and that order must be np.argsort's."""
    rng = np.random.default_rng(seed)
    row = np.repeat(rng.random((60, 3)), rng.integers(1, 5, 60), axis=0)[None]
    costs = np.sqrt(np.sum((row[0, 1:] - row[0, :-1]) ** 2, axis=-1))
    assert _sort_costs(costs)[2] == _ZERO_TIES
    for min_size in (2, 3):
        _assert_same_labels(row, scale, 0.0, min_size)


@settings(max_examples=40, deadline=None)
@given(
    height=st.integers(1, 25),
    width=st.integers(1, 25),
    channels=st.integers(1, 4),
    seed=st.integers(0, 2**32 - 1),
    magnitude=st.sampled_from([1e-6, 1.0, 1e3]),
)
def test_edge_costs_are_skimages_expression_bitwise(height, width, channels, seed, magnitude):
    image = np.random.default_rng(seed).random((height, width, channels)) * magnitude
    right = image[:, 1:] - image[:, :-1]
    down = image[1:] - image[:-1]
    down_right = image[1:, 1:] - image[:-1, :-1]
    up_right = image[1:, :-1] - image[:-1, 1:]
    expected = np.concatenate([np.sqrt(np.sum(d * d, axis=-1)).ravel() for d in (right, down, down_right, up_right)])
    costs = _edge_costs(image)
    assert costs.shape == expected.shape and np.array_equal(costs.view(np.uint64), expected.view(np.uint64))


def test_sort_costs_is_argsort_when_costs_are_distinct():
    """Distinct costs, many sharing a float32 value (the insertion fix-up), in shuffled order."""
    rng = np.random.default_rng(3)
    close = 1.0 + np.arange(60) * 1e-12  # one float32 value, distinct float64 values
    costs = rng.permutation(np.concatenate([rng.random(5000) * 2, close, [0.0], np.exp(-rng.random(300) * 50)]))
    assert len(np.unique(costs)) == len(costs)
    order, sorted_costs, ties = _sort_costs(costs)
    assert ties == _NO_TIES
    assert np.array_equal(order, np.argsort(costs)) and np.array_equal(sorted_costs, costs[order])
    for n in (0, 1):
        order, _, ties = _sort_costs(costs[:n])
        assert ties == _NO_TIES and np.array_equal(order, np.arange(n))
    # Thousands of distinct costs on one float32 value: the fix-up gives up, np.argsort will run.
    assert _sort_costs(rng.permutation(1.0 + np.arange(3000) * 1e-12))[2] == _OTHER_TIES


def test_sort_costs_reports_ties():
    rng = np.random.default_rng(6)
    costs = rng.permutation(np.concatenate([np.zeros(50), rng.random(200) + 0.1]))
    order, _, ties = _sort_costs(costs)
    assert ties == _ZERO_TIES
    positive = costs[order] > 0
    assert np.array_equal(costs[order], np.sort(costs))
    assert np.array_equal(order[positive], np.argsort(costs)[positive])
    for bad in (costs.max(), np.nan):  # a positive tie, NaN
        with_bad = costs.copy()
        with_bad[np.argmin(costs)] = bad
        assert _sort_costs(with_bad)[2] == _OTHER_TIES


def test_rejects_bad_shape_and_sigma():
    with pytest.raises(ValueError, match="shape"):
        felzenszwalb(np.zeros((2, 3, 4, 5)))
    with pytest.raises(ValueError, match="sigma"):
        felzenszwalb(np.zeros((4, 4, 3)), sigma=-1.0)

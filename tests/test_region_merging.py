"""The classical segmenter's compiled region merging (`perception.classical.region_merging`) against
the plain array steps it replaced (np.unique, lexsort, bincount), its components against scipy's, and
the colour steps against np.linalg.norm."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from meridian_torch.perception.classical.region_merging import _components, colour_steps, merge_regions


def _reference_merge(labels, feats, step_h, step_v, lw, tw, bw, threshold, levels, min_px):
    """The merging in NumPy array steps: region sums by bincount, edges by np.unique of their keys,
    each region's best edge by a stable lexsort, components by scipy."""
    n = int(labels.max()) + 1
    flat = labels.ravel()
    count = np.bincount(flat, minlength=n).astype(np.float64)
    sums = np.stack([np.bincount(flat, weights=feats[..., c].ravel(), minlength=n) for c in range(4)], 1)

    def set_edges(a, b, length, step, n):
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        keep = lo != hi
        uniq, inv = np.unique(lo[keep] * n + hi[keep], return_inverse=True)
        return (np.stack([uniq // n, uniq % n], 1), np.bincount(inv, weights=length[keep], minlength=uniq.size),
                np.bincount(inv, weights=step[keep], minlength=uniq.size))

    a = np.concatenate([labels[:, :-1].ravel(), labels[:-1, :].ravel()])
    b = np.concatenate([labels[:, 1:].ravel(), labels[1:, :].ravel()])
    s = np.concatenate([step_h.ravel(), step_v.ravel()])
    edges, length, step = set_edges(a, b, np.ones(len(a)), s, n)

    def weights():
        mean = sums / count[:, None]
        d = mean[edges[:, 0]] - mean[edges[:, 1]]
        return np.sqrt((lw * d[:, 0]) ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2) + tw * np.abs(d[:, 3]) + bw * step / length

    def best_edges(weight):
        node = np.concatenate([edges[:, 0], edges[:, 1]])
        eidx = np.concatenate([np.arange(len(edges))] * 2)
        order = np.lexsort((weight[eidx], node))
        node, eidx = node[order], eidx[order]
        first = np.ones(len(node), dtype=bool)
        first[1:] = node[1:] != node[:-1]
        return node[first], eidx[first]

    def merge(chosen):
        nonlocal edges, length, step, count, sums
        pairs = edges[chosen]
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(count), len(count)))
        m, comp = connected_components(graph, directed=False)
        count = np.bincount(comp, weights=count, minlength=m)
        sums = np.stack([np.bincount(comp, weights=sums[:, c], minlength=m) for c in range(4)], 1)
        edges, length, step = set_edges(comp[edges[:, 0]], comp[edges[:, 1]], length, step, m)
        return comp

    lut = np.arange(n)
    for level in range(1, levels + 1):
        tau = threshold * level / levels
        while len(edges):
            weight = weights()
            _, best = best_edges(weight)
            chosen = best[weight[best] < tau]
            if chosen.size == 0:
                break
            lut = merge(chosen)[lut]
    while len(edges):
        node, best = best_edges(weights())
        chosen = best[count[node] < min_px]
        if chosen.size == 0:
            break
        lut = merge(np.unique(chosen))[lut]
    return lut, edges, weights(), length


def _blocky_image(rng, h, w, n_regions, quantised):
    """Labels of random rectangles over a random partition, features constant-ish per region (ties when quantised)."""
    labels = rng.integers(0, n_regions, (h // 4 + 1, w // 4 + 1)).repeat(4, 0).repeat(4, 1)[:h, :w]
    labels = np.unique(labels, return_inverse=True)[1].reshape(h, w).astype(np.int64)
    base = rng.uniform(0, 100, (labels.max() + 1, 4))
    feats = base[labels] + rng.normal(0, 3, (h, w, 4))
    step_h = rng.uniform(0, 20, (h, w - 1)).astype(np.float32)
    step_v = rng.uniform(0, 20, (h - 1, w)).astype(np.float32)
    if quantised:  # equal weights between regions: the tie-break decides
        feats, step_h, step_v = np.round(feats / 10) * 10, np.round(step_h), np.round(step_v)
    return labels, feats.astype(np.float64), step_h, step_v


@pytest.mark.parametrize("seed", range(8))
def test_merging_equals_the_array_steps(seed: int):
    rng = np.random.default_rng(seed)
    labels, feats, step_h, step_v = _blocky_image(rng, int(rng.integers(8, 60)), int(rng.integers(8, 60)),
                                                  int(rng.integers(10, 300)), quantised=seed % 2 == 1)
    args = (1.5, 0.5, 0.8, 25.0, 4, float(rng.integers(20, 120)))
    lut, edges, weight, length = merge_regions(labels, feats, step_h, step_v, *args)
    ref = _reference_merge(labels, feats, step_h, step_v, *args)
    assert lut.max() + 1 < labels.max() + 1  # the image merges
    assert np.array_equal(lut, ref[0]) and np.array_equal(edges, ref[1])
    assert weight.tobytes() == ref[2].tobytes() and length.tobytes() == ref[3].tobytes()


def test_components_equal_scipy_connected_components():
    """Same count and the same label per node (numbered by smallest node), on random graphs and chains."""
    rng = np.random.default_rng(4)
    graphs = []
    for _ in range(400):
        n = int(rng.integers(1, 300))
        pairs = np.sort(rng.integers(0, n, (int(rng.integers(0, 2 * n + 1)), 2)), axis=1)
        graphs.append((pairs[pairs[:, 0] != pairs[:, 1]], n))
    order = rng.permutation(200)  # one long chain in shuffled order
    graphs.append((np.sort(np.stack([order[:-1], order[1:]], axis=1), axis=1), 200))
    graphs.append((np.zeros((0, 2), dtype=np.int64), 5))
    for pairs, n in graphs:
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        expected_count, expected = connected_components(graph, directed=False)
        count, labels = _components(pairs.astype(np.int64), np.arange(len(pairs)), n)
        assert count == expected_count
        assert np.array_equal(labels, expected)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1), h=st.integers(1, 40), w=st.integers(1, 40), channels=st.integers(1, 4),
    scale=st.sampled_from([1e-3, 1.0, 100.0]),
)
def test_colour_steps_are_numpys_norms_bit_for_bit(seed: int, h: int, w: int, channels: int, scale: float):
    """Float32 images of any size (one row or column included) and channel weights: the steps are
    the segmenter's former NumPy expressions, bitwise."""
    rng = np.random.default_rng(seed)
    image = (rng.normal(0.0, scale, (h, w, channels))).astype(np.float32)
    weights = rng.uniform(0.1, 2.0, channels).astype(np.float32)
    step_h, step_v = colour_steps(image, weights)
    expected_h = np.linalg.norm((image[:, 1:] - image[:, :-1]) * weights, axis=-1)
    expected_v = np.linalg.norm((image[1:] - image[:-1]) * weights, axis=-1)
    assert step_h.dtype == step_v.dtype == np.float32
    assert step_h.tobytes() == expected_h.tobytes() and step_h.shape == expected_h.shape
    assert step_v.tobytes() == expected_v.tobytes() and step_v.shape == expected_v.shape

"""The classical segmenter's array-step connected components against scipy's sparse-graph ones."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from meridian_torch.perception.classical.segmenter import _connected_labels


def test_connected_labels_equal_scipy_connected_components():
    """Same count and the same label per node (numbered by smallest node), on random graphs and chains."""
    rng = np.random.default_rng(4)
    graphs = []
    for _ in range(400):
        n = int(rng.integers(1, 300))
        pairs = np.sort(rng.integers(0, n, (int(rng.integers(0, 2 * n + 1)), 2)), axis=1)
        graphs.append((pairs[pairs[:, 0] != pairs[:, 1]], n))
    order = rng.permutation(200)  # one long chain in shuffled order: many hooking rounds
    graphs.append((np.sort(np.stack([order[:-1], order[1:]], axis=1), axis=1), 200))
    graphs.append((np.zeros((0, 2), dtype=np.int64), 5))
    for pairs, n in graphs:
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        expected_count, expected = connected_components(graph, directed=False)
        count, labels = _connected_labels(pairs, n)
        assert count == expected_count
        assert np.array_equal(labels, expected)

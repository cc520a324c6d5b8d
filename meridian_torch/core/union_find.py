"""Union-find root lookup for the compiled (numba) kernels: the Felzenszwalb segmentation, the
classical segmenter's region merging and the grid DBSCAN of grouped point clouds share it."""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["find_root"]


@njit(cache=True, nogil=True, inline="always")
def find_root(parent: np.ndarray, node: int) -> int:
    """Root of `node` in the forest `parent` (roots point at themselves), with path halving: every
    visited node skips to its grandparent."""
    while parent[node] != node:
        parent[node] = parent[parent[node]]
        node = parent[node]
    return node

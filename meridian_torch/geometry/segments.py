"""Points against 2D segments: the squared distance (torch) and the closest point (numpy).

Both project onto the segment and clamp the parameter to [0, 1]. The torch one floors the
squared length at 1e-12, so a zero-length segment measures to its start; the numpy one does not
(a zero-length segment gives NaN). The affinity's bounded lines (segment, ray or infinite, in
component form) are in `matching.affinity.lines`.
"""

from __future__ import annotations

import numpy as np
from torch import Tensor

from meridian_torch.geometry.vectors import dot2, squared_norm2

__all__ = ["squared_segment_distance", "closest_point_on_segment"]


def squared_segment_distance(p: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """Squared distance from points p (K, 2) to segments a-b (K, 2)."""
    ab = b - a
    t = dot2(p - a, ab) / squared_norm2(ab).clamp_min(1e-12)
    return squared_norm2(a + t.clamp(0.0, 1.0)[:, None] * ab - p)


def closest_point_on_segment(p: np.ndarray, a0: np.ndarray, a1: np.ndarray) -> np.ndarray:
    """Closest point to p (E, 2) on segments a0-a1 (E, 2)."""
    d = a1 - a0
    t = np.clip(((p - a0) * d).sum(-1) / (d * d).sum(-1), 0.0, 1.0)
    return a0 + t[:, None] * d

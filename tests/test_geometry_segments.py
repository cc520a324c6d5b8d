from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from meridian_torch.geometry.segments import closest_point_on_segment, squared_segment_distance

coords = st.floats(-100.0, 100.0, allow_nan=False)
points = arrays(np.float64, (8, 2), elements=coords)


def _sampled(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Nearest of 2001 points along each segment: an upper bound within half a step of the truth."""
    t = np.linspace(0.0, 1.0, 2001)[None, :, None]
    along = a[:, None] + t * (b - a)[:, None]
    return np.linalg.norm(along - p[:, None], axis=-1).min(1)


@settings(max_examples=50)
@given(points, points, points)
def test_squared_segment_distance_is_the_nearest_point_of_the_segment(p, a, b) -> None:
    d = np.sqrt(squared_segment_distance(*(torch.from_numpy(v) for v in (p, a, b))).numpy())
    sampled = _sampled(p, a, b)
    step = np.linalg.norm(b - a, axis=1) / 2000
    assert np.all(d <= sampled + 1e-6)  # 1e-6: the 1e-12 floor of the squared length
    assert np.all(d >= sampled - step / 2 - 1e-6)


@settings(max_examples=50)
@given(points, points, points)
def test_closest_point_lies_on_the_segment_and_matches_the_distance(p, a, b) -> None:
    b = np.where(np.linalg.norm(b - a, axis=1, keepdims=True) < 1e-3, a + 1.0, b)  # no zero-length segments
    q = closest_point_on_segment(p, a, b)
    cross = (q - a)[:, 0] * (b - a)[:, 1] - (q - a)[:, 1] * (b - a)[:, 0]
    assert np.allclose(cross, 0.0, atol=1e-9 * (1.0 + np.abs(b - a).max()) ** 2)
    t = ((q - a) * (b - a)).sum(1) / ((b - a) ** 2).sum(1)
    assert np.all((t >= -1e-9) & (t <= 1.0 + 1e-9))
    d2 = squared_segment_distance(*(torch.from_numpy(v) for v in (p, a, b))).numpy()
    assert np.allclose(((q - p) ** 2).sum(1), d2, rtol=1e-9, atol=1e-9)


def test_a_zero_length_segment() -> None:
    p, a = torch.tensor([[3.0, 4.0]]), torch.zeros(1, 2)
    assert squared_segment_distance(p, a, a).item() == 25.0  # measured to its start
    with np.errstate(invalid="ignore"):
        assert np.isnan(closest_point_on_segment(p.numpy(), a.numpy(), a.numpy())).all()

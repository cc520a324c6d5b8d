"""scripts/bench_matching.py: how much faster the Langevin loop must run for a loop / batched ratio."""

from __future__ import annotations

import sys

from conftest import REPO
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(REPO / "scripts"))
from bench_matching import _speedup_for_ratio  # noqa: E402

seconds = st.floats(1e-4, 10.0)


def ratio(f: float, lb: float, restb: float, ll: float, restl: float) -> float:
    return (restl + ll / f) / (restb + lb / f)


@settings(max_examples=200, deadline=None)
@given(st.floats(1.5, 10.0), seconds, seconds, seconds, seconds)
def test_speedup_reaches_the_target_and_no_less_does(target, lb, restb, ll, restl) -> None:
    f = _speedup_for_ratio(target, lb, restb, ll, restl)
    if f is None:  # the rest alone stays at or below the target: no speed-up of the loop gets there
        assert restl / restb <= target
        assert ratio(1e12, lb, restb, ll, restl) < target * (1 + 1e-9)
    elif f == 1.0:
        assert ratio(1.0, lb, restb, ll, restl) >= target * (1 - 1e-12)
    else:
        assert f > 1.0
        assert abs(ratio(f, lb, restb, ll, restl) - target) <= 1e-9 * target
        assert ratio(0.99 * f, lb, restb, ll, restl) < target

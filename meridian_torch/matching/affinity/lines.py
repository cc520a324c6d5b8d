"""Bounded-line geometry of the affinity: lines (segment / ray / infinite) in parametric form,
nearest points and the closest points of two lines.

Everything is written on separate x / y component tensors: the scoring runs on millions of
pairs, and scalar tensors avoid the slow strided size-2 axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from meridian_torch.geometry.se2 import wrap_line_angle
from meridian_torch.types import LineKind

__all__ = ["nearest_point_on_line", "closest_points_between_lines"]

# The reference's C++ constants: lines count as parallel within 0.1 deg, a point lies on a
# bounded line if its parameter is within 1 mm of the line's extent.
PARALLEL_EPS_RAD = math.radians(0.1)
NEARBY_EPS_M = 1e-3


@dataclass(frozen=True)
class _Lines:
    """Lines as origin + t * direction with t in [lo, hi]; all fields broadcast together.

    ox, oy: origin (endpoints[0]); dx, dy: unit direction; lo: 0 or -inf; hi: segment length
    or +inf; tref: parameter of the reference point used for lever arms.
    """

    ox: torch.Tensor
    oy: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    tref: torch.Tensor

    def map_axis(self, axis: int) -> "_Lines":
        """Insert a broadcasting axis at `axis` in every field."""
        return _Lines(*(getattr(self, f.name).unsqueeze(axis) for f in fields(self)))

    def point(self, t: torch.Tensor) -> torch.Tensor:
        """(..., 2) the point at parameter t."""
        return torch.stack([self.ox + t * self.dx, self.oy + t * self.dy], dim=-1)

    def angle(self) -> torch.Tensor:
        """Sign-less direction angle in [0, pi)."""
        return wrap_line_angle(torch.atan2(self.dy, self.dx))


def _line_params(endpoints: torch.Tensor, kinds: torch.Tensor) -> _Lines:
    """Parametric form of lines given by endpoints (..., 2, 2) and LineKind codes (...).

    SEGMENT: t in [0, |e1 - e0|]; RAY: t in [0, inf) from e0 through e1; INFINITE: all t.
    Reference point: segment midpoint, ray start, midpoint of an infinite line's two points.
    """
    e0 = endpoints[..., 0, :]
    delta = endpoints[..., 1, :] - e0
    length = delta.norm(dim=-1)
    safe = length.clamp_min(torch.finfo(delta.dtype).tiny)
    infinite = kinds == int(LineKind.INFINITE)
    ray = kinds == int(LineKind.RAY)
    lo = torch.where(infinite, torch.full_like(length, float("-inf")), torch.zeros_like(length))
    hi = torch.where(kinds == int(LineKind.SEGMENT), length, torch.full_like(length, float("inf")))
    tref = torch.where(ray, torch.zeros_like(length), 0.5 * length)
    return _Lines(e0[..., 0], e0[..., 1], delta[..., 0] / safe, delta[..., 1] / safe, lo, hi, tref)


def _clamp(t: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    return torch.minimum(torch.maximum(t, lo), hi)


def nearest_point_on_line(points: torch.Tensor, endpoints: torch.Tensor, kinds: torch.Tensor) -> torch.Tensor:
    """Nearest point to `points` on bounded lines (segment / ray / infinite), batched: the
    orthogonal projection clamped to the segment or to the ray's start.

    Shapes: points (..., 2), endpoints (..., 2, 2), kinds (...) broadcastable -> (..., 2).
    """
    line = _line_params(endpoints, kinds)
    t = (points[..., 0] - line.ox) * line.dx + (points[..., 1] - line.oy) * line.dy
    return line.point(_clamp(t, line.lo, line.hi))


def _closest_params(l1: _Lines, l2: _Lines) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Parameters (s1 on l1, s2 on l2) of the closest points of two bounded 2D lines, and
    `meet` (the lines touch, so the gap is exactly zero); fields broadcast together.

    Non-parallel lines whose infinite-line intersection lies on both bounded lines meet there.
    Parallel lines where one is infinite: that line's reference point and its nearest point on
    the other line. Otherwise the best endpoint candidate (each finite endpoint of one line with
    its nearest point on the other), which is the exact minimum for disjoint convex sets in 2D.
    """
    wx, wy = l2.ox - l1.ox, l2.oy - l1.oy
    c12 = l1.dx * l2.dx + l1.dy * l2.dy
    x12 = l1.dx * l2.dy - l1.dy * l2.dx
    w_d1 = wx * l1.dx + wy * l1.dy
    w_d2 = wx * l2.dx + wy * l2.dy
    w_x_d1 = wx * l1.dy - wy * l1.dx
    w_x_d2 = wx * l2.dy - wy * l2.dx
    parallel = c12.abs() >= math.cos(PARALLEL_EPS_RAD)
    safe = torch.where(parallel, torch.ones_like(x12), x12)
    t1, t2 = w_x_d2 / safe, w_x_d1 / safe
    meet = (
        ~parallel
        & (t1 >= l1.lo - NEARBY_EPS_M)
        & (t1 <= l1.hi + NEARBY_EPS_M)
        & (t2 >= l2.lo - NEARBY_EPS_M)
        & (t2 <= l2.hi + NEARBY_EPS_M)
    )

    # Endpoint candidates as a running best. An endpoint at parameter e of line 1 is
    # -w + e d1 relative to o2: along-l2 parameter -w.d2 + e c12, across cross(w, d2) - e x12.
    # An endpoint of line 2 relative to o1: along w.d1 + e c12, across w x d1 - e x12.
    best_d = torch.full_like(t1, float("inf"))
    s1, s2 = t1, t2
    for t_own, first in ((l1.lo, True), (l1.hi, True), (l2.lo, False), (l2.hi, False)):
        finite = torch.isfinite(t_own)
        e = torch.where(finite, t_own, torch.zeros_like(t_own))
        if first:
            along, across, lo, hi = -w_d2 + e * c12, w_x_d2 - e * x12, l2.lo, l2.hi
        else:
            along, across, lo, hi = w_d1 + e * c12, w_x_d1 - e * x12, l1.lo, l1.hi
        near = _clamp(along, lo, hi)
        dist = (across.square() + (along - near).square()).masked_fill(~finite, float("inf"))
        better = dist < best_d
        best_d = torch.minimum(best_d, dist)
        s1 = torch.where(better, e if first else near, s1)
        s2 = torch.where(better, near if first else e, s2)

    # Parallel with an infinite line: the gap is the same everywhere, anchor it at the reference.
    inf1 = torch.isinf(l1.lo)
    par1 = torch.where(inf1, l1.tref, _clamp(w_d1 + l2.tref * c12, l1.lo, l1.hi))
    par2 = torch.where(inf1, _clamp(-w_d2 + l1.tref * c12, l2.lo, l2.hi), l2.tref)
    par_inf = parallel & (inf1 | torch.isinf(l2.lo))
    s1 = torch.where(meet, t1, torch.where(par_inf, par1, s1))
    s2 = torch.where(meet, t2, torch.where(par_inf, par2, s2))
    return s1, s2, meet


def closest_points_between_lines(
    endpoints_1: torch.Tensor, kinds_1: torch.Tensor, endpoints_2: torch.Tensor, kinds_2: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closest points of two bounded 2D lines (segment / ray / infinite), batched.

    Shapes: endpoints_k (..., 2, 2), kinds_k (...) broadcastable -> (c1, c2), each (..., 2):
    c1 lies on line 1, c2 on line 2 (both the intersection point when the lines touch).
    """
    l1, l2 = _line_params(endpoints_1, kinds_1), _line_params(endpoints_2, kinds_2)
    s1, s2, meet = _closest_params(l1, l2)
    c1 = l1.point(s1)
    return c1, torch.where(meet[..., None], c1, l2.point(s2))

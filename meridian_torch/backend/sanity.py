"""The localizer's last check on its own answer: a trajectory that cannot be right is reported
as not localized, with the reason, rather than as a confident wrong "yes"."""

from __future__ import annotations

import numpy as np

__all__ = ["off_map_fraction", "sanity_problems"]


def off_map_fraction(xy: np.ndarray, patch_bounds_xy: np.ndarray, margin_m: float) -> float:
    """Share of the (N, 2) positions outside every patch grown by `margin_m` (bounds (P, 4):
    x_min, x_max, y_min, y_max, the frame of the positions)."""
    b = np.asarray(patch_bounds_xy, dtype=np.float64)
    x, y = xy[:, :1], xy[:, 1:2]
    inside = ((x >= b[:, 0] - margin_m) & (x <= b[:, 1] + margin_m)
              & (y >= b[:, 2] - margin_m) & (y <= b[:, 3] + margin_m)).any(axis=1)
    return float(1.0 - inside.mean()) if len(xy) else 0.0


def sanity_problems(T_map_base: np.ndarray, patch_bounds_xy: np.ndarray, margin_m: float,
                    max_off_map_fraction: float) -> list[str]:
    """Why the final trajectory (N, 4, 4), in the map's frame, cannot be right (empty: no reason found).

    The robot was localized in the aerial map, so its trajectory must lie on the map: a solution
    that leaves it (a wrong fix carried along the odometry, a georeference that disagrees with
    the map) is refused.
    """
    off = off_map_fraction(T_map_base[:, :2, 3], patch_bounds_xy, margin_m)
    if off > max_off_map_fraction:
        return [f"{100 * off:.0f} % of the final trajectory lies more than {margin_m:g} m outside the aerial map "
                f"(backend.sanity_max_off_map_fraction = {max_off_map_fraction:g})"]
    return []

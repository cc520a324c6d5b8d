"""The localizer's last check on its own answer: a trajectory that cannot be right is reported
as not localized, with the reason, rather than as a confident wrong "yes".

Three checks, each cheap and each with a generous threshold (`backend.sanity_*`): the final
trajectory must lie on the aerial map, agree with the loop closures it was optimized on, and bend
the odometry's heading only as much as odometry can drift.
"""

from __future__ import annotations

import numpy as np

from meridian_torch.config import BackendConfig
from meridian_torch.geometry.planar import wrap_angle, yaw_of

__all__ = ["heading_bend_deg", "inlier_disagreement", "off_map_fraction", "sanity_problems"]


def off_map_fraction(xy: np.ndarray, patch_bounds_xy: np.ndarray, margin_m: float) -> float:
    """Share of the (N, 2) positions outside every patch grown by `margin_m` (bounds (P, 4):
    x_min, x_max, y_min, y_max, the frame of the positions)."""
    b = np.asarray(patch_bounds_xy, dtype=np.float64)
    x, y = xy[:, :1], xy[:, 1:2]
    inside = ((x >= b[:, 0] - margin_m) & (x <= b[:, 1] + margin_m)
              & (y >= b[:, 2] - margin_m) & (y <= b[:, 3] + margin_m)).any(axis=1)
    return float(1.0 - inside.mean()) if len(xy) else 0.0


def inlier_disagreement(T_solution: np.ndarray, T_measured: np.ndarray, max_m: float, max_deg: float) -> float:
    """Share of loop closures (K, 3, 3 measured poses of their nodes) that the optimized poses of
    those nodes (K, 3, 3) miss by more than `max_m` or `max_deg`."""
    if len(T_measured) == 0:
        return 0.0
    dt = np.linalg.norm(T_solution[:, :2, 2] - T_measured[:, :2, 2], axis=1)
    dyaw = np.degrees(np.abs(wrap_angle(yaw_of(T_solution) - yaw_of(T_measured))))
    return float(((dt > max_m) | (dyaw > max_deg)).mean())


def heading_bend_deg(T_solution: np.ndarray, T_odom: np.ndarray, window_m: float) -> float:
    """Largest change of the heading correction yaw(T_solution) - yaw(T_odom) (N, 3, 3 per frame)
    within any `window_m` of travelled odometry path: how far the solution turned the odometry."""
    if len(T_solution) < 2:
        return 0.0
    correction = np.unwrap(yaw_of(T_solution) - yaw_of(T_odom))
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(T_odom[:, :2, 2], axis=0), axis=1))])
    start = np.searchsorted(path, path - window_m)  # first frame of the window ending at each frame
    bend = [np.ptp(correction[s : k + 1]) for k, s in enumerate(start)]  # once per run: a plain loop
    return float(np.degrees(max(bend)))


def sanity_problems(
    T_map_base: np.ndarray,
    patch_bounds_xy: np.ndarray,
    cfg: BackendConfig,
    *,
    T_solution_se2: np.ndarray | None = None,
    T_odom_se2: np.ndarray | None = None,
    inlier_nodes: np.ndarray | None = None,
    T_inlier_se2: np.ndarray | None = None,
) -> list[str]:
    """Why the final trajectory cannot be right (empty: no reason found).

    Args:
        T_map_base: (N, 4, 4) final trajectory in the map's frame.
        patch_bounds_xy: (P, 4) the aerial map's patches.
        cfg: the thresholds (`sanity_*`).
        T_solution_se2, T_odom_se2: (N, 3, 3) the planar solution and odometry per frame.
        inlier_nodes, T_inlier_se2: (K,) the frames of the loop closures it was optimized on and
            (K, 3, 3) the poses they measured there.
    """
    problems = []
    off = off_map_fraction(T_map_base[:, :2, 3], patch_bounds_xy, cfg.sanity_off_map_margin_m)
    if off > cfg.sanity_max_off_map_fraction:
        problems.append(f"{100 * off:.0f} % of the final trajectory lies more than {cfg.sanity_off_map_margin_m:g} m "
                        f"outside the aerial map (backend.sanity_max_off_map_fraction = "
                        f"{cfg.sanity_max_off_map_fraction:g})")
    if inlier_nodes is not None and T_solution_se2 is not None and len(inlier_nodes):
        missed = inlier_disagreement(T_solution_se2[inlier_nodes], T_inlier_se2, cfg.sanity_inlier_residual_m,
                                     cfg.sanity_inlier_residual_deg)
        if missed > cfg.sanity_max_inlier_disagreement:
            problems.append(f"the final trajectory misses {100 * missed:.0f} % of its own loop closures by more than "
                            f"{cfg.sanity_inlier_residual_m:g} m or {cfg.sanity_inlier_residual_deg:g} deg "
                            f"(backend.sanity_max_inlier_disagreement = {cfg.sanity_max_inlier_disagreement:g})")
    if T_solution_se2 is not None and T_odom_se2 is not None:
        bend = heading_bend_deg(T_solution_se2, T_odom_se2, cfg.sanity_heading_window_m)
        if bend > cfg.sanity_max_heading_bend_deg:
            problems.append(f"the final trajectory turns the odometry's heading by {bend:.0f} deg within "
                            f"{cfg.sanity_heading_window_m:g} m of travel (backend.sanity_max_heading_bend_deg = "
                            f"{cfg.sanity_max_heading_bend_deg:g})")
    return problems

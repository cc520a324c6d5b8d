"""Plots a person would rather look at than read. matplotlib is imported only inside functions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from meridian_torch.core.kmeans import cosine_kmeans
from meridian_torch.geometry.planar import se2_from_se3
from meridian_torch.io.atomic import save_figure_atomic
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.types import AerialMap

__all__ = ["plot_aerial_map", "plot_ground_submap"]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_aerial_map(aerial_map: AerialMap, ortho: Orthophoto | None, out_png: Path, *, clusters: int = 8) -> Path:
    """Primitives over the orthophoto, coloured by descriptor cluster, with the patch grid.

    Axes are metres in the map frame; with a local origin (projected CRS) the labels say which
    world coordinate their zero is, so UTM-sized numbers do not crowd the ticks.
    """
    plt = _pyplot()
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Rectangle

    prims = aerial_map.primitives
    points = prims.points_xy[prims.point_valid].numpy()
    lines = prims.line_endpoints[prims.line_valid].numpy()
    desc = torch.cat([prims.point_descriptors[prims.point_valid], prims.line_descriptors[prims.line_valid]])
    _, labels = cosine_kmeans(desc.float(), clusters, generator=torch.Generator().manual_seed(0))
    colours = plt.get_cmap("tab10")(labels.numpy() % 10)

    local_x, local_y = aerial_map.local_origin_xy
    x_min, y_max = aerial_map.origin_xy[0] - local_x, aerial_map.origin_xy[1] - local_y
    width, height = aerial_map.image_size
    extent = (x_min, x_min + width * aerial_map.meters_per_pixel, y_max - height * aerial_map.meters_per_pixel, y_max)
    size = 12.0 * np.array([1.0, (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)])
    fig, ax = plt.subplots(figsize=tuple(np.clip(size, 4, 24)), dpi=110)
    if ortho is not None:
        ax.imshow(ortho.image, extent=extent, alpha=0.75)
    for x0, x1, y0, y1 in aerial_map.patches.bounds_xy:
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=0.4, ec="white", alpha=0.5))
    ax.add_collection(LineCollection(lines, colors=colours[len(points):], linewidths=1.6))
    ax.scatter(points[:, 0], points[:, 1], s=14, c=colours[: len(points)], edgecolors="black", linewidths=0.4, zorder=3)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)" + (f" - {local_x:.0f}" if local_x else ""))
    ax.set_ylabel("y north (m)" + (f" - {local_y:.0f}" if local_y else ""))
    ax.set_title(f"aerial map: {len(aerial_map)} patches, {len(points)} points, {len(lines)} lines "
                 f"(colour = descriptor cluster)")
    return save_figure_atomic(fig, out_png)


def plot_ground_submap(
    submap,
    out_png: Path,
    *,
    geometry=None,
    ortho: Orthophoto | None = None,
    T_world_odom: np.ndarray | None = None,
) -> Path:
    """One ground submap: its flattened segments, occluded points and primitives in the odom x-y
    frame; with `ortho` and `T_world_odom` (4x4, e.g. from the ground truth) a second panel shows
    the primitives over the orthophoto. `submap` is a `GroundSubmap`, `geometry` its
    `SubmapGeometry` (optional)."""
    plt = _pyplot()
    from matplotlib.collections import LineCollection

    prims = submap.primitives
    points = prims.points_xy.detach().cpu().double().numpy().reshape(-1, 2)
    lines = prims.line_endpoints.detach().cpu().double().numpy().reshape(-1, 2, 2)
    centre = np.asarray(submap.T_odom_base, dtype=np.float64)[:2, 3]
    overlay = ortho is not None and T_world_odom is not None
    fig, axes = plt.subplots(1, 2 if overlay else 1, figsize=(16 if overlay else 8.5, 8), dpi=100, squeeze=False)
    ax = axes[0, 0]
    if geometry is not None and len(geometry.points_xy):
        cmap = plt.get_cmap("tab20")
        ax.scatter(*geometry.points_xy.T, s=0.3, c=cmap(geometry.point_segment % 20), alpha=0.35, lw=0)
        if len(geometry.occluded_xy):
            ax.scatter(*geometry.occluded_xy.T, s=0.6, c="red", alpha=0.4, lw=0, label="occluded")
    ax.add_collection(LineCollection(lines, colors="navy", linewidths=1.6, label="lines"))
    ax.scatter(points[:, 0], points[:, 1], s=30, c="orange", edgecolors="black", linewidths=0.5, zorder=3,
               label="points")
    ax.plot(*centre, marker="*", ms=14, c="magenta", mec="black", zorder=4, label="centre")
    ax.set_aspect("equal")
    ax.set_xlabel("odom x (m)")
    ax.set_ylabel("odom y (m)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"submap {submap.index}: t = {submap.time:.1f} s, path {submap.path_length_m:.0f} m, "
                 f"{len(points)} points, {len(lines)} lines")
    if overlay:
        S = se2_from_se3(T_world_odom)
        R, t = S[:2, :2], S[:2, 2]
        ax2 = axes[0, 1]
        w_pts = points @ R.T + t
        w_lines = lines @ R.T + t
        w_centre = centre @ R.T + t
        half = 45.0
        x0, y_top = ortho.origin_xy
        h_px, w_px = ortho.image.shape[:2]
        mpp = ortho.meters_per_pixel
        ax2.imshow(ortho.image, extent=(x0, x0 + w_px * mpp, y_top - h_px * mpp, y_top), alpha=0.8)
        ax2.add_collection(LineCollection(w_lines, colors="cyan", linewidths=1.8))
        ax2.scatter(w_pts[:, 0], w_pts[:, 1], s=30, c="orange", edgecolors="black", linewidths=0.5, zorder=3)
        ax2.plot(*w_centre, marker="*", ms=14, c="magenta", mec="black", zorder=4)
        ax2.set_xlim(w_centre[0] - half, w_centre[0] + half)
        ax2.set_ylim(w_centre[1] - half, w_centre[1] + half)
        ax2.set_aspect("equal")
        ax2.set_xlabel("world x east (m)")
        ax2.set_ylabel("world y north (m)")
        ax2.set_title("over the orthophoto through the ground-truth pose")
    return save_figure_atomic(fig, out_png)

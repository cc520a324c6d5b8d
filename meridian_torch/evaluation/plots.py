"""Plots a person would rather look at than read. matplotlib is imported only inside functions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from meridian_torch.io.atomic import atomic_path
from meridian_torch.io.map_file import AerialMap
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.perception.kmeans import cosine_kmeans

__all__ = ["plot_aerial_map"]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_aerial_map(aerial_map: AerialMap, ortho: Orthophoto | None, out_png: Path, *, clusters: int = 8) -> Path:
    """Primitives over the orthophoto (world metres), coloured by descriptor cluster, with the patch grid."""
    plt = _pyplot()
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Rectangle

    prims = aerial_map.primitives
    points = prims.points_xy[prims.point_valid].numpy()
    lines = prims.line_endpoints[prims.line_valid].numpy()
    desc = torch.cat([prims.point_descriptors[prims.point_valid], prims.line_descriptors[prims.line_valid]])
    _, labels = cosine_kmeans(desc.float(), clusters, generator=torch.Generator().manual_seed(0))
    colours = plt.get_cmap("tab10")(labels.numpy() % 10)

    x_min, y_max = aerial_map.origin_xy
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
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(f"aerial map: {len(aerial_map)} patches, {len(points)} points, {len(lines)} lines "
                 f"(colour = descriptor cluster)")
    out_png = Path(out_png)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    plt.close(fig)
    return out_png

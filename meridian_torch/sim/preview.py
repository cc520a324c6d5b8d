"""Preview of a sequence folder: the orthophoto with the ground-truth path, and a contact sheet
of RGB and depth frames. Reads the folder back, so it shows what was written, not what was meant."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from meridian_torch.io.atomic import save_figure_atomic
from meridian_torch.io.sequence import SequenceReader

__all__ = ["write_preview"]


def write_preview(sequence: Path, out_png: Path, n_frames: int = 6) -> Path:
    """Write a PNG preview of `sequence` to `out_png` and return its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reader = SequenceReader(sequence)
    ortho = reader.ortho()
    picks = np.unique(np.linspace(0, len(reader) - 1, n_frames).round().astype(int))

    fig = plt.figure(figsize=(16, 8), dpi=100)
    grid = fig.add_gridspec(len(picks), 3, width_ratios=[2.2, 1, 1], wspace=0.05, hspace=0.12)
    ax_map = fig.add_subplot(grid[:, 0])
    ax_map.imshow(ortho.image)
    path = reader.groundtruth
    if path is not None:
        px = ortho.world_to_pixel(path.positions[:, :2])
        ax_map.plot(px[:, 0], px[:, 1], color="yellow", lw=1.5, label="ground truth")
        frame_px = ortho.world_to_pixel(path.interpolate(reader.frame_times[picks])[:, :2, 3])
        ax_map.scatter(frame_px[:, 0], frame_px[:, 1], c="red", s=25, zorder=3, label="frames shown")
        for k, (c, r) in zip(picks, frame_px):
            ax_map.annotate(str(k), (c, r), color="white", fontsize=8, xytext=(4, 4), textcoords="offset points")
        ax_map.legend(loc="lower right", fontsize=8)
    ax_map.set_title(f"{sequence.name}: orthophoto {ortho.size_px[0]}x{ortho.size_px[1]} px "
                     f"at {ortho.meters_per_pixel:g} m/px")
    ax_map.axis("off")

    frames = [reader[int(k)] for k in picks]
    valid = [f.depth[f.depth > 0] for f in frames]
    max_depth = max((float(v.max()) for v in valid if v.size), default=1.0)
    depth_axes = []
    for row, frame in enumerate(frames):
        ax_rgb = fig.add_subplot(grid[row, 1])
        ax_rgb.imshow(frame.rgb)
        ax_rgb.set_title(f"frame {frame.index}  t={frame.timestamp:.1f} s", fontsize=8)
        ax_rgb.axis("off")
        ax_depth = fig.add_subplot(grid[row, 2])
        depth_axes.append(ax_depth)
        ax_depth.set_facecolor("black")
        im = ax_depth.imshow(np.where(frame.depth > 0, frame.depth, np.nan), cmap="turbo", vmin=0, vmax=max_depth)
        ax_depth.set_title("depth (m), black = none", fontsize=8)
        ax_depth.set_xticks([])
        ax_depth.set_yticks([])
    fig.colorbar(im, ax=depth_axes, fraction=0.03, pad=0.02, label="depth (m)")

    return save_figure_atomic(fig, out_png)

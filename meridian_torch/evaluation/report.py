"""A short Markdown report of a localization run with two plots. matplotlib is imported only inside.

- `trajectory.png`: estimate (final and incremental) vs ground truth over the orthophoto, with
  the inlier loop closures (measured positions, joined to the final pose at their time);
- `error_vs_distance.png`: 2D position error of the final and incremental estimates against the
  ground-truth distance travelled;
- `report.md`: the metrics, per-stage timings and the two images.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from meridian_torch.evaluation.trajectory_metrics import (
    CONSISTENT_NEES,
    CONSISTENT_POSITION_NEES,
    CONSISTENT_WITHIN_2SIGMA,
    trajectory_errors,
)
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.atomic import save_figure_atomic, write_text_atomic
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.io.results import RunOutputs, read_outputs

__all__ = [
    "ERROR_PNG",
    "REPORT_MD",
    "TRAJECTORY_PNG",
    "plot_error_vs_distance",
    "plot_trajectory",
    "write_report",
]

REPORT_MD = "report.md"
TRAJECTORY_PNG = "trajectory.png"
ERROR_PNG = "error_vs_distance.png"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectory(
    outputs: RunOutputs,
    out_png: Path,
    *,
    ortho: Orthophoto | None = None,
    groundtruth: Trajectory | None = None,
) -> Path:
    """Trajectories over the orthophoto (world metres) with the inlier loop closures."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 9), dpi=110)
    if ortho is not None:
        w, h = ortho.size_px
        x0, y0 = ortho.origin_xy
        mpp = ortho.meters_per_pixel
        ax.imshow(ortho.image, extent=(x0, x0 + w * mpp, y0 - h * mpp, y0), alpha=0.8)
    if groundtruth is not None:
        ax.plot(*groundtruth.positions[:, :2].T, color="black", lw=2.0, label="ground truth")
    if outputs.incremental is not None:
        ax.plot(
            *outputs.incremental.positions[:, :2].T, color="tab:orange", lw=1.2, label="incremental (online)"
        )
    if outputs.final is not None:
        ax.plot(*outputs.final.positions[:, :2].T, color="tab:blue", lw=1.5, label="final")
    lc = outputs.loop_closures
    if len(lc):
        ax.scatter(
            lc["x"],
            lc["y"],
            s=22,
            c="tab:green",
            edgecolors="black",
            linewidths=0.5,
            zorder=4,
            label=f"inlier loop closures ({len(lc)})",
        )
        if outputs.final is not None:
            ends = outputs.final.interpolate(
                np.clip(lc["time"], outputs.final.timestamps[0], outputs.final.timestamps[-1])
            )
            for x, y, e in zip(lc["x"], lc["y"], ends):
                ax.plot([x, e[0, 3]], [y, e[1, 3]], color="tab:green", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)
    ax.set_title("trajectory estimate vs ground truth")
    return save_figure_atomic(fig, out_png)


def plot_error_vs_distance(
    outputs: RunOutputs, groundtruth: Trajectory, out_png: Path, max_difference_s: float = 0.01
) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 3.5), dpi=110)
    for name, traj, colour in (
        ("final", outputs.final, "tab:blue"),
        ("incremental", outputs.incremental, "tab:orange"),
    ):
        if traj is not None:
            e = trajectory_errors(traj, groundtruth, max_difference_s)
            ax.plot(e.distance_m, e.translation_m, color=colour, lw=1.2, label=name)
    ax.set_xlabel("distance travelled (m, ground truth)")
    ax.set_ylabel("2D position error (m)")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)
    return save_figure_atomic(fig, out_png)


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def write_report(
    out_dir: str | Path,
    *,
    stage_seconds: dict[str, float] | None = None,
    real_time_factor: float | None = None,
    peak_memory_mib: float | None = None,
    metrics: dict[str, Any] | None = None,
    ortho: Orthophoto | None = None,
    groundtruth: Trajectory | None = None,
    max_difference_s: float = 0.01,
) -> Path:
    """Write `report.md` and the plots into `out_dir` (a folder written by `write_outputs`).

    `stage_seconds`, `real_time_factor`, `peak_memory_mib` (optional) describe the whole run
    (`pipeline.SequenceRun`); without `stage_seconds` the localizer's own stage timings from the
    outputs are shown.
    """
    out = Path(out_dir)
    outputs = read_outputs(out)
    plot_trajectory(outputs, out / TRAJECTORY_PNG, ortho=ortho, groundtruth=groundtruth)
    lines = ["# Localization report", ""]
    s = outputs.summary
    lines += [
        (
            f"- localized: **{s['localized']}** ({s['n_inliers']} inlier loop closures, "
            f"{s['n_submaps']} submaps, {s['n_frames']} frames)"
        ),
        f"- global fix committed at submap {_fmt(s['fix_submap_index'])}, time {_fmt(s['fix_time'])} s",
    ]
    if s.get("rejected_because"):
        lines.append(f"- **refused by the sanity gate**: {s['rejected_because']}")
    lines += [""]
    if metrics is not None:
        lines += ["| metric | final | incremental |", "|---|---|---|"]
        for key in ("ate_rmse_m", "ate_mean_m", "ate_max_m", "heading_rmse_deg", "heading_max_deg", "n"):
            lines.append(
                f"| {key} | {_fmt((metrics.get('final') or {}).get(key))} | "
                f"{_fmt((metrics.get('incremental') or {}).get(key))} |"
            )
        lines += [
            "",
            f"- fraction of frames localized online: {_fmt(metrics.get('fraction_localized'))}",
            (
                f"- time / distance to the first fix: {_fmt(metrics.get('time_to_first_fix_s'))} s / "
                f"{_fmt(metrics.get('distance_to_first_fix_m'))} m"
            ),
        ]
        for name in ("final", "incremental"):
            consistency = metrics.get(f"{name}_covariance_consistency")
            if consistency is None:
                continue
            within = consistency["position_within_2sigma"]
            lines.append(
                f"- {name} covariance consistency over {consistency['n']} poses: mean NEES "
                f"{_fmt(consistency['nees_mean'])}, position NEES {_fmt(consistency['position_nees_mean'])}, "
                f"{'-' if within is None else f'{100 * within:.1f} %'} of positions inside the 2-sigma ellipse "
                f"(consistent: {CONSISTENT_NEES:g}, {CONSISTENT_POSITION_NEES:g}, "
                f"{100 * CONSISTENT_WITHIN_2SIGMA:.1f} %; larger NEES, smaller fraction: overconfident)"
            )
        lines.append("")
        for mode, by_threshold in (metrics.get("registration_success") or {}).items():
            for threshold, values in by_threshold.items():
                ranks = ", ".join(f"{k} {_fmt(v)}" for k, v in values.items())
                lines.append(f"- registration success ({mode}, {threshold}): {ranks}")
        lines.append("")
    timings = stage_seconds if stage_seconds is not None else (s.get("timings_s") or {})
    if timings:
        lines += (
            ["| stage | seconds |", "|---|---|"] + [f"| {k} | {v:.2f} |" for k, v in timings.items()] + [""]
        )
    if real_time_factor is not None and peak_memory_mib is not None:
        lines += [
            (
                f"- real-time factor {real_time_factor:.2f} (sequence duration / processing time), "
                f"peak memory {peak_memory_mib:.0f} MiB"
            ),
            "",
        ]
    lines += [f"![trajectory]({TRAJECTORY_PNG})", ""]
    if groundtruth is not None and (outputs.final is not None or outputs.incremental is not None):
        plot_error_vs_distance(outputs, groundtruth, out / ERROR_PNG, max_difference_s)
        lines += [f"![error vs distance]({ERROR_PNG})", ""]
    write_text_atomic(out / REPORT_MD, "\n".join(lines))
    return out / REPORT_MD

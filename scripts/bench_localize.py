#!/usr/bin/env python
"""End-to-end speed of the online pipeline: frames/s, real-time factor, peak memory, time per stage.

Runs `localize_sequence` (ground mapping frame by frame, every submap localized as it appears,
then the final offline pass) on one sequence folder and prints:
- frames/s and the real-time factor (sequence duration / wall time), online (frames and submaps
  as they come) and in total (with the final pass);
- the process's CPU time (user + system, all threads) while online, and how many cores that kept
  busy on average: near the machine's core count, only less work can make the run faster;
- the peak resident memory of the process, online and with the final pass, and which stages raised it;
- seconds per stage and sub-stage (perception, 3D observations, tracking, submaps, place
  recognition, associations, affinity, particles, registration, verification, consistency,
  pose graph, ...), as recorded by `meridian_torch.core.timing`; stages that run in threads
  (perception ahead of tracking, a match's patch groups) count each thread's seconds, so
  sub-stages can add up to more than their parent;
- the final and incremental ATE when the sequence has ground truth, so that speed and accuracy
  are read together.

Each measurement runs in a fresh child process, so that its peak memory is its own.
`--baseline-src DIR` runs the same measurement on another source tree (e.g. a git worktree of an
older commit: `git worktree add ../base <commit>`) right after, and prints both side by side;
the older tree may lack the sub-stage timings. A config of this checkout's configs/ is read from
the other tree's configs/ in its run (each tree at its own defaults; older trees refuse new keys). `--passes N` replays the drive N times, forward
and backward in turn (a physically continuous drive of N times the length: the robot retraces
its path), to show that memory and frames/s do not depend on how long it drives.
`--profile FILE` writes a cProfile of the run (open with `python -m pstats FILE` or snakeviz);
`--torch-profile FILE` a torch.profiler Chrome trace.

Timings are noisy on shared machines: the load average before each run is printed with it.
`--rounds N` runs each tree N times, alternated with the order swapped every round, and adds the
median and range of each tree's headline numbers and the ratio of the medians: on these 2-vCPU
machines one pair of trees measured 0.92 against 0.85 in one run and 0.82 against 0.87 in the
next, and a tree against itself 0.90 against 0.84 (medians of 2 rounds). A fresh worktree
compiles its numba kernels in its first run (about a minute): run it once before comparing, or
read the median of three or more rounds.

Example:
    python scripts/bench_localize.py runs/kitti09-7hz -c configs/kitti09.yaml --threads 2
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from _tree_child import config_in_tree, run_in_tree  # scripts/ is on sys.path when a script runs

RESULT_TAG = "BENCH_LOCALIZE_RESULT "
REPO = Path(__file__).resolve().parents[1]

# Stages in the order of the data flow; sub-stages are printed under the stage they ran in.
STAGE_ORDER = (
    "read frames", "ground mapping", "global descriptors", "segmentation", "segment descriptors",
    "observations", "tracking", "submaps", "localization", "place recognition", "matching", "associations",
    "affinity", "pruning", "particles", "langevin", "clipper", "registration", "clustering",
    "verification", "consistency", "pose graph",
    "final pass",
)
_PASS_STAGES = ("ground mapping", "matching", "consistency", "pose graph")  # seconds per pass of the drive


# ---------------------------------------------------------------------------------- the drive


@dataclass(frozen=True)
class _ReplayedFrame:
    index: int
    timestamp: float
    rgb: object
    depth: object
    T_odom_base: object


class ReplayedSequence:
    """A sequence driven `passes` times, forward and backward in turn, with increasing times.

    Frame k of pass p is the recorded frame i (i = k forward, n - 1 - k backward; the turning
    frame is not repeated), shown at a time that grows by the recorded frame spacing. Odometry
    and ground truth are the recorded poses of the frames shown, so the drive is physically
    continuous: the robot retraces its path.
    """

    def __init__(self, reader, passes: int) -> None:
        import numpy as np

        from meridian_torch.geometry.trajectory import Trajectory

        self.reader = reader
        n = len(reader)
        order = [np.arange(n)]
        for p in range(1, passes):
            step = np.arange(n - 2, -1, -1) if p % 2 else np.arange(1, n)
            order.append(step)
        self.order = np.concatenate(order)
        self.pass_ends = [int(e) for e in np.cumsum([len(o) for o in order])]  # frames shown by the end of each pass
        t = reader.frame_times
        dt = np.diff(t)
        steps = [dt] + [dt[::-1] if p % 2 else dt for p in range(1, passes)]
        self.frame_times = t[0] + np.concatenate([[0.0], np.cumsum(np.concatenate(steps))])
        self.camera = reader.camera
        self._odom = reader.T_odom_base[self.order]
        self.T_odom_base = self._odom
        self.odometry = Trajectory(self.frame_times, self._odom)
        gt = reader.groundtruth
        self.groundtruth = None if gt is None else Trajectory(self.frame_times, gt.interpolate(t)[self.order])

    def __len__(self) -> int:
        return len(self.order)

    def __getitem__(self, k: int):
        frame = self.reader[int(self.order[k])]
        return _ReplayedFrame(k, float(self.frame_times[k]), frame.rgb, frame.depth, self._odom[k])

    def ortho(self):
        return self.reader.ortho()

    def require_odometry_without_gaps(self, max_gap_s: float, n_frames: int | None = None) -> None:
        """The replay shows recorded poses only: the recording's gaps are its gaps (all checked)."""
        self.reader.require_odometry_without_gaps(max_gap_s)


# ---------------------------------------------------------------------------------- one run


def _load_average() -> float:
    return os.getloadavg()[0]


def run_child(args: argparse.Namespace) -> dict:
    """One measurement in this process (the child)."""
    import torch

    from meridian_torch.config import load_config
    from meridian_torch.io.map_file import load_aerial_map
    from meridian_torch.io.sequence import SequenceReader
    from meridian_torch.mapping.aerial_map import build_map_file, map_config_dict
    from meridian_torch.pipeline import localize_sequence
    from meridian_torch.runtime import current_rss_mib, peak_rss_mib, resolve_runtime

    try:  # absent in source trees older than the stage timings
        from meridian_torch.core.timing import record_stages
    except ImportError:
        record_stages = None

    cfg = load_config(args.config, args.overrides)
    if args.threads:
        torch.set_num_threads(args.threads)
    runtime = resolve_runtime(cfg.runtime)
    reader = SequenceReader(args.sequence)
    map_config = map_config_dict(cfg.aerial_map, cfg.perception, cfg.primitives)
    if args.map is not None and args.map.exists():
        aerial_map = load_aerial_map(args.map, expected_config=map_config)
    else:
        from meridian_torch.config import config_key

        path = args.map or Path(args.sequence) / f"aerial-{config_key(map_config)}.mtm"
        aerial_map = (load_aerial_map(path, expected_config=map_config) if path.exists() else
                      build_map_file(Path(args.sequence), path, cfg.aerial_map, cfg.perception, cfg.primitives))
    source = reader if args.passes == 1 else ReplayedSequence(reader, args.passes)
    if args.frames:
        source = _FirstFrames(source, args.frames)
    source = _PassMarks(source, getattr(source, "pass_ends", None) or
                        getattr(getattr(source, "source", None), "pass_ends", None) or [len(source)])

    rss_before = current_rss_mib()
    load = _load_average()
    profiler = None
    if args.profile:
        import cProfile

        profiler = cProfile.Profile()
    stage_times = None
    online_end: list[float] = []
    online_cpu: list[float] = []
    online_peak: list[float] = []
    started, cpu_started = time.perf_counter(), time.process_time()

    def on_stage(name: str) -> None:
        online_end.append(time.perf_counter())
        online_cpu.append(time.process_time())
        online_peak.append(peak_rss_mib())
        source.mark(len(source))  # a last pass whose final frames were not mapped (never read)

    def go():
        return localize_sequence(source, aerial_map, cfg, runtime, on_stage=on_stage)

    def profiled():
        if profiler is None:
            return go()
        profiler.enable()
        try:
            return go()
        finally:
            profiler.disable()
            profiler.dump_stats(args.profile)

    source.stage_times = _peak_stage_times() if record_stages is not None else None
    if args.torch_profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as tp:
            run, stage_times = _with_stages(record_stages, source.stage_times, profiled)
        tp.export_chrome_trace(str(args.torch_profile))
    else:
        run, stage_times = _with_stages(record_stages, source.stage_times, profiled)
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    online = (online_end[0] if online_end else time.perf_counter()) - started
    cpu_online = (online_cpu[0] if online_cpu else time.process_time()) - cpu_started

    metrics = None
    if source.groundtruth is not None:
        metrics = _metrics(run, source, cfg)
    n = len(source)
    duration = float(source.frame_times[-1] - source.frame_times[0])
    return {
        "source": str(Path(sys.modules["meridian_torch"].__file__).parent.parent),
        "frames": n,
        "frames_mapped": getattr(run, "frames_mapped", n),  # older trees map every frame
        "submaps": len(run.submaps),
        "duration_s": duration,
        "wall_s": wall,
        "online_s": online,
        "frames_per_s": n / wall,
        "rtf_online": duration / online,
        "rtf_total": duration / wall,
        "cpu_s": cpu,  # the process's user + system CPU, all threads
        "cpu_online_s": cpu_online,
        "cpus": os.cpu_count(),
        "peak_rss_mib": peak_rss_mib(),
        "peak_rss_online_mib": online_peak[0] if online_peak else None,
        "rss_before_mib": rss_before,
        "load_average": load,
        "threads": torch.get_num_threads(),
        "pipeline_seconds": run.seconds,
        # a source tree without stage marks records nothing: report its pipeline seconds only
        "stages": {"seconds": stage_times.seconds, "calls": stage_times.calls,
                   "peak_raised_mib": stage_times.peak_raised_mib} if stage_times and stage_times.calls else None,
        "localized": bool(run.result.localized),
        "fix_submap": run.result.fix_submap_index,
        "metrics": metrics,
        "passes": _pass_rows(source, started),
    }


def _pass_rows(source: _PassMarks, started: float) -> list[dict]:
    """Per pass of the drive: frames, seconds of driving and of wall time, frames/s, RSS at its end,
    and the seconds of the main stages that ended within it."""
    rows, prev_frames, prev_wall, prev_stages = [], 0, started, {}
    for frames, wall, rss, stages in source.marks:
        drive = float(source.frame_times[frames - 1] - source.frame_times[max(prev_frames - 1, 0)])
        rows.append({"frames": frames - prev_frames, "drive_s": drive, "wall_s": wall - prev_wall,
                     "frames_per_s": (frames - prev_frames) / max(wall - prev_wall, 1e-9), "rss_mib": rss,
                     "stage_s": {k: v - prev_stages.get(k, 0.0) for k, v in stages.items()}})
        prev_frames, prev_wall, prev_stages = frames, wall, stages
    return rows


class _PassMarks:
    """Wraps a source and notes the wall clock and resident memory when each pass's last frame is
    read (frames are read one batch ahead of the mapper, so a mark leads its pass by a batch; when
    the mapper skips a pass's last frames, at the next frame read, or at the end of the drive)."""

    def __init__(self, source, pass_ends) -> None:
        from meridian_torch.runtime import current_rss_mib

        self.source, self._rss = source, current_rss_mib
        self.pass_ends = [int(e) for e in pass_ends if e <= len(source)] or [len(source)]
        if self.pass_ends[-1] < len(source):
            self.pass_ends.append(len(source))
        self.frame_times, self.T_odom_base = source.frame_times, source.T_odom_base
        self.camera, self.odometry, self.groundtruth = source.camera, source.odometry, source.groundtruth
        self.stage_times = None  # the run's stage table, when recorded
        self.marks: list[tuple[int, float, float, dict]] = []  # (frames read, perf_counter, RSS MiB, stage s)

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, k: int):
        frame = self.source[k]
        self.mark(k + 1)
        return frame

    def mark(self, frames: int) -> None:
        """Mark every pass that ends within the first `frames` frames and is not marked yet."""
        for end in self.pass_ends:
            if end <= frames and all(m[0] != end for m in self.marks):
                times = self.stage_times
                stages = {name: times.total(name) for name in _PASS_STAGES} if times is not None else {}
                self.marks.append((end, time.perf_counter(), self._rss(), stages))

    def ortho(self):
        return self.source.ortho()

    def require_odometry_without_gaps(self, max_gap_s: float, n_frames: int | None = None) -> None:
        self.source.require_odometry_without_gaps(max_gap_s, n_frames)


class _FirstFrames:
    """The first `n` frames of a sequence."""

    def __init__(self, source, n: int) -> None:
        self.source, self.n = source, min(n, len(source))
        self.frame_times, self.T_odom_base = source.frame_times[: self.n], source.T_odom_base[: self.n]
        self.camera, self.odometry, self.groundtruth = source.camera, source.odometry, source.groundtruth

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, k: int):
        if k >= self.n:
            raise IndexError(k)
        return self.source[k]

    def ortho(self):
        return self.source.ortho()

    def require_odometry_without_gaps(self, max_gap_s: float, n_frames: int | None = None) -> None:
        self.source.require_odometry_without_gaps(max_gap_s, self.n if n_frames is None else min(n_frames, self.n))


def _peak_stage_times():
    """A stage table that also credits every rise of the process's peak RSS since it was made to
    the next stage that ends (the innermost one running when the peak rose, or, for a rise outside
    every stage, the next one to end): `peak_raised_mib` per stage path."""
    import resource

    from meridian_torch.core.timing import StageTimes

    def peak_mib() -> float:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux

    class PeakStageTimes(StageTimes):
        def __init__(self) -> None:
            super().__init__()
            self.peak_raised_mib: dict[str, float] = {}
            self._peak = peak_mib()

        def add(self, path: str, seconds: float) -> None:
            super().add(path, seconds)
            peak = peak_mib()
            with self._lock:
                if peak > self._peak:
                    self.peak_raised_mib[path] = self.peak_raised_mib.get(path, 0.0) + peak - self._peak
                    self._peak = peak

    return PeakStageTimes()


def _with_stages(record_stages, times, fn):
    if record_stages is None:
        return fn(), None
    with record_stages(times) as times:
        run = fn()
    return run, times


def _metrics(run, source, cfg) -> dict:
    from meridian_torch.evaluation.trajectory_metrics import evaluate_run
    try:
        from meridian_torch.pipeline.outputs import write_outputs
    except ImportError:  # source trees before the writer moved to the pipeline
        from meridian_torch.io.results import write_outputs

    with tempfile.TemporaryDirectory() as tmp:
        write_outputs(tmp, run.result, crs=None)
        m = evaluate_run(tmp, source.groundtruth, cfg.evaluation)
    final, inc = m.get("final") or {}, m.get("incremental") or {}
    return {
        "ate_final_m": final.get("ate_rmse_m"),
        "ate_incremental_m": inc.get("ate_rmse_m"),
        "fraction_localized": m.get("fraction_localized"),
        "first_fix_m": m.get("distance_to_first_fix_m"),
    }


# ---------------------------------------------------------------------------------- reporting


def _stage_rows(result: dict) -> list[tuple[str, float, int]]:
    """(indented name, seconds, calls) in data-flow order, children under their parents."""
    stages = result.get("stages")
    if not stages:
        return [(name, s, 0) for name, s in result["pipeline_seconds"].items() if name != "total"]
    seconds, calls = stages["seconds"], stages["calls"]

    def key(path: str) -> tuple:
        parts = path.split("/")
        return tuple(STAGE_ORDER.index(p) if p in STAGE_ORDER else len(STAGE_ORDER) for p in parts)

    rows = []
    for path in sorted(seconds, key=key):
        depth = path.count("/")
        rows.append(("  " * depth + path.rsplit("/", 1)[-1], seconds[path], calls[path]))
    return rows


def report(results: list[tuple[str, dict]]) -> str:
    def fmt(v, spec=".2f", unit=""):
        return "-" if v is None else f"{v:{spec}}{unit}"

    head = "| | " + " | ".join(label for label, _ in results) + " |"
    sep = "|---|" + "---|" * len(results)
    lines = [head, sep]
    rows = [
        ("frames / mapped / submaps", lambda r: f"{r['frames']} / {r.get('frames_mapped', r['frames'])} / {r['submaps']}"),
        ("sequence duration", lambda r: fmt(r["duration_s"], ".1f", " s")),
        ("wall time (online + final pass)", lambda r: f"{r['online_s']:.1f} + {r['wall_s'] - r['online_s']:.1f} s"),
        ("frames/s (total)", lambda r: fmt(r["frames_per_s"], ".1f")),
        ("real-time factor online / total", lambda r: f"{r['rtf_online']:.2f} / {r['rtf_total']:.2f}"),
        ("process CPU online (cores busy on average)", lambda r: "-" if "cpu_online_s" not in r else
            f"{r['cpu_online_s']:.1f} s ({r['cpu_online_s'] / r['online_s']:.2f} of {r['cpus']})"),
        ("peak RSS online / total", lambda r: f"{fmt(r.get('peak_rss_online_mib'), '.0f')} / "
                                              f"{fmt(r['peak_rss_mib'], '.0f', ' MiB')}"),
        ("localized (fix at submap)", lambda r: f"{'yes' if r['localized'] else 'no'} ({r['fix_submap']})"),
        ("ATE incremental / final", lambda r: "-" if not r["metrics"] else
            f"{fmt(r['metrics']['ate_incremental_m'])} / {fmt(r['metrics']['ate_final_m'])} m"),
        ("load average before, threads", lambda r: f"{r['load_average']:.2f}, {r['threads']}"),
    ]
    for stage in results[0][1]["pipeline_seconds"]:
        if stage != "total":
            rows.append((f"{stage} (s)", lambda r, k=stage: fmt(r["pipeline_seconds"].get(k), ".1f")))
    for name, f in rows:
        lines.append(f"| {name} | " + " | ".join(f(r) for _, r in results) + " |")
    lines.append("")
    for label, r in results:
        if len(r.get("passes") or []) > 1:
            lines.append(f"per pass of the drive, {label} (wall and RSS when its last frame was read):")
            names = list(r["passes"][0].get("stage_s") or {})
            lines.append("| pass | frames | driving s | wall s | frames/s | RSS MiB |"
                         + "".join(f" {n} s |" for n in names))
            lines.append("|---|---|---|---|---|---|" + "---|" * len(names))
            for i, row in enumerate(r["passes"]):
                lines.append(f"| {i + 1} | {row['frames']} | {row['drive_s']:.0f} | {row['wall_s']:.0f} | "
                             f"{row['frames_per_s']:.2f} | {row['rss_mib']:.0f} |"
                             + "".join(f" {row['stage_s'].get(n, 0.0):.1f} |" for n in names))
            lines.append("")
    for label, r in results:
        raised = sorted(((r.get("stages") or {}).get("peak_raised_mib") or {}).items(), key=lambda kv: -kv[1])
        if raised:
            lines.append(f"where the peak RSS rose, {label} (MiB each rise of the peak is credited to the "
                         "next stage to end, the innermost running; the rest of the peak is the process "
                         "before the run):")
            lines.append("| stage | peak raised MiB |")
            lines.append("|---|---|")
            lines += [f"| {path} | {mib:.0f} |" for path, mib in raised[:8]]
            lines.append("")
    for label, r in results:
        lines.append(f"time per stage, {label} ({r['source']}) (work done in threads, such as perception "
                     "ahead of tracking or a match's patch groups, counts each thread's seconds):")
        lines.append("| stage | s | % of wall | calls | ms per call |")
        lines.append("|---|---|---|---|---|")
        for name, s, calls in _stage_rows(r):
            per = f"{1000 * s / calls:.1f}" if calls else "-"
            lines.append(f"| {name} | {s:.1f} | {100 * s / r['wall_s']:.0f} | {calls or '-'} | {per} |")
        lines.append("")
    return "\n".join(lines)


def summary(trees: list[tuple[str, list[dict]]]) -> str:
    """Median and range over the rounds of each tree's headline numbers, and the ratio of the
    medians against the first tree's."""
    rows = [
        ("real-time factor online", lambda r: r["rtf_online"], ".2f"),
        ("wall time online, s", lambda r: r["online_s"], ".1f"),
        ("process CPU online, s", lambda r: r.get("cpu_online_s"), ".1f"),
        ("ground mapping, s", lambda r: r["pipeline_seconds"].get("ground_mapping"), ".1f"),
        ("matching, s", lambda r: r["pipeline_seconds"].get("matching"), ".1f"),
        ("peak RSS online, MiB", lambda r: r.get("peak_rss_online_mib"), ".0f"),
        ("peak RSS, MiB", lambda r: r["peak_rss_mib"], ".0f"),
    ]
    lines = [f"over {len(trees[0][1])} rounds: median (min-max) per tree, and its ratio to {trees[0][0]}'s median",
             "| | " + " | ".join(label for label, _ in trees) + " |", "|---|" + "---|" * len(trees)]
    for name, get, spec in rows:
        values = [[v for v in (get(r) for r in runs) if v is not None] for _, runs in trees]
        medians = [statistics.median(v) if v else None for v in values]
        cells = []
        for k, (v, median) in enumerate(zip(values, medians)):
            if median is None:
                cells.append("-")
                continue
            ratio = f", x{median / medians[0]:.3f}" if k and medians[0] else ""
            cells.append(f"{median:{spec}} ({min(v):{spec}}-{max(v):{spec}}{ratio})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _child_argv(args: argparse.Namespace, source: Path, profile: bool) -> list[str]:
    """The child's command line: this measurement's options (profiles only for this tree; a
    shipped config as the tree's own copy)."""
    config = config_in_tree(args.config, source)
    argv = [str(args.sequence), "-c", str(config), "--threads", str(args.threads), "--passes", str(args.passes)]
    for item in args.overrides:
        argv += ["--set", item]
    for flag, value in (("--map", args.map), ("--frames", args.frames)):
        if value is not None:
            argv += [flag, str(value)]
    if profile:
        for flag, value in (("--profile", args.profile), ("--torch-profile", args.torch_profile)):
            if value is not None:
                argv += [flag, str(value)]
    return argv + ["--child"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequence", type=Path, help="sequence folder")
    p.add_argument("-c", "--config", type=Path, default=REPO / "configs" / "default.yaml",
                   help="config the sequence belongs to (its map is built with it)")
    p.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    p.add_argument("--map", type=Path, default=None,
                   help="aerial map file (default: SEQUENCE/aerial-<config key>.mtm, built when missing)")
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    p.add_argument("--frames", type=int, default=None, help="only the first N frames")
    p.add_argument("--passes", type=int, default=1, help="drive the sequence N times, forward and back (memory runs)")
    p.add_argument("--baseline-src", type=Path, default=None,
                   help="also run the source tree DIR (e.g. a worktree of an older commit) and compare")
    p.add_argument("--rounds", type=int, default=1,
                   help="runs of each tree, alternated (the order swapped every round), with a summary of their "
                        "medians: one pair can mislead on a shared machine (default 1)")
    p.add_argument("--profile", type=Path, default=None, help="write a cProfile of the run to FILE")
    p.add_argument("--torch-profile", type=Path, default=None, help="write a torch.profiler Chrome trace to FILE")
    p.add_argument("--json", type=Path, default=None, help="also write the results to FILE")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    if args.rounds < 1:
        raise SystemExit(f"bench_localize: --rounds must be at least 1, got {args.rounds}")
    if args.child:
        print(RESULT_TAG + json.dumps(run_child(args), default=float), flush=True)
        return 0
    if not (args.sequence / "ground").is_dir():
        raise SystemExit(f"bench_localize: {args.sequence} is not a sequence folder (no ground/)")
    trees = [("this tree", REPO)] + ([("baseline", args.baseline_src.resolve())] if args.baseline_src else [])
    results = []
    per_tree: dict[str, list[dict]] = {label: [] for label, _ in trees}
    for k in range(args.rounds):
        # every other round starts with the other tree, so that neither always runs on a machine
        # the other has just warmed (or loaded)
        for label, source in (trees if k % 2 == 0 else trees[::-1]):
            profile = label == "this tree" and k == 0  # profiles of this tree's first run only
            result = run_in_tree(__file__, _child_argv(args, source, profile=profile), source, RESULT_TAG)
            results.append((f"{label} #{k + 1}" if args.rounds > 1 else label, result))
            per_tree[label].append(result)
    print(report(results))
    if args.rounds > 1:
        print(summary(list(per_tree.items())))
    if args.json is not None:
        args.json.write_text(json.dumps(dict(results), indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

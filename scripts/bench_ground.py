#!/usr/bin/env python
"""Ground mapping speed: frames per second, process CPU, real-time factor and peak memory on a sequence.

Runs the mapper over the sequence (default: the demo world, rendered into the cache if missing)
as `GroundMapper.map_sequence` does (the next batch read and perceived in a second thread while
the current one is tracked) and reports wall time split into stages (frame reading,
segmentation, segment descriptors, observations in the perception thread; tracking, submaps,
global descriptors in the main thread, and how long it waited for perception), frames per
second, the process CPU time (user) per frame, the real-time factor (sequence duration / wall
time) and the peak resident memory. The frames' global descriptors are left out, as `localize`
leaves them out unless place recognition reads them (`global` mode, or a coarse search fused
with neural descriptors); `--frame-descriptors` computes them as such a run does (every
`ground_map.frame_descriptor_dist_m` of travel). Per-frame numbers count the frames mapped
(those due at `ground_map.mapping_rate_hz`; `--set ground_map.mapping_rate_hz=null` maps every
frame). Stage times are the mapper's own `core.timing` stages (wall time; the two threads
overlap, so they add up to more than the wall time); numbers depend on the machine's load, so say
how loaded it was when quoting them.

`--stage-cpu` measures CPU instead of wall time per stage: every stage runs in one thread (torch
and the per-frame thread pools at 1 thread; the perception thread still runs ahead) and the stage
clock is that thread's CPU time, so the stages add up to the process CPU and do not depend on the
load. Every run is a fresh child process; `--baseline-src DIR` also runs another source tree (e.g.
a worktree of an older commit: `git worktree add ../base <commit>`), alternating the two trees
`--rounds` times, and prints them side by side (on a shared machine compare the CPU per frame); a
config of this checkout's configs/ is read from the other tree's configs/ in its runs.

Example: python scripts/bench_ground.py --threads 2 demo-sequence -c configs/demo.yaml
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
import types
from pathlib import Path

from _tree_child import config_in_tree, run_in_tree  # scripts/ is on sys.path when a script runs

RESULT_TAG = "BENCH_GROUND_RESULT "
REPO = Path(__file__).resolve().parents[1]


def run_child(args: argparse.Namespace) -> dict:
    """One measurement in this process (the `meridian_torch` on the path)."""
    import torch

    import meridian_torch
    from meridian_torch.config import CONFIG_DIR, load_config
    from meridian_torch.core import timing
    from meridian_torch.io.sequence import SequenceReader
    from meridian_torch.mapping.ground_map import GroundMapper, perceived_batches
    from meridian_torch.runtime import peak_rss_mib, resolve_runtime

    cfg = load_config(args.config or CONFIG_DIR / "demo.yaml", args.overrides)
    threads = 1 if args.stage_cpu else args.threads
    if threads:
        torch.set_num_threads(threads)
    if args.stage_cpu:  # each stage opens and closes in one thread: its CPU time is the stage's
        timing.time = types.SimpleNamespace(perf_counter=time.thread_time)
    seq = args.sequence
    if seq is None:
        from meridian_torch.sim.simulate import simulate_sequence

        seq = Path.home() / ".cache" / "meridian-torch" / "bench" / cfg.sim.name
        if not seq.exists():
            simulate_sequence(cfg.sim, seq)
    reader = SequenceReader(seq)
    n = len(reader) if args.frames is None else min(args.frames, len(reader))

    mapper = GroundMapper.from_config(cfg, reader.camera, resolve_runtime(cfg.runtime),
                                      frame_descriptors=args.frame_descriptors)
    load = list(os.getloadavg())
    cpu_before = resource.getrusage(resource.RUSAGE_SELF)
    started = time.perf_counter()
    submaps = []
    waiting = 0.0
    with timing.record_stages() as times:  # per stage, also of the perception thread's stages
        batches = perceived_batches(mapper, reader, n)  # as map_sequence: the next batch perceived meanwhile
        while True:
            t = time.perf_counter()
            batch = next(batches, None)
            waiting += time.perf_counter() - t
            if batch is None:
                break
            submaps += mapper.integrate(batch)
        submaps += mapper.finish()
    wall = time.perf_counter() - started
    cpu_after = resource.getrusage(resource.RUSAGE_SELF)
    stages = dict(times.seconds)
    if not args.stage_cpu:
        stages["waiting for perception (main thread)"] = waiting
    span = float(reader.frame_times[n - 1] - reader.frame_times[0])
    duration = span * n / max(n - 1, 1)  # n frames at the recorded spacing
    mapped = len(mapper.frames)  # frames due at ground_map.mapping_rate_hz: per-frame numbers are per mapped frame
    return {
        "source": str(Path(meridian_torch.__file__).resolve().parents[1]), "sequence": str(seq), "frames": mapped,
        "frames_offered": n, "threads": torch.get_num_threads(),
        "stage_clock": "thread CPU" if args.stage_cpu else "wall",
        "submaps": len(submaps), "wall_s": wall, "fps": mapped / wall, "real_time_factor": duration / wall,
        "cpu_user_s": cpu_after.ru_utime - cpu_before.ru_utime, "cpu_system_s": cpu_after.ru_stime - cpu_before.ru_stime,
        "peak_rss_mb": peak_rss_mib(), "stages_s": stages, "load_average_before": load,
        "load_average_after": list(os.getloadavg()),
    }


def report(result: dict) -> str:
    n = result["frames"]
    offered = result.get("frames_offered", n)
    lines = [f"{result['source']}: {offered} frames ({n} mapped), {result['submaps']} submaps in {result['wall_s']:.1f} s: "
             f"{result['fps']:.2f} frames/s, process CPU {result['cpu_user_s']:.1f} s user "
             f"({1000 * result['cpu_user_s'] / n:.0f} ms/frame) + {result['cpu_system_s']:.1f} s system, "
             f"real-time factor {result['real_time_factor']:.2f}, peak RSS {result['peak_rss_mb']:.0f} MB, "
             f"torch threads {result['threads']}, load average {result['load_average_before'][0]:.1f} -> "
             f"{result['load_average_after'][0]:.1f}; stages ({result['stage_clock']}):"]
    for name, sec in sorted(result["stages_s"].items(), key=lambda kv: -kv[1]):
        lines.append(f"  {name:38s} {sec:7.2f} s  {1000 * sec / n:7.1f} ms/frame")
    return "\n".join(lines)


def comparison(results: list[tuple[str, dict]]) -> str:
    """Markdown table: one column per run, frames/s, CPU per frame and ms per frame per stage."""
    lines = ["| | " + " | ".join(label for label, _ in results) + " |", "|---" * (len(results) + 1) + "|"]
    rows = [("frames/s", lambda r: f"{r['fps']:.2f}"),
            ("process CPU user, ms/frame", lambda r: f"{1000 * r['cpu_user_s'] / r['frames']:.0f}"),
            ("load average before / after", lambda r: f"{r['load_average_before'][0]:.1f} / {r['load_average_after'][0]:.1f}")]
    names = list(dict.fromkeys(k for _, r in results for k in r["stages_s"]))
    rows += [(f"{name}, ms/frame", lambda r, k=name: f"{1000 * r['stages_s'].get(k, float('nan')) / r['frames']:.1f}")
             for name in names]
    for name, f in rows:
        lines.append(f"| {name} | " + " | ".join(f(r) for _, r in results) + " |")
    return "\n".join(lines)


def _child_argv(args: argparse.Namespace, source: Path) -> list[str]:
    argv = [] if args.sequence is None else [str(args.sequence)]
    config = config_in_tree(args.config, source)
    for flag, value in (("-c", config), ("--threads", args.threads), ("--frames", args.frames)):
        if value is not None:
            argv += [flag, str(value)]
    for item in args.overrides:
        argv += ["--set", item]
    flags = [flag for flag, on in (("--stage-cpu", args.stage_cpu), ("--frame-descriptors", args.frame_descriptors)) if on]
    return argv + flags + ["--child"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path, nargs="?", default=None, help="sequence folder (default: the demo world)")
    ap.add_argument("-c", "--config", type=Path, default=None, help="config (default: configs/demo.yaml)")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames")
    ap.add_argument("--stage-cpu", action="store_true", help="CPU time per stage (one thread per stage)")
    ap.add_argument("--frame-descriptors", action="store_true",
                    help="also compute the frames' global descriptors (as localize does only in global mode or a "
                         "coarse search fused with neural descriptors)")
    ap.add_argument("--baseline-src", type=Path, default=None, help="also run the source tree DIR, alternating")
    ap.add_argument("--rounds", type=int, default=1, help="runs of each tree (alternated with --baseline-src)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(RESULT_TAG + json.dumps(run_child(args)), flush=True)
        return
    trees = [("this tree", REPO)] + ([("baseline", args.baseline_src.resolve())] if args.baseline_src else [])
    results = []
    for k in range(args.rounds):
        for label, source in trees:
            result = run_in_tree(__file__, _child_argv(args, source), source, RESULT_TAG)
            print(report(result), flush=True)
            results.append((f"{label} #{k + 1}" if args.rounds > 1 else label, result))
    if len(results) > 1:
        print(comparison(results))
    if args.json:
        args.json.write_text(json.dumps(dict(results), indent=1) + "\n")


if __name__ == "__main__":
    main()

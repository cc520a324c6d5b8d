#!/usr/bin/env python
"""Ground mapping speed: frames per second, real-time factor and peak memory on a sequence.

Runs the mapper over the sequence (default: the demo world, rendered into the cache if missing)
as `GroundMapper.map_sequence` does (the next batch read and perceived in a second thread while
the current one is tracked) and reports wall time split into stages (frame reading,
segmentation, segment descriptors, observations in the perception thread; tracking, submaps,
global descriptors in the main thread, and how long it waited for perception), frames per
second, the real-time factor (sequence duration / wall time) and the peak resident memory.
Stage times are the mapper's own `core.timing` stages (wall time; the two threads overlap, so
they add up to more than the wall time); numbers depend on the machine's load, so say how
loaded it was when quoting them.

Example: python scripts/bench_ground.py --threads 2 demo-sequence -c configs/demo.yaml
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.core.timing import record_stages
from meridian_torch.io.sequence import SequenceReader
from meridian_torch.mapping.ground_map import GroundMapper, perceived_batches
from meridian_torch.runtime import peak_rss_mib, resolve_runtime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path, nargs="?", default=None, help="sequence folder (default: the demo world)")
    ap.add_argument("-c", "--config", type=Path, default=CONFIG_DIR / "demo.yaml")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    cfg = load_config(args.config, args.overrides)
    if args.threads:
        torch.set_num_threads(args.threads)
    seq = args.sequence
    if seq is None:
        from meridian_torch.sim.simulate import simulate_sequence

        seq = Path.home() / ".cache" / "meridian-torch" / "bench" / cfg.sim.name
        if not seq.exists():
            simulate_sequence(cfg.sim, seq)
    reader = SequenceReader(seq)
    n = len(reader) if args.frames is None else min(args.frames, len(reader))

    mapper = GroundMapper.from_config(cfg, reader.camera, resolve_runtime(cfg.runtime))
    started = time.perf_counter()
    submaps = []
    waiting = 0.0
    with record_stages() as times:  # wall time per stage, also of the perception thread's stages
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
    stages = dict(times.seconds)
    stages["waiting for perception (main thread)"] = waiting
    span = float(reader.frame_times[n - 1] - reader.frame_times[0])
    duration = span * n / max(n - 1, 1)  # n frames at the recorded spacing
    peak_mb = peak_rss_mib()
    result = {
        "sequence": str(seq), "frames": n, "threads": torch.get_num_threads(), "submaps": len(submaps),
        "wall_s": wall, "fps": n / wall, "real_time_factor": duration / wall, "peak_rss_mb": peak_mb,
        "stages_s": dict(stages), "load_average": list(os.getloadavg()),
    }
    print(f"{n} frames, {len(submaps)} submaps in {wall:.1f} s: {n / wall:.2f} frames/s, "
          f"real-time factor {duration / wall:.2f} (sequence {duration:.0f} s), peak RSS {peak_mb:.0f} MB, "
          f"torch threads {torch.get_num_threads()}, load average {result['load_average'][0]:.1f}")
    for name, sec in sorted(stages.items(), key=lambda kv: -kv[1]):
        print(f"  {name:38s} {sec:7.2f} s  {1000 * sec / n:7.1f} ms/frame")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

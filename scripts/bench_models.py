"""Benchmark neural perception models: per-image latency and peak memory, torch eager vs onnxruntime.

Cases (random weights: timing depends on the architecture, not on the values):
- DINOv2 ViT-S/14 dense features (the real vits14 architecture) on 224 x 224 and 448 x 448 images;
- tiny SAM (configs/tiny.yaml architecture): image encoder on one 128 x 128 image, and the prompt
  decoder on 64 point prompts (one automatic-generator batch), reported per call.

The parent exports the graphs once with `meridian_torch.export.models.export_model` (checked
against torch), then runs every (case, engine) in a fresh subprocess so that the process peak
resident set size belongs to that one model. Each child loads its model, runs `--warmup` calls,
then times `--repeats` calls; the median is reported with the peak RSS (VmHWM) and the RSS
before the timed calls (after imports and loading). Threads: torch.set_num_threads(--threads)
and onnxruntime's default (all cores) capped by the same number.

    python scripts/bench_models.py                 # all cases
    python scripts/bench_models.py --repeats 5 --cases vits14-224 sam-tiny-encoder
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

from meridian_torch.runtime import current_rss_mib, peak_rss_mib

RESULT_TAG = "BENCH_MODELS_RESULT "
CASES = ("vits14-224", "vits14-448", "sam-tiny-encoder", "sam-tiny-decoder")


def _config(case: str):  # noqa: ANN202 - the MeridianConfig import is deferred to keep --help fast
    from meridian_torch.config import CONFIG_DIR, load_config

    if case.startswith("vits14"):
        return load_config(CONFIG_DIR / "tiny.yaml", ["perception.descriptor.dinov2.architecture=vits14"])
    return load_config(CONFIG_DIR / "tiny.yaml")


def _model_name(case: str) -> str:
    return {"vits14-224": "dinov2-dense", "vits14-448": "dinov2-dense", "sam-tiny-encoder": "sam-encoder",
            "sam-tiny-decoder": "sam-decoder"}[case]


def _inputs(case: str) -> dict:
    """Named inputs of one call, built without the model (the onnxruntime child never builds it)."""
    import torch

    from meridian_torch.perception.neural.sam.model import SAM_ARCHITECTURES

    g = torch.Generator().manual_seed(0)
    if case.startswith("vits14"):
        size = int(case.split("-")[1])
        return {"images": torch.rand(1, 3, size, size, generator=g)}
    a = SAM_ARCHITECTURES["tiny"]
    if case == "sam-tiny-encoder":
        return {"images": torch.randn(1, 3, a.image_size, a.image_size, generator=g)}
    return {
        "image_embeddings": torch.randn(1, a.prompt_embed_dim, a.embedding_size, a.embedding_size, generator=g),
        "point_coords": torch.rand(64, 1, 2, generator=g) * a.image_size,
        "point_labels": torch.ones(64, 1, dtype=torch.int64),
    }


def child(case: str, engine: str, graph: str, threads: int, warmup: int, repeats: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    inputs = _inputs(case)
    if engine == "torch":
        from meridian_torch.export.models import export_spec

        module = export_spec(_model_name(case), _config(case).perception).module.eval()

        def run() -> None:
            with torch.inference_mode():
                module(*inputs.values())
    else:
        import onnxruntime as ort

        feeds = {name: t.numpy() for name, t in inputs.items()}
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        session = ort.InferenceSession(graph, sess_options=options, providers=["CPUExecutionProvider"])

        def run() -> None:
            session.run(None, feeds)

    baseline = current_rss_mib()
    for _ in range(warmup):
        run()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    times.sort()
    return {"case": case, "engine": engine, "median_ms": 1e3 * times[len(times) // 2], "min_ms": 1e3 * times[0],
            "peak_rss_mib": peak_rss_mib(), "rss_before_runs_mib": baseline}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--child", nargs=3, metavar=("CASE", "ENGINE", "GRAPH"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        case, engine, graph = args.child
        print(RESULT_TAG + json.dumps(child(case, engine, graph, args.threads, args.warmup, args.repeats)))
        return

    from meridian_torch.export.models import export_model

    load_before = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-models-") as folder:
        graphs: dict[str, str] = {}
        for case in args.cases:
            key = f"{_model_name(case)}-{case.split('-')[0]}"
            if key not in graphs:
                graphs[key] = os.path.join(folder, key + ".onnx")
                report = export_model(_model_name(case), _config(case).perception, graphs[key])
                print(f"exported {key}: max abs difference to torch {report.max_abs_diff:.2g}, "
                      f"{report.size_bytes / 2**20:.1f} MiB", flush=True)
            for engine in ("torch", "onnxruntime"):
                cmd = [sys.executable, os.path.abspath(__file__), "--child", case, engine, graphs[key],
                       "--threads", str(args.threads), "--warmup", str(args.warmup), "--repeats", str(args.repeats)]
                out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
                rows.append(json.loads(next(line for line in out.splitlines() if line.startswith(RESULT_TAG))
                                       [len(RESULT_TAG):]))
    print(f"\n{'case':18s} {'engine':12s} {'median ms':>10s} {'min ms':>8s} {'peak RSS MiB':>13s} "
          f"{'RSS before runs':>16s}")
    for r in rows:
        print(f"{r['case']:18s} {r['engine']:12s} {r['median_ms']:10.1f} {r['min_ms']:8.1f} "
              f"{r['peak_rss_mib']:13.0f} {r['rss_before_runs_mib']:16.0f}")
    print(f"\nper call of batch 1 (decoder: 64 prompts), {args.threads} threads; load average "
          f"{load_before:.1f} before, {os.getloadavg()[0]:.1f} after (other processes distort timings)")


if __name__ == "__main__":
    main()

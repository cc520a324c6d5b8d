"""Benchmark `solve_clipper` on random consistency graphs with a planted clique.

Each problem has n associations, random outlier affinities U(0, 1) on a fraction `--density`
of the pairs, and a planted clique of `--clique` inliers with affinities U(0.8, 1) (the setting
of clipper.md, where CLIPPER's default rounding keeps ~18 of 20 inliers). For every size and
rounding it reports the median wall time of the full solve (input checks, solve, rounding), the
process's peak resident memory so far, and the precision and recall of the planted clique.

    python scripts/bench_clipper.py --sizes 500 1000 2000 --dtype float64
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from meridian_torch.config.matching import ClipperConfig
from meridian_torch.matching.clipper import solve_clipper
from meridian_torch.runtime import peak_rss_mib

__all__ = ["planted_clique_problem", "bench_clipper", "main"]

ROUNDINGS = ("clipper", "support", "densest")


def planted_clique_problem(
    n: int, k: int, density: float, seed: int, dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, torch.Tensor]:
    """A symmetric (n, n) affinity with unit diagonal and a planted k-clique; returns (M, truth)."""
    g = torch.Generator().manual_seed(seed)
    W = torch.rand(n, n, generator=g, dtype=dtype) * (torch.rand(n, n, generator=g) < density)
    members = torch.randperm(n, generator=g)[:k]
    W[members[:, None], members[None, :]] = 0.8 + 0.2 * torch.rand(k, k, generator=g, dtype=dtype)
    M = torch.triu(W, 1)
    M = M + M.T
    M.fill_diagonal_(1.0)
    truth = torch.zeros(n, dtype=torch.bool)
    truth[members] = True
    return M, truth


def bench_clipper(
    sizes: list[int],
    seed: int,
    *,
    clique: int = 20,
    density: float = 0.08,
    dtype: torch.dtype = torch.float64,
    repeats: int = 3,
    roundings: tuple[str, ...] = ROUNDINGS,
) -> list[dict]:
    """Time `solve_clipper` per size and rounding; one dict per (size, rounding).

    Keys: n, rounding, dtype, time_ms (median of `repeats` after one warm-up), peak_rss_mib
    (process peak so far), baseline_rss_mib (peak before the first problem: imports),
    iterations, penalty_updates, selected, precision, recall.
    """
    baseline = peak_rss_mib()
    rows = []
    for i, n in enumerate(sizes):
        M, truth = planted_clique_problem(n, clique, density, seed + i, dtype)
        for rounding in roundings:
            cfg = ClipperConfig(rounding=rounding)
            solve_clipper(M, cfg=cfg)  # warm-up: lazy imports and allocator
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                result = solve_clipper(M, cfg=cfg)
                times.append(time.perf_counter() - start)
            selected = result.inliers[0]
            hits = int((selected & truth).sum())
            rows.append(
                {
                    "n": n,
                    "rounding": rounding,
                    "dtype": str(dtype).removeprefix("torch."),
                    "time_ms": 1e3 * statistics.median(times),
                    "peak_rss_mib": peak_rss_mib(),
                    "baseline_rss_mib": baseline,
                    "iterations": int(result.iterations[0]),
                    "penalty_updates": int(result.penalty_updates[0]),
                    "selected": int(selected.sum()),
                    "precision": hits / max(int(selected.sum()), 1),
                    "recall": hits / int(truth.sum()),
                }
            )
    return rows


def main(argv: list[str] | None = None) -> None:
    """Command-line driver: parse options, run `bench_clipper`, print a table."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--sizes", type=int, nargs="+", default=[500, 1000, 2000], help="numbers of associations n"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the random graphs")
    parser.add_argument("--clique", type=int, default=20, help="size of the planted clique")
    parser.add_argument(
        "--density", type=float, default=0.08, help="fraction of outlier pairs with an affinity"
    )
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    parser.add_argument(
        "--repeats", type=int, default=3, help="timed runs per configuration (median reported)"
    )
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    rows = bench_clipper(
        args.sizes,
        args.seed,
        clique=args.clique,
        density=args.density,
        dtype=getattr(torch, args.dtype),
        repeats=args.repeats,
    )
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, dtype {args.dtype}, "
        f"peak RSS before the first problem {rows[0]['baseline_rss_mib']:.1f} MiB"
    )
    header = ("n", "rounding", "time ms", "peak MiB", "iters", "sel", "prec", "recall")
    print("{:>6} {:>9} {:>9} {:>9} {:>6} {:>5} {:>5} {:>6}".format(*header))
    for r in rows:
        print(
            f"{r['n']:>6} {r['rounding']:>9} {r['time_ms']:>9.1f} {r['peak_rss_mib']:>9.1f} "
            f"{r['iterations']:>6} {r['selected']:>5} {r['precision']:>5.2f} {r['recall']:>6.2f}"
        )


if __name__ == "__main__":
    main()

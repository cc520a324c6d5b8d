#!/usr/bin/env python
"""Ground submaps against the simulator's ground truth.

Maps each sequence with `GroundMapper` (config + overrides), moves every submap's primitives to
the world through the ground-truth pose at the submap time (x-y part of T_world_base *
T_odom_base^-1), and scores them with `meridian_torch.evaluation.primitive_metrics`:

points  optimal one-to-one matching within 2 m; GT = centres of compact objects (tree, bush,
        rock, car < 50 m^2).
lines   by length, a piece counts when within 1 m of a GT line with direction within 10 deg;
        GT = region borders + building outlines.
Precision is against all ground truth; recall only against the ground truth the submap could
have seen: GT points within 2 m and GT line pieces within 1 m of the submap's flattened segment
points (its observed footprint).
artefact fraction  the share of predicted line length that is NOT near a GT line and lies along
        the submap's occluded points (>= half of its samples within `artifact_dist_m` of them):
        FOV-edge, depth-cutoff and crop-edge lines. With --unfiltered the same is reported for
        the submaps made without the artefact-line test, to show what it removes.
Totals pool all submaps (length- / count-weighted).

Example: python scripts/eval_submaps.py demo-sequence -c configs/demo.yaml --unfiltered
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from meridian_torch.config import load_config
from meridian_torch.evaluation.primitive_metrics import (
    line_metrics,
    point_metrics,
    sample_segments,
    world_ground_truth,
)
from meridian_torch.geometry.planar import scalar_yaw_of, se2_from_xy_yaw
from meridian_torch.geometry.se3 import se3_inverse
from meridian_torch.io.sequence import SequenceReader
from meridian_torch.mapping.ground_map import GroundMapper
from meridian_torch.runtime import resolve_runtime
from meridian_torch.sim.ground_truth import load_ground_truth


def _gt_segments(polylines: list[np.ndarray]) -> np.ndarray:
    segs = [np.stack([p[:-1], p[1:]], axis=1) for p in polylines if len(p) >= 2]
    return np.concatenate(segs) if segs else np.zeros((0, 2, 2))


def run_mapper(seq: Path, cfg, max_frames: int | None = None) -> tuple[list, list, float, int]:
    reader = SequenceReader(seq)
    mapper = GroundMapper.from_config(cfg, reader.camera, resolve_runtime(cfg.runtime), keep_geometries=True)
    n = len(reader) if max_frames is None else min(max_frames, len(reader))
    batch = cfg.ground_map.batch_size
    started = time.perf_counter()
    submaps = []
    for s in range(0, n, batch):
        submaps += mapper.add_frames([reader[i] for i in range(s, min(s + batch, n))])
    submaps += mapper.finish()
    return submaps, mapper.geometries, time.perf_counter() - started, n


def score(seq: Path, submaps: list, geometries: list, dist_artifact: float) -> dict:
    reader = SequenceReader(seq)
    gt_points, gt_lines = world_ground_truth(load_ground_truth(seq / "sim"))
    gt_segs = _gt_segments(gt_lines)
    tot = {k: 0.0 for k in ("p_match", "p_pred", "p_gt", "l_cov_pred", "l_pred", "l_cov_gt", "l_gt", "artefact")}
    rows = []
    for sm, geo in zip(submaps, geometries):
        T_world_base = reader.groundtruth.interpolate(np.array([sm.time]))[0]
        T_world_odom = T_world_base @ se3_inverse(sm.T_odom_base)
        S = se2_from_xy_yaw(T_world_odom[0, 3], T_world_odom[1, 3], scalar_yaw_of(T_world_odom))
        R, t = S[:2, :2], S[:2, 2]
        pts = sm.primitives.points_xy.double().numpy() @ R.T + t
        lines = sm.primitives.line_endpoints.double().numpy() @ R.T + t
        seen = geo.points_xy @ R.T + t
        occ = geo.occluded_xy @ R.T + t
        seen_tree = cKDTree(seen) if len(seen) else None
        # ground truth the submap could have seen
        gp = gt_points[seen_tree.query(gt_points)[0] <= 2.0] if seen_tree is not None and len(gt_points) else gt_points[:0]
        mids, _, _, idx = sample_segments(gt_segs, 0.25)
        near_gt = seen_tree.query(mids)[0] <= 1.0 if seen_tree is not None else np.zeros(len(mids), bool)
        seen_pieces = np.unique(idx[near_gt])
        pm_prec = point_metrics(pts, gt_points, 2.0)
        pm_rec = point_metrics(pts, gp, 2.0)
        lm_prec = line_metrics(lines, gt_segs, 1.0, 10.0)
        lm_rec = line_metrics(lines, gt_segs[seen_pieces], 1.0, 10.0)
        # artefacts: uncovered predicted length along occluded points
        art = 0.0
        if len(lines):
            m, _, w, li = sample_segments(lines, 0.25)
            along = np.zeros(len(lines))
            if len(occ):
                near_occ = cKDTree(occ).query(m)[0] <= dist_artifact
                along = np.bincount(li, w * near_occ, minlength=len(lines)) / np.maximum(
                    np.bincount(li, w, minlength=len(lines)), 1e-9)
            uncovered = _uncovered_length(lines, gt_segs)
            art = float(uncovered[along >= 0.5].sum())
        tot["p_match"] += pm_prec["n_matched"]
        tot["p_pred"] += pm_prec["n_pred"]
        tot["p_gt"] += pm_rec["n_gt"]
        tot["l_cov_pred"] += lm_prec["covered_pred_length"]
        tot["l_pred"] += lm_prec["pred_length"]
        tot["l_cov_gt"] += lm_rec["covered_gt_length"]
        tot["l_gt"] += lm_rec["gt_length"]
        tot["artefact"] += art
        rows.append({"index": sm.index, "points": len(pts), "lines": len(lines),
                     "point_precision": pm_prec["precision"], "point_recall": pm_rec["recall"],
                     "line_precision": lm_prec["precision"], "line_recall": lm_rec["recall"],
                     "line_length_m": lm_prec["pred_length"], "artefact_length_m": art})
    return {"rows": rows, "totals": tot}


def _uncovered_length(lines: np.ndarray, gt_segs: np.ndarray) -> np.ndarray:
    """Per predicted line, the length of its pieces NOT within 1 m / 10 deg of a GT segment."""
    from meridian_torch.evaluation.primitive_metrics import _near_compatible_pairs

    mids, dirs, w, li = sample_segments(lines, 0.25)
    i, _ = _near_compatible_pairs(mids, dirs, gt_segs[:, 0], gt_segs[:, 1], 1.0, math.cos(math.radians(10)))
    covered = np.zeros(len(mids), bool)
    covered[i] = True
    return np.bincount(li, w * ~covered, minlength=len(lines))


def summarize(name: str, result: dict, seconds: float, frames: int, duration_s: float) -> dict:
    t = result["totals"]
    return {
        "sequence": name,
        "submaps": len(result["rows"]),
        "points": int(sum(r["points"] for r in result["rows"])),
        "lines": int(sum(r["lines"] for r in result["rows"])),
        "point_precision": t["p_match"] / t["p_pred"] if t["p_pred"] else float("nan"),
        "point_recall": float(np.nanmean([r["point_recall"] for r in result["rows"]])) if result["rows"] else float("nan"),
        "line_precision": t["l_cov_pred"] / t["l_pred"] if t["l_pred"] else float("nan"),
        "line_recall": t["l_cov_gt"] / t["l_gt"] if t["l_gt"] else float("nan"),
        "artefact_fraction": t["artefact"] / t["l_pred"] if t["l_pred"] else float("nan"),
        "line_length_m": t["l_pred"],
        "seconds": seconds,
        "fps": frames / seconds,
        "real_time_factor": duration_s / seconds,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequences", nargs="+", type=Path, help="simulated sequence folders (with sim/)")
    ap.add_argument("-c", "--config", type=Path, default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="KEY=VALUE config override")
    ap.add_argument("--unfiltered", action="store_true", help="also score submaps without the artefact-line test")
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames of each sequence")
    ap.add_argument("--json", type=Path, default=None, help="write the table as JSON here")
    args = ap.parse_args()
    cfg = load_config(args.config, args.overrides)
    variants = [("", cfg)]
    if args.unfiltered:
        variants.append((" (no artefact test)", load_config(args.config, args.overrides + [
            "ground_map.artifact_min_near_fraction=0", "ground_map.artifact_min_clear_fraction=0"])))
    table = []
    for seq in args.sequences:
        reader = SequenceReader(seq)
        for suffix, c in variants:
            submaps, geometries, seconds, frames = run_mapper(seq, c, args.frames)
            duration = float(reader.frame_times[frames - 1] - reader.frame_times[0])
            res = score(seq, submaps, geometries, c.ground_map.artifact_dist_m)
            table.append(summarize(seq.name + suffix, res, seconds, frames, duration))
    cols = ["sequence", "submaps", "points", "lines", "point_precision", "point_recall", "line_precision",
            "line_recall", "artefact_fraction", "fps", "real_time_factor"]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for row in table:
        print("| " + " | ".join(f"{row[c]:.2f}" if isinstance(row[c], float) else str(row[c]) for c in cols) + " |")
    if args.json:
        args.json.write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()

"""Compare classical segmenter/describer variants on simulated aerial patches, ground frames and real orthophotos.

Metrics (all per variant, averaged over patches):

* BR: boundary recall, fraction of ground-truth class-border pixels within 1 m of a segment border;
* BP: boundary precision, fraction of segment-border pixels within 1 m of a ground-truth border;
* UE: under-segmentation error (Neubert & Protzel), sum over segments of min(inside, outside)
  pixels per ground-truth region, divided by the image size;
* obj: fraction of ground-truth objects (tree, bush, rock, car, building; >= 2 m^2, not touching
  the patch border) that have their own segment (IoU > 0.5);
* M: segments per patch; ms: wall time per 200x200 patch (0.3 m/px);
* tree@0.5: fraction of real NEON tree boxes (deepforest, 0.1 m/px) matched by a segment box with IoU > 0.5;
* ground: ms per 640x360 ground frame and segments per frame;
* same/diff: median descriptor cosine between segments (>= 70 % one class) of the same / of
  different classes, aerial vs ground views (cross-view, what the matcher needs).

Usage: python scripts/tune_segmentation.py [--patches 12] [--frames 6] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import torch

from meridian_torch.config.perception import (
    ClassicalSegmenterConfig,
    DescriptorConfig,
    PixelFeatureConfig,
    SegmenterConfig,
)
from meridian_torch.config.sim import (
    CameraConfig,
    GroundRenderConfig,
    OrthoRenderConfig,
    TrajectoryConfig,
    WorldConfig,
)
from meridian_torch.perception.factory import build_segment_describer, build_segmenter
from meridian_torch.sim.camera import camera_model_from_config
from meridian_torch.sim.classes import OBJECT_CLASSES
from meridian_torch.sim.ground_render import GroundRenderer
from meridian_torch.sim.ortho_render import render_orthophoto
from meridian_torch.sim.procedural import generate_world
from meridian_torch.sim.trajectory import plan_drive

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
MPP = 0.3
PATCH = 200

# Segmenter variants: (name, classical segmenter settings, descriptor texture weight).
VARIANTS: list[tuple[str, dict, float]] = [
    ("felz, no merge", dict(merge_threshold=1e-6, merge_levels=1), 0.4),
    ("felz+RAG colour only", dict(texture_weight=0.0, boundary_weight=0.0), 0.4),
    ("felz+RAG colour+border", dict(texture_weight=0.0), 0.4),
    ("felz+RAG colour+border+texture", dict(), 0.4),
    ("felz+RAG (default), desc w/o texture", dict(), 0.0),
    ("slic+RAG colour+border+texture", dict(oversegmentation="slic"), 0.4),
]


def _borders(labels: np.ndarray) -> np.ndarray:
    b = np.zeros(labels.shape, bool)
    dh = labels[:, 1:] != labels[:, :-1]
    dv = labels[1:, :] != labels[:-1, :]
    b[:, 1:] |= dh
    b[:, :-1] |= dh
    b[1:, :] |= dv
    b[:-1, :] |= dv
    return b


def _near(border: np.ndarray, radius_px: float) -> np.ndarray:
    dist = cv2.distanceTransform((~border).astype(np.uint8), cv2.DIST_L2, 3)
    return dist <= radius_px


def _contingency(seg: np.ndarray, gt: np.ndarray) -> np.ndarray:
    s = np.unique(seg, return_inverse=True)[1].ravel()
    g = np.unique(gt, return_inverse=True)[1].ravel()
    table = np.zeros((s.max() + 1, g.max() + 1), np.int64)
    np.add.at(table, (s, g), 1)
    return table


def aerial_metrics(seg: np.ndarray, cls: np.ndarray, inst: np.ndarray) -> dict[str, float]:
    """Boundary recall/precision, under-segmentation error and object recall for one patch."""
    # Ground-truth regions: object instances, and connected areas of each region class.
    gt = np.where(inst >= 0, inst.astype(np.int64) + 1000, -1)
    for c in np.unique(cls[inst < 0]):
        n, comp = cv2.connectedComponents(((cls == c) & (inst < 0)).astype(np.uint8), connectivity=4)
        gt = np.where((cls == c) & (inst < 0), comp + 100_000 * (int(c) + 1), gt)
    gtb, sb = _borders(gt), _borders(seg)
    r = 1.0 / MPP
    br = float((_near(sb, r) & gtb).sum() / max(gtb.sum(), 1))
    bp = float((_near(gtb, r) & sb).sum() / max(sb.sum(), 1))
    table = _contingency(seg, gt)
    ue = float(np.minimum(table, table.sum(1, keepdims=True) - table).sum() / seg.size)
    # Objects fully inside the patch and at least 2 m^2.
    ids = [i for i in np.unique(inst[inst >= 0]) if int(np.bincount(cls[inst == i]).argmax()) in OBJECT_CLASSES]
    edge = np.unique(np.concatenate([inst[0], inst[-1], inst[:, 0], inst[:, -1]]))
    hits, total = 0, 0
    for i in ids:
        m = inst == i
        if i in edge or m.sum() * MPP**2 < 2.0:
            continue
        total += 1
        inter = np.bincount(seg[m], minlength=seg.max() + 1)
        union = np.bincount(seg.ravel(), minlength=seg.max() + 1) + m.sum() - inter
        hits += bool((inter / union).max() > 0.5)
    return dict(BR=br, BP=bp, UE=ue, obj=hits / max(total, 1), n_obj=total)


def _labels(segmentation) -> np.ndarray:
    return segmentation.masks[0].to(torch.uint8).argmax(0).numpy()


def sim_data(seed: int, n_patches: int, n_frames: int):
    world = generate_world(WorldConfig(), seed)
    ortho = render_orthophoto(world, OrthoRenderConfig(meters_per_pixel=MPP), seed)
    img = np.asarray(ortho.image, np.float32) / 255.0
    h, w = img.shape[:2]
    cls = cv2.resize(world.class_map, (w, h), interpolation=cv2.INTER_NEAREST)
    inst = cv2.resize(world.instance_map, (w, h), interpolation=cv2.INTER_NEAREST)
    rng = np.random.default_rng(seed)
    patches = []
    for _ in range(n_patches):
        r, c = rng.integers(0, h - PATCH), rng.integers(0, w - PATCH)
        sl = np.s_[r : r + PATCH, c : c + PATCH]
        patches.append((img[sl], cls[sl], inst[sl]))
    camera = camera_model_from_config(CameraConfig())
    traj = plan_drive(world, TrajectoryConfig(length_m=300.0), seed)
    idx = np.linspace(0, len(traj) - 1, n_frames).astype(int)
    T = traj.poses[idx] @ camera.T_base_camera
    renderer = GroundRenderer(world, camera, GroundRenderConfig())
    rgb, _ = renderer.render(T, seed=seed)
    gcls, _, _ = renderer.render_labels(T)
    frames = [(f.astype(np.float32) / 255.0, c) for f, c in zip(rgb, gcls)]
    return patches, frames


def neon_trees() -> list[tuple[np.ndarray, np.ndarray]]:
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)  # GeoTIFF tags are not errors here
    out = []
    for name in ("OSBS_029.tif", "SOAP_061.png"):
        img = cv2.imread(str(SHARED / "deepforest_neon" / name), cv2.IMREAD_COLOR)
        xml = SHARED / "deepforest_neon" / (Path(name).stem + ".xml")
        if img is None or not xml.exists():
            continue
        boxes = [
            [float(o.find("bndbox").find(k).text) for k in ("xmin", "ymin", "xmax", "ymax")]
            for o in ET.parse(xml).getroot().iter("object")
        ]
        out.append((cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0, np.array(boxes)))
    return out


def tree_recall(seg: np.ndarray, boxes: np.ndarray) -> tuple[int, int]:
    ys, xs = np.indices(seg.shape)
    n = seg.max() + 1
    sb = np.stack(
        [
            np.array([xs.ravel()[seg.ravel() == i].min() for i in range(n)]),
            np.array([ys.ravel()[seg.ravel() == i].min() for i in range(n)]),
            np.array([xs.ravel()[seg.ravel() == i].max() + 1 for i in range(n)]),
            np.array([ys.ravel()[seg.ravel() == i].max() + 1 for i in range(n)]),
        ],
        1,
    )
    lt = np.maximum(boxes[:, None, :2], sb[None, :, :2])
    rb = np.minimum(boxes[:, None, 2:], sb[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), -1)
    area = lambda b: np.prod(b[..., 2:] - b[..., :2], -1)  # noqa: E731
    iou = inter / (area(boxes)[:, None] + area(sb)[None] - inter)
    return int((iou.max(1) > 0.5).sum()), len(boxes)


def _segment_classes(desc: torch.Tensor, seg: np.ndarray, cls: np.ndarray) -> tuple[list[torch.Tensor], list[int]]:
    out_d, out_c = [], []
    for i in range(seg.max() + 1):
        c = cls[seg == i]
        c = c[c != 255]
        if c.size < 30:
            continue
        counts = np.bincount(c)
        if counts.max() >= 0.7 * c.size:
            out_d.append(desc[i])
            out_c.append(int(counts.argmax()))
    return out_d, out_c


def cross_view_cosines(aerial: tuple[list, list], ground: tuple[list, list]) -> tuple[float, float]:
    if not aerial[0] or not ground[0]:
        return float("nan"), float("nan")
    a, ca = torch.stack(aerial[0]), torch.tensor(aerial[1])
    g, cg = torch.stack(ground[0]), torch.tensor(ground[1])
    cos = a @ g.T
    same = ca[:, None] == cg[None, :]
    return float(cos[same].median()), float(cos[~same].median())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--patches", type=int, default=12, help="200x200 simulated aerial patches")
    ap.add_argument("--frames", type=int, default=6, help="simulated 640x360 ground frames")
    ap.add_argument("--seed", type=int, default=0, help="world seed")
    ap.add_argument("--no-real", action="store_true", help="skip the real NEON tree orthophotos")
    args = ap.parse_args()
    torch.manual_seed(0)
    patches, frames = sim_data(args.seed, args.patches, args.frames)
    neon = [] if args.no_real else neon_trees()
    cols = ["BR", "BP", "UE", "obj", "M", "ms", "tree@0.5", "gr ms", "gr M", "same", "diff"]
    print(f"{'variant':40s}" + "".join(f"{c:>9s}" for c in cols))
    for name, kw, tex_w in VARIANTS:
        seg = build_segmenter(SegmenterConfig(classical=ClassicalSegmenterConfig(**kw)))
        describer = build_segment_describer(DescriptorConfig(classical=PixelFeatureConfig(texture_weight=tex_w)))
        rows, times, counts = [], [], []
        aerial_desc: tuple[list, list] = ([], [])
        for img, cls, inst in patches:
            x = torch.from_numpy(img).permute(2, 0, 1)[None].contiguous()
            t0 = time.perf_counter()
            s = seg.segment(x, MPP)
            times.append(time.perf_counter() - t0)
            lab = _labels(s)
            counts.append(int(s.valid.sum()))
            rows.append(aerial_metrics(lab, cls, inst))
            d, c = _segment_classes(describer.describe(x, s.masks, s.valid)[0], lab, cls)
            aerial_desc[0].extend(d)
            aerial_desc[1].extend(c)
        hit = tot = 0
        for img, boxes in neon:
            x = torch.from_numpy(img).permute(2, 0, 1)[None].contiguous()
            h, t = tree_recall(_labels(seg.segment(x, 0.1)), boxes)
            hit, tot = hit + h, tot + t
        g_times, g_counts = [], []
        ground_desc: tuple[list, list] = ([], [])
        for img, cls in frames:
            x = torch.from_numpy(img).permute(2, 0, 1)[None].contiguous()
            t0 = time.perf_counter()
            s = seg.segment(x, None)
            g_times.append(time.perf_counter() - t0)
            g_counts.append(int(s.valid.sum()))
            d, c = _segment_classes(describer.describe(x, s.masks, s.valid)[0], _labels(s), cls)
            ground_desc[0].extend(d)
            ground_desc[1].extend(c)
        same, diff = cross_view_cosines(aerial_desc, ground_desc)
        obj = sum(r["obj"] * r["n_obj"] for r in rows) / max(sum(r["n_obj"] for r in rows), 1)
        vals = [
            np.mean([r["BR"] for r in rows]),
            np.mean([r["BP"] for r in rows]),
            np.mean([r["UE"] for r in rows]),
            obj,
            np.mean(counts),
            1e3 * np.median(times),
            hit / max(tot, 1),
            1e3 * np.median(g_times),
            np.mean(g_counts),
            same,
            diff,
        ]
        print(f"{name:40s}" + "".join(f"{v:9.3f}" if abs(v) < 10 else f"{v:9.1f}" for v in vals))


if __name__ == "__main__":
    main()

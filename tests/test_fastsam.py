"""FastSAM back end: batched postprocessing against slow loops, letterbox geometry through a scripted
ONNX graph, graph checks, and the tiny random stand-in model through the factory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.ndimage import map_coordinates
from torch import nn

from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.config.perception import FastSamConfig
from meridian_torch.errors import ConfigError, ModelWeightsError
from meridian_torch.export.onnx import export_checked
from meridian_torch.export.tiny_yolo_seg import export_tiny_yolo_seg
from meridian_torch.perception.factory import build_segmenter
from meridian_torch.perception.neural.fastsam import (
    PAD_VALUE,
    FastSamSegmenter,
    letterbox,
    prototype_masks,
    select_detections,
)

pytest.importorskip("onnxruntime")


def _settings(**overrides) -> dict:
    """The shipped segmenter settings (the config's defaults) with `overrides`."""
    return {**FastSamConfig().model_dump(exclude={"weights_path", "random_weights_seed"}), **overrides}


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def _slow_detections(preds: np.ndarray, nc: int, conf: float, iou: float, max_det: int) -> list[list[tuple]]:
    """Per image: every (anchor, class) above conf, greedy same-class NMS in score order."""
    out = []
    for p in preds:
        cands = []
        for a in range(p.shape[1]):
            cx, cy, w, h = p[:4, a]
            box = np.array([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])
            for c in range(nc):
                if p[4 + c, a] >= conf:
                    cands.append((p[4 + c, a], c, box, p[4 + nc :, a]))
        cands.sort(key=lambda t: -t[0])
        kept: list[tuple] = []
        for cand in cands:
            if all(k[1] != cand[1] or _iou(k[2], cand[2]) <= iou for k in kept):
                kept.append(cand)
        out.append(kept[:max_det])
    return out


def test_select_detections_equals_greedy_loop() -> None:
    g = torch.Generator().manual_seed(0)
    b, nc, k, n = 3, 2, 4, 80
    centres = torch.rand(b, 2, n, generator=g) * 100
    sizes = 5 + torch.rand(b, 2, n, generator=g) * 40
    scores = torch.rand(b, nc, n, generator=g)
    scores[2] *= 0.2  # an image with few candidates
    preds = torch.cat([centres, sizes, scores, torch.randn(b, k, n, generator=g)], dim=1).double()
    boxes, got_scores, coeffs, valid = select_detections(preds, nc, conf=0.3, iou=0.4, max_det=7)
    expected = _slow_detections(preds.numpy(), nc, 0.3, 0.4, 7)
    assert valid.shape == (b, max(len(e) for e in expected))
    for i, kept in enumerate(expected):
        m = len(kept)
        assert valid[i].tolist() == [True] * m + [False] * (valid.shape[1] - m)
        np.testing.assert_allclose(got_scores[i, :m].numpy(), [t[0] for t in kept])
        np.testing.assert_allclose(boxes[i, :m].numpy(), np.stack([t[2] for t in kept]) if m else np.zeros((0, 4)))
        np.testing.assert_allclose(coeffs[i, :m].numpy(), np.stack([t[3] for t in kept]) if m else np.zeros((0, k)))
        assert torch.all(got_scores[i, m:] == 0)
    assert int(valid.sum(1).max()) == 7  # max_det truncates


def test_prototype_masks_equal_per_detection_resampling() -> None:
    g = torch.Generator().manual_seed(1)
    images = torch.rand(2, 3, 90, 70, generator=g)  # portrait: padding left and right
    _, geo = letterbox(images, imgsz=128, stride=32, input_hw=(128, 128))
    k, m, (ph, pw) = 5, 6, (32, 32)
    protos = torch.randn(2, k, ph, pw, generator=g, dtype=torch.float64)
    coeffs = torch.randn(2, m, k, generator=g, dtype=torch.float64)
    xy0 = torch.rand(2, m, 2, generator=g, dtype=torch.float64) * 80
    boxes = torch.cat([xy0, xy0 + 20 + torch.rand(2, m, 2, generator=g, dtype=torch.float64) * 60], dim=-1)
    valid = torch.ones(2, m, dtype=torch.bool)
    valid[1, 4:] = False
    masks = prototype_masks(coeffs, protos, boxes, valid, geo)

    h, w = geo.image_hw
    (rh, rw), (ih, iw) = geo.resized_hw, geo.input_hw
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    # frame pixel centre -> input pixel -> prototype cell coordinate (cell i is centred at i)
    py = ((rows + 0.5) * rh / h + geo.pad_top) * ph / ih - 0.5
    px = ((cols + 0.5) * rw / w + geo.pad_left) * pw / iw - 0.5
    for bi in range(2):
        for mi in range(m):
            if not valid[bi, mi]:
                assert not masks[bi, mi].any()
                continue
            logit = np.tensordot(coeffs[bi, mi].numpy(), protos[bi].numpy(), axes=1)
            value = map_coordinates(logit, [py, px], order=1, mode="nearest")
            x0, y0, x1, y1 = boxes[bi, mi].numpy()
            in_box = ((cols + 0.5 >= (x0 - geo.pad_left) * w / rw) & (cols + 0.5 < (x1 - geo.pad_left) * w / rw)
                      & (rows + 0.5 >= (y0 - geo.pad_top) * h / rh) & (rows + 0.5 < (y1 - geo.pad_top) * h / rh))
            np.testing.assert_array_equal(masks[bi, mi].numpy(), (value > 0) & in_box)


def test_letterbox_centres_the_frame_on_grey() -> None:
    images = torch.rand(1, 3, 60, 100)
    canvas, geo = letterbox(images, imgsz=200, stride=32)  # dynamic graph: canvas to a stride multiple
    assert geo.resized_hw == (120, 200) and geo.input_hw == (128, 224)
    assert (geo.pad_top, geo.pad_left) == (4, 12)
    top, left = geo.pad_top, geo.pad_left
    inner = canvas[..., top : top + 120, left : left + 200]
    assert torch.allclose(inner, torch.nn.functional.interpolate(images, size=(120, 200), mode="bilinear"))
    pad = torch.ones_like(canvas, dtype=torch.bool)
    pad[..., top : top + 120, left : left + 200] = False
    assert torch.all(canvas[pad] == PAD_VALUE)


class _ScriptedYoloSeg(nn.Module):
    """Fixed predictions and prototypes (a graph input is still required and used)."""

    def __init__(self, preds: torch.Tensor, protos: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("preds", preds)
        self.register_buffer("protos", protos)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        zero = images.mean() * 0
        return self.preds + zero, self.protos + zero


def _detection(cx: float, cy: float, w: float, h: float, score: float, channel: int) -> torch.Tensor:
    coeffs = torch.zeros(32)
    coeffs[channel] = 1.0
    return torch.cat([torch.tensor([cx, cy, w, h, score]), coeffs])


@pytest.fixture(scope="module")
def scripted_graph(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # 256 px input; a 72 x 128 frame is scaled x2 to 144 x 256 and padded 56 px at the top.
    protos = torch.full((1, 32, 64, 64), -10.0)
    protos[0, 0, 20:30, 10:30] = 10.0  # input y 80..120, x 40..120 -> frame rows 12..32, cols 20..60
    protos[0, 1, 39:49, 50:60] = 10.0  # input y 156..196, x 200..240 -> frame rows 50..70, cols 100..120
    dets = [
        _detection(40, 128, 80, 144, 0.9, 0),  # box = frame cols 0..40: crops the first blob to cols 20..40
        _detection(40, 128, 80, 144, 0.1, 0),  # below conf
        _detection(41, 128, 80, 144, 0.8, 0),  # IoU 0.975 with the first: suppressed
        _detection(128, 128, 256, 144, 0.5, 1),  # whole frame
    ]
    preds = torch.stack(dets, dim=1)[None]  # (1, 37, 4)
    path = tmp_path_factory.mktemp("fastsam") / "scripted.onnx"
    export_checked(_ScriptedYoloSeg(preds, protos), (torch.rand(1, 3, 256, 256),), path,
                   input_names=["images"], output_names=["output0", "output1"])
    return path


def test_scripted_graph_masks_land_where_the_geometry_says(scripted_graph: Path) -> None:
    segmenter = FastSamSegmenter.from_file(scripted_graph, **_settings(imgsz=256))
    seg = segmenter.segment(torch.rand(2, 3, 72, 128), None)  # fixed batch 1: two graph calls
    expected = torch.zeros(2, 72, 128, dtype=torch.bool)
    expected[0, 12:32, 20:40] = True
    expected[1, 50:70, 100:120] = True
    assert seg.masks.shape == (2, 2, 72, 128)
    assert seg.valid.all()
    for b in range(2):
        assert torch.equal(seg.masks[b], expected)
        assert torch.allclose(seg.scores[b], torch.tensor([0.9, 0.5]))


def test_graph_problems_are_clear_errors(tmp_path: Path, scripted_graph: Path) -> None:
    with pytest.raises(ModelWeightsError, match="FastSAM ONNX graph not found: .*missing.onnx"):
        FastSamSegmenter.from_file(tmp_path / "missing.onnx")
    with pytest.raises(ConfigError, match="256x256 px.*imgsz is 1024"):
        FastSamSegmenter.from_file(scripted_graph, **_settings(imgsz=1024))
    one_output = tmp_path / "one.onnx"
    export_checked(nn.Conv2d(3, 8, 3), (torch.rand(1, 3, 64, 64),), one_output, input_names=["images"],
                   output_names=["out"])
    with pytest.raises(ModelWeightsError, match="expected two outputs"):
        FastSamSegmenter.from_file(one_output, **_settings(imgsz=64))
    cfg = load_config(None, ["perception.ground_segmenter.backend=fastsam"])
    with pytest.raises(ConfigError, match="fastsam.weights_path"):
        build_segmenter(cfg.perception.ground_segmenter)


def test_tiny_random_model_through_the_factory_keeps_the_protocol() -> None:
    cfg = load_config(CONFIG_DIR / "tiny.yaml", ["perception.ground_segmenter.backend=fastsam"])
    segmenter = build_segmenter(cfg.perception.ground_segmenter)
    images = torch.rand(2, 3, 72, 128, generator=torch.Generator().manual_seed(3))
    seg = segmenter.segment(images, None)
    b, m, h, w = seg.masks.shape
    assert (b, h, w) == (2, 72, 128) and seg.masks.dtype == torch.bool
    assert seg.valid.any()
    area = seg.masks.flatten(2).sum(-1)
    assert torch.all((area > 0) == seg.valid)  # empty masks are invalid, invalid masks empty
    assert torch.all(seg.scores[~seg.valid] == 0)
    conf = cfg.perception.ground_segmenter.fastsam.conf
    for i in range(b):
        s = seg.scores[i, seg.valid[i]]
        assert torch.all((s >= conf) & (s <= 1)) and torch.all(s[:-1] >= s[1:])


def test_dynamic_graph_batch_equals_single_images(tmp_path: Path) -> None:
    path = export_tiny_yolo_seg(tmp_path / "tiny_dynamic.onnx", seed=4, imgsz=256, dynamic=True)
    segmenter = FastSamSegmenter.from_file(path, **_settings(imgsz=256))
    assert segmenter.input_hw is None and segmenter.fixed_batch is None
    images = torch.rand(3, 3, 60, 100, generator=torch.Generator().manual_seed(5))
    batch = segmenter.segment(images, None)
    for i in range(3):
        single = segmenter.segment(images[i : i + 1], None)
        n = int(single.valid.shape[1])
        assert torch.equal(batch.valid[i, :n], single.valid[0]) and not batch.valid[i, n:].any()
        assert torch.equal(batch.masks[i, :n], single.masks[0])
        assert torch.allclose(batch.scores[i, :n], single.scores[0])

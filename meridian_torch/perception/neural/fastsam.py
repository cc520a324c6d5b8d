"""FastSAM (YOLOv8-seg) ground-frame segmenter running an ONNX graph exported by the model's owner.

Only the graph runs in onnxruntime; preprocessing and postprocessing are ours and batched:

1. letterbox: scale each frame to fit `imgsz` (aspect kept), pad with grey 114/255 to the graph's
   fixed input size or, for dynamic graphs, to the next multiple of `stride`;
2. detections: candidates with confidence >= `conf` (per class), class-aware box NMS at IoU
   `iou` (torchvision), at most `max_det` per image, in decreasing confidence;
3. masks: coefficients x prototypes, sampled bilinearly straight from the prototype grid at
   every full-resolution pixel (un-letterboxing and upsampling in one step, "retina masks"),
   cropped to the detection box and thresholded at sigmoid 0.5 (logit 0).

Scores are the detection confidences. Reference settings: 1024 px, conf 0.2,
IoU 0.9. Not reproduced: FastSAM's adjustment of boxes that nearly cover the whole frame.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from meridian_torch.errors import ConfigError, ModelWeightsError
from meridian_torch.perception.protocols import Segmentation

__all__ = [
    "LetterboxGeometry",
    "letterbox",
    "select_detections",
    "prototype_masks",
    "FastSamSegmenter",
]

_log = logging.getLogger(__name__)

PAD_VALUE = 114.0 / 255.0
# masks are rendered in chunks of this many detections to bound the float intermediate
_MASK_CHUNK = 32


@dataclass(frozen=True)
class LetterboxGeometry:
    """Where the original frame sits inside the letterboxed network input.

    The frame (H, W) was resized to `resized_hw` and placed at (`pad_top`, `pad_left`) of an
    input of size `input_hw`, all in pixels.
    """

    image_hw: tuple[int, int]
    resized_hw: tuple[int, int]
    input_hw: tuple[int, int]
    pad_top: int
    pad_left: int


def letterbox(
    images: torch.Tensor, imgsz: int, stride: int, input_hw: tuple[int, int] | None = None
) -> tuple[torch.Tensor, LetterboxGeometry]:
    """Resize (B, 3, H, W) images to fit `imgsz` (aspect kept) and centre them on a grey canvas.

    The canvas is `input_hw` (a graph with a fixed input size) or the resized size rounded up to
    a multiple of `stride`.
    """
    h, w = images.shape[-2:]
    box_h, box_w = input_hw if input_hw is not None else (imgsz, imgsz)
    scale = min(box_h / h, box_w / w)
    rh, rw = max(1, round(h * scale)), max(1, round(w * scale))
    if input_hw is None:
        input_hw = (-(-rh // stride) * stride, -(-rw // stride) * stride)
    pad_h, pad_w = input_hw[0] - rh, input_hw[1] - rw
    top, left = pad_h // 2, pad_w // 2
    resized = images if (rh, rw) == (h, w) else F.interpolate(images, size=(rh, rw), mode="bilinear",
                                                              align_corners=False, antialias=scale < 1)
    canvas = F.pad(resized, (left, pad_w - left, top, pad_h - top), value=PAD_VALUE)
    return canvas, LetterboxGeometry((h, w), (rh, rw), tuple(input_hw), top, left)


def select_detections(
    preds: torch.Tensor, num_classes: int, conf: float, iou: float, max_det: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Confidence filter and class-aware NMS over a batch of raw YOLOv8-seg predictions.

    Args:
        preds: (B, 4 + num_classes + K, N) boxes (cx, cy, w, h), class scores, mask coefficients.

    Returns:
        boxes (B, M, 4) as (x0, y0, x1, y1) in input pixels, scores (B, M), coefficients (B, M, K)
        and valid (B, M), each image's detections first and in decreasing score.
    """
    from torchvision.ops import batched_nms

    b, c, n = preds.shape
    k = c - 4 - num_classes
    preds = preds.transpose(1, 2)  # (B, N, C)
    cx, cy, bw, bh = preds[..., 0], preds[..., 1], preds[..., 2], preds[..., 3]
    boxes = torch.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], dim=-1)
    class_scores = preds[..., 4 : 4 + num_classes]
    # every (anchor, class) pair above the threshold is a candidate, as in multi-label YOLO NMS
    image_idx, anchor_idx, class_idx = torch.nonzero(class_scores >= conf, as_tuple=True)
    cand_scores = class_scores[image_idx, anchor_idx, class_idx]
    cand_boxes = boxes[image_idx, anchor_idx]
    keep = batched_nms(cand_boxes, cand_scores, image_idx * num_classes + class_idx, iou)  # decreasing score
    kept_images = image_idx[keep]
    # rank of each kept detection within its image, in score order
    order = torch.argsort(kept_images, stable=True)
    keep, kept_images = keep[order], kept_images[order]
    counts = torch.bincount(kept_images, minlength=b)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(keep), device=preds.device) - starts[kept_images]
    take = rank < max_det
    keep, kept_images, rank = keep[take], kept_images[take], rank[take]
    m = int(counts.clamp(max=max_det).max()) if b else 0
    out_boxes = preds.new_zeros(b, m, 4)
    out_scores = preds.new_zeros(b, m)
    out_coeffs = preds.new_zeros(b, m, k)
    valid = torch.zeros(b, m, dtype=torch.bool, device=preds.device)
    out_boxes[kept_images, rank] = cand_boxes[keep]
    out_scores[kept_images, rank] = cand_scores[keep]
    out_coeffs[kept_images, rank] = preds[kept_images, anchor_idx[keep], 4 + num_classes :]
    valid[kept_images, rank] = True
    return out_boxes, out_scores, out_coeffs, valid


def _prototype_grid(geometry: LetterboxGeometry, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """(1, H, W, 2) grid_sample coordinates of every frame pixel centre over the input (and so the prototypes)."""
    h, w = geometry.image_hw
    (rh, rw), (ih, iw) = geometry.resized_hw, geometry.input_hw
    ys = (torch.arange(h, device=device, dtype=dtype) + 0.5) * (rh / h) + geometry.pad_top
    xs = (torch.arange(w, device=device, dtype=dtype) + 0.5) * (rw / w) + geometry.pad_left
    # input pixels -> normalized [-1, 1] over the input (align_corners=False: edges at +-1)
    gy, gx = 2 * ys / ih - 1, 2 * xs / iw - 1
    return torch.stack(torch.meshgrid(gx, gy, indexing="xy"), dim=-1)[None]


def prototype_masks(
    coeffs: torch.Tensor,
    protos: torch.Tensor,
    boxes: torch.Tensor,
    valid: torch.Tensor,
    geometry: LetterboxGeometry,
) -> torch.Tensor:
    """Full-resolution boolean masks from mask coefficients and prototypes.

    Args:
        coeffs: (B, M, K) mask coefficients; protos: (B, K, h, w) prototypes over the input.
        boxes: (B, M, 4) (x0, y0, x1, y1) in input pixels; valid: (B, M).

    Returns:
        (B, M, H, W) bool at the original frame size: logit > 0 inside the detection box.
    """
    b, m, _ = coeffs.shape
    h, w = geometry.image_hw
    logits = torch.einsum("bmk,bkyx->bmyx", coeffs, protos)
    grid = _prototype_grid(geometry, protos.device, logits.dtype).expand(b, -1, -1, -1)
    # boxes from input pixels to frame pixels
    sy, sx = geometry.resized_hw[0] / h, geometry.resized_hw[1] / w
    x0 = (boxes[..., 0] - geometry.pad_left) / sx
    x1 = (boxes[..., 2] - geometry.pad_left) / sx
    y0 = (boxes[..., 1] - geometry.pad_top) / sy
    y1 = (boxes[..., 3] - geometry.pad_top) / sy
    cols = torch.arange(w, device=coeffs.device, dtype=coeffs.dtype) + 0.5
    rows = torch.arange(h, device=coeffs.device, dtype=coeffs.dtype) + 0.5
    masks = torch.zeros(b, m, h, w, dtype=torch.bool, device=coeffs.device)
    for start in range(0, m, _MASK_CHUNK):  # bounds the float (B, chunk, H, W) intermediate
        sl = slice(start, start + _MASK_CHUNK)
        sampled = F.grid_sample(logits[:, sl], grid, mode="bilinear", padding_mode="border", align_corners=False)
        in_x = (cols >= x0[:, sl, None]) & (cols < x1[:, sl, None])  # (B, c, W)
        in_y = (rows >= y0[:, sl, None]) & (rows < y1[:, sl, None])  # (B, c, H)
        masks[:, sl] = (sampled > 0) & in_y[..., :, None] & in_x[..., None, :] & valid[:, sl, None, None]
    return masks


class FastSamSegmenter:
    """Segmenter over an ONNX FastSAM / YOLOv8-seg graph (one image input, predictions and prototypes out).

    The settings are those of `config.perception.FastSamConfig` (defaults live there).
    """

    def __init__(
        self,
        session: Any,
        source: str,
        *,
        imgsz: int,
        conf: float,
        iou: float,
        max_det: int,
        stride: int,
    ) -> None:
        from meridian_torch.core.onnx_runtime import graph_signature

        self.session, self.source = session, source
        self.imgsz, self.conf, self.iou, self.max_det, self.stride = imgsz, conf, iou, max_det, stride
        sig = graph_signature(session)
        if len(sig.inputs) != 1:
            raise ModelWeightsError(f"{source}: a FastSAM graph has one image input, this one has {dict(sig.inputs)}")
        (self.input_name, in_shape), = sig.inputs.items()
        if len(in_shape) != 4 or in_shape[1] != 3 or sig.input_types[self.input_name] != "tensor(float)":
            raise ModelWeightsError(f"{source}: input {self.input_name!r} must be float (B, 3, H, W), "
                                    f"got {sig.input_types[self.input_name]} {in_shape}")
        ranks = {name: len(shape) for name, shape in sig.outputs.items()}
        preds = [n for n, r in ranks.items() if r == 3]
        protos = [n for n, r in ranks.items() if r == 4]
        if len(sig.outputs) != 2 or len(preds) != 1 or len(protos) != 1:
            raise ModelWeightsError(f"{source}: expected two outputs, predictions (1, 4+classes+K, N) and prototypes "
                                    f"(1, K, h, w), got {dict(sig.outputs)} (is this a YOLOv8-seg/FastSAM export?)")
        self.preds_name, self.protos_name = preds[0], protos[0]
        self.output_order = [list(sig.outputs).index(self.preds_name), list(sig.outputs).index(self.protos_name)]
        self.fixed_batch = in_shape[0] if isinstance(in_shape[0], int) else None
        fixed = [isinstance(d, int) for d in in_shape[2:]]
        if all(fixed):
            self.input_hw: tuple[int, int] | None = (int(in_shape[2]), int(in_shape[3]))
            if max(self.input_hw) != imgsz:
                h, w = self.input_hw
                raise ConfigError(f"{source}: the graph takes {h}x{w} px images but imgsz is {imgsz}; "
                                  f"set fastsam.imgsz={max(h, w)} or re-export at {imgsz}")
        elif any(fixed):
            raise ModelWeightsError(f"{source}: input size {in_shape[2:]} is half fixed, half dynamic")
        else:
            self.input_hw = None
        self.num_coeffs = sig.outputs[self.protos_name][1]
        channels = sig.outputs[self.preds_name][1]
        self.num_classes = None
        if isinstance(channels, int) and isinstance(self.num_coeffs, int):
            self.num_classes = channels - 4 - self.num_coeffs
            if self.num_classes < 1:
                raise ModelWeightsError(f"{source}: predictions have {channels} channels, fewer than "
                                        f"4 box + 1 class + {self.num_coeffs} mask coefficients")
        _log.info("FastSAM graph %s: input %s %s, %s classes", source, self.input_name, in_shape, self.num_classes)

    @classmethod
    def from_file(cls, path: str | os.PathLike[str], **kwargs: Any) -> FastSamSegmenter:
        from meridian_torch.core.onnx_runtime import open_session

        return cls(open_session(path, "FastSAM ONNX graph"), str(path), **kwargs)

    def _run(self, batch: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        from meridian_torch.core.onnx_runtime import run_session

        if self.fixed_batch is None:
            chunks = [batch]
        elif self.fixed_batch == 1:
            chunks = [batch[i : i + 1] for i in range(len(batch))]  # owner exports take one image per call
        else:
            raise ModelWeightsError(f"{self.source}: a fixed batch of {self.fixed_batch} is not supported "
                                    "(export with batch 1 or dynamic)")
        outs = [run_session(self.session, {self.input_name: chunk}) for chunk in chunks]
        preds = torch.from_numpy(np.concatenate([o[self.output_order[0]] for o in outs]))
        protos = torch.from_numpy(np.concatenate([o[self.output_order[1]] for o in outs]))
        return preds, protos

    def segment(self, images: torch.Tensor, meters_per_pixel: float | None) -> Segmentation:
        """Segment (B, 3, H, W) frames in [0, 1]; `meters_per_pixel` is not used (FastSAM works in pixels)."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"images must be (B, 3, H, W), got {tuple(images.shape)}")
        lb, geometry = letterbox(images.detach().to("cpu", torch.float32), self.imgsz, self.stride, self.input_hw)
        preds, protos = self._run(lb.numpy())
        num_classes = self.num_classes if self.num_classes is not None else preds.shape[1] - 4 - protos.shape[1]
        boxes, scores, coeffs, valid = select_detections(preds, num_classes, self.conf, self.iou, self.max_det)
        masks = prototype_masks(coeffs, protos, boxes, valid, geometry)
        valid &= masks.flatten(2).any(dim=2)  # a box can crop its mask away entirely
        scores = torch.where(valid, scores, torch.zeros_like(scores))
        return Segmentation(masks.to(images.device), scores.to(images.device, images.dtype), valid.to(images.device))

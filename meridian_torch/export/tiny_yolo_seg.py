"""A tiny random-weight stand-in with the output signature of an exported FastSAM / YOLOv8-seg model.

Real FastSAM graphs come from their owner's tooling (models/README.md); this one exists so that
tests, `configs/tiny.yaml` runs and the benchmark can exercise the FastSAM back end end to end
without any download. Outputs, as in the owner's ONNX export:

* `output0` (B, 4 + num_classes + num_coeffs, N): per anchor the box (cx, cy, w, h) in input
  pixels, the class scores in [0, 1], then the mask coefficients; N anchors over strides 8, 16, 32;
* `output1` (B, num_coeffs, H/4, W/4): the mask prototypes.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F

__all__ = [
    "TinyYoloSeg",
    "export_tiny_yolo_seg",
    "tiny_yolo_seg_session",
    "TINY_YOLO_SEG_INPUT",
    "TINY_YOLO_SEG_OUTPUTS",
]

TINY_YOLO_SEG_INPUT = "images"
TINY_YOLO_SEG_OUTPUTS = ("output0", "output1")
_STRIDES = (8, 16, 32)


def _conv(c_in: int, c_out: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1), nn.SiLU())


class TinyYoloSeg(nn.Module):
    """Strided conv pyramid with anchor-free box, class and coefficient heads plus a prototype head.

    Input (B, 3, H, W) in [0, 1] with H and W multiples of 32.
    """

    def __init__(self, num_classes: int = 1, num_coeffs: int = 32, width: int = 16) -> None:
        super().__init__()
        self.num_classes = num_classes
        self.stem = nn.Sequential(_conv(3, width, 2), _conv(width, width, 2))  # stride 4
        self.down = nn.ModuleList([_conv(width, width, 2), _conv(width, width, 2), _conv(width, width, 2)])
        self.head = nn.Conv2d(width, 4 + num_classes + num_coeffs, 1)
        self.proto = nn.Sequential(_conv(width, width, 1), nn.Conv2d(width, num_coeffs, 1))

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.stem(images)
        protos = self.proto(x)
        preds = []
        for stride, down in zip(_STRIDES, self.down):
            x = down(x)
            raw = self.head(x)  # (B, 4 + nc + nm, h, w)
            b, _, h, w = raw.shape
            ys = (torch.arange(h, device=raw.device, dtype=raw.dtype) + 0.5) * stride
            xs = (torch.arange(w, device=raw.device, dtype=raw.dtype) + 0.5) * stride
            centre_y, centre_x = torch.meshgrid(ys, xs, indexing="ij")
            # distances to the box sides, as the anchor-free YOLOv8 head predicts them
            left, top, right, bottom = (F.softplus(raw[:, i]) * stride * 2 for i in range(4))
            x0, y0, x1, y1 = centre_x - left, centre_y - top, centre_x + right, centre_y + bottom
            boxes = torch.stack([(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0], dim=1)
            scores = torch.sigmoid(raw[:, 4 : 4 + self.num_classes])
            preds.append(torch.cat([boxes, scores, raw[:, 4 + self.num_classes :]], dim=1).flatten(2))
        return torch.cat(preds, dim=2), protos


def export_tiny_yolo_seg(
    path: str | os.PathLike[str], seed: int, imgsz: int = 256, dynamic: bool = False, width: int = 16
) -> Path:
    """Build a seeded TinyYoloSeg and export it (checked with onnxruntime) to `path`.

    `dynamic` keeps batch and image size symbolic; otherwise the graph takes (1, 3, imgsz, imgsz)
    like the owner's default FastSAM export.
    """
    from meridian_torch.export.onnx import export_checked

    generator = torch.Generator().manual_seed(seed)
    model = TinyYoloSeg(width=width)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=generator) * 0.2)  # spreads scores over (0, 1)
    example = (torch.rand(2 if dynamic else 1, 3, imgsz, imgsz, generator=generator),)
    checks = [(torch.rand(1, 3, imgsz + 32, imgsz - 32, generator=generator),)] if dynamic else []
    export_checked(
        model, example, path, input_names=[TINY_YOLO_SEG_INPUT], output_names=list(TINY_YOLO_SEG_OUTPUTS),
        dynamic_axes={TINY_YOLO_SEG_INPUT: [0, 2, 3]} if dynamic else None, check_inputs=checks,
    )
    return Path(path)


def tiny_yolo_seg_session(seed: int, imgsz: int) -> tuple[object, str]:
    """An onnxruntime session of a freshly exported TinyYoloSeg (the file is deleted after loading)."""
    from meridian_torch.core.onnx_runtime import open_session

    with tempfile.TemporaryDirectory(prefix="meridian-tiny-yolo-seg-") as folder:
        path = export_tiny_yolo_seg(Path(folder) / "tiny_yolo_seg.onnx", seed=seed, imgsz=imgsz)
        return open_session(path), f"tiny random FastSAM stand-in (seed {seed}, {imgsz} px)"

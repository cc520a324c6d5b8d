"""SAM automatic mask generation, batched over prompts and images, and the `sam` segmenter back end.

The generator reproduces the official `SamAutomaticMaskGenerator` without crops
(crop_n_layers 0) or small-region clean-up (min_mask_region_area 0), which are the aerial
settings of the reference: a regular point grid prompts the decoder (multimask outputs), masks
are kept when predicted IoU > `pred_iou_thresh` and stability >= `stability_score_thresh`, and
duplicates are removed by box NMS, per image. Differences from the official code are in how, not
what: the prompts of all images go through the decoder together (each prompt carries its image
index, NMS uses the image index as category), and the official chain "bilinear to the encoder
size, crop the padding, bilinear to the image size" is applied as one precomputed separable
linear map, so the large intermediate masks are never built.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from meridian_torch.perception.neural.sam.model import Sam
from meridian_torch.perception.protocols import Segmentation

__all__ = [
    "point_grid",
    "upsampling_taps",
    "upsample_logits",
    "stability_scores",
    "mask_boxes",
    "GeneratedMasks",
    "AutomaticMaskGenerator",
    "SamSegmenter",
]

MASK_THRESHOLD = 0.0  # logit at which a pixel is inside the mask (fixed by the model)


def point_grid(points_per_side: int) -> torch.Tensor:
    """(n * n, 2) cell-centre points (x, y) in [0, 1], x fastest (the official grid order)."""
    centres = (torch.arange(points_per_side, dtype=torch.float64) + 0.5) / points_per_side
    ys, xs = torch.meshgrid(centres, centres, indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1)


def upsampling_taps(
    low_size: int, image_size: int, input_size: int, output_size: int, device: torch.device | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """One axis of the official mask upsampling as taps into the low-resolution axis.

    The official chain is: bilinear `low_size -> image_size`, keep the first `input_size`
    (drop the padding), bilinear `input_size -> output_size`. Each step is linear per axis, so
    the chain is a matrix (output_size, low_size) with at most a few non-zeros per row; it is
    built by running the chain on the identity and stored as (indices, weights), both
    (output_size, K).
    """
    eye = torch.eye(low_size, dtype=torch.float64, device=device)[None]  # channel c = basis vector c
    up = F.interpolate(eye, size=image_size, mode="linear", align_corners=False)[..., :input_size]
    operator = F.interpolate(up, size=output_size, mode="linear", align_corners=False)[0].T
    taps = int((operator != 0).sum(dim=1).max())
    indices = operator.abs().topk(taps, dim=1).indices
    return indices, operator.gather(1, indices)


def upsample_logits(
    logits: torch.Tensor, taps_h: tuple[torch.Tensor, torch.Tensor], taps_w: tuple[torch.Tensor, torch.Tensor]
) -> torch.Tensor:
    """Low-resolution logits (N, h, w) -> (N, H, W) through the separable taps of `upsampling_taps`."""
    idx_h, w_h = taps_h[0], taps_h[1].to(logits.dtype)
    idx_w, w_w = taps_w[0], taps_w[1].to(logits.dtype)
    rows = sum(w_h[:, k, None] * logits[:, idx_h[:, k], :] for k in range(idx_h.shape[1]))
    return sum(w_w[:, k] * rows[:, :, idx_w[:, k]] for k in range(idx_w.shape[1]))


def stability_scores(logits: torch.Tensor, offset: float) -> torch.Tensor:
    """(N, H, W) logits -> (N,) IoU of the masks thresholded at +offset and -offset (NaN if both empty)."""
    inner = (logits > MASK_THRESHOLD + offset).flatten(1).sum(1)
    outer = (logits > MASK_THRESHOLD - offset).flatten(1).sum(1)
    return inner / outer


def mask_boxes(masks: torch.Tensor) -> torch.Tensor:
    """(N, H, W) bool -> (N, 4) float boxes (x0, y0, x1, y1), inclusive pixel indices; zeros if empty."""
    h, w = masks.shape[-2:]
    rows, cols = masks.any(dim=2), masks.any(dim=1)  # (N, H), (N, W)
    row_idx = torch.arange(h, device=masks.device)
    col_idx = torch.arange(w, device=masks.device)
    y0 = torch.where(rows, row_idx, h).amin(dim=1)
    y1 = torch.where(rows, row_idx, -1).amax(dim=1)
    x0 = torch.where(cols, col_idx, w).amin(dim=1)
    x1 = torch.where(cols, col_idx, -1).amax(dim=1)
    boxes = torch.stack([x0, y0, x1, y1], dim=1)
    return torch.where(rows.any(dim=1)[:, None], boxes, 0).float()


@dataclass(frozen=True)
class GeneratedMasks:
    """Masks of a batch of images, padded to the largest count M, in descending predicted IoU.

    Shape:
        masks: (B, M, H, W) bool; iou_predictions, stability_scores: (B, M) float; valid: (B, M) bool.
    """

    masks: torch.Tensor
    iou_predictions: torch.Tensor
    stability_scores: torch.Tensor
    valid: torch.Tensor


class AutomaticMaskGenerator:
    """Segment everything in images with a point grid of prompts (the official generator's method).

    The settings are those of `config.perception.SamSegmenterConfig` (defaults live there).
    """

    def __init__(
        self,
        sam: Sam,
        *,
        points_per_side: int,
        points_per_batch: int,
        encoder_batch_size: int,
        pred_iou_thresh: float,
        stability_score_thresh: float,
        stability_score_offset: float,
        box_nms_thresh: float,
    ) -> None:
        self.sam = sam
        self.points_per_side = points_per_side
        self.points_per_batch = points_per_batch
        self.encoder_batch_size = encoder_batch_size
        self.pred_iou_thresh = pred_iou_thresh
        self.stability_score_thresh = stability_score_thresh
        self.stability_score_offset = stability_score_offset
        self.box_nms_thresh = box_nms_thresh

    @torch.no_grad()
    def generate(self, images: torch.Tensor) -> GeneratedMasks:
        """Images (B, 3, H, W) in [0, 1] -> masks at (H, W).

        `points_per_batch` prompts go through the decoder at a time, taken in order from the
        grids of all images, so a call may mix images. The encoder sees `encoder_batch_size`
        images at a time: a global-attention block of ViT-L holds about 2 GB per image.
        """
        from torchvision.ops import batched_nms

        b, _, h, w = images.shape
        device = images.device
        chunks = images.split(self.encoder_batch_size)
        embeddings = torch.cat([self.sam.image_encoder(self.sam.preprocess(chunk)) for chunk in chunks])
        input_h, input_w = self.sam.input_size(h, w)

        # grid points in image pixels, then in encoder-input pixels (the official coordinate path)
        points = point_grid(self.points_per_side) * torch.tensor([w, h], dtype=torch.float64)
        coords = points * torch.tensor([input_w / w, input_h / h], dtype=torch.float64)
        coords = coords.to(device, images.dtype)
        num_points = len(coords)
        low = 4 * self.sam.architecture.embedding_size
        taps_h = upsampling_taps(low, self.sam.image_size, input_h, h, device)
        taps_w = upsampling_taps(low, self.sam.image_size, input_w, w, device)

        kept_masks, kept_iou, kept_stability, kept_image = [], [], [], []
        for start in range(0, b * num_points, self.points_per_batch):
            prompt = torch.arange(start, min(start + self.points_per_batch, b * num_points), device=device)
            image_of_prompt = prompt // num_points
            low_logits, iou = self.sam.decode_points(
                embeddings[image_of_prompt],
                coords[prompt % num_points][:, None],
                torch.ones(len(prompt), 1, dtype=torch.int64, device=device),
            )
            # the multimask outputs, flattened prompt-major as the official generator does
            low_logits, iou = low_logits[:, 1:].flatten(0, 1), iou[:, 1:].flatten()
            image_of_mask = image_of_prompt.repeat_interleave(3)
            # a threshold of 0 disables its filter, as in the official generator
            keep = (iou > self.pred_iou_thresh) | (self.pred_iou_thresh <= 0)
            logits = upsample_logits(low_logits[keep], taps_h, taps_w)
            stability = stability_scores(logits, self.stability_score_offset)
            stable = (stability >= self.stability_score_thresh) | (self.stability_score_thresh <= 0)
            kept_masks.append(logits[stable] > MASK_THRESHOLD)
            kept_iou.append(iou[keep][stable])
            kept_stability.append(stability[stable])
            kept_image.append(image_of_mask[keep][stable])

        masks = torch.cat(kept_masks)
        iou = torch.cat(kept_iou)
        stability = torch.cat(kept_stability)
        image = torch.cat(kept_image)
        order = batched_nms(mask_boxes(masks), iou.float(), image, self.box_nms_thresh)  # by descending IoU
        order = order[torch.sort(image[order], stable=True).indices]  # group by image, keep IoU order
        return _pad_per_image(masks[order], iou[order], stability[order], image[order], b)


def _pad_per_image(
    masks: torch.Tensor, iou: torch.Tensor, stability: torch.Tensor, image: torch.Tensor, batch_size: int
) -> GeneratedMasks:
    """Masks sorted by image index -> padded (B, M, ...) tensors."""
    counts = torch.bincount(image, minlength=batch_size)
    m = int(counts.max()) if len(image) else 0
    first = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(image), device=image.device) - first[image]
    h, w = masks.shape[-2:]
    out_masks = masks.new_zeros(batch_size, m, h, w)
    out_iou = iou.new_zeros(batch_size, m)
    out_stability = stability.new_zeros(batch_size, m)
    valid = torch.zeros(batch_size, m, dtype=torch.bool, device=masks.device)
    out_masks[image, slot] = masks
    out_iou[image, slot] = iou
    out_stability[image, slot] = stability
    valid[image, slot] = True
    return GeneratedMasks(out_masks, out_iou, out_stability, valid)


class SamSegmenter:
    """The `sam` segmenter back end: automatic SAM masks on images shrunk by `downsample_factor`.

    As in the reference, images are first shrunk by `downsample_factor` per axis (bilinear without
    antialiasing, like its OpenCV linear resize) and SAM runs on that image (resized inside to
    the encoder's longer side); the masks are then brought back to the input resolution by
    nearest-neighbour upsampling, so each working pixel covers `downsample_factor` x
    `downsample_factor` input pixels. The factor is in pixels, as in the reference, so
    `meters_per_pixel` is not used. Scores are the predicted IoU, clipped to [0, 1].
    """

    def __init__(self, generator: AutomaticMaskGenerator, downsample_factor: float) -> None:
        self.generator = generator
        self.downsample_factor = downsample_factor

    def segment(self, images: torch.Tensor, meters_per_pixel: float | None) -> Segmentation:
        """Images (B, 3, H, W) in [0, 1] -> padded masks at (H, W)."""
        h, w = images.shape[-2:]
        sam = self.generator.sam
        sam.to(device=images.device, dtype=images.dtype)  # no-op after the first call
        working = images
        if self.downsample_factor != 1:
            size = (max(1, round(h / self.downsample_factor)), max(1, round(w / self.downsample_factor)))
            working = F.interpolate(images, size=size, mode="bilinear", align_corners=False)
        out = self.generator.generate(working)
        # nearest working pixel of every input pixel centre (a gather also works when M = 0)
        work_h, work_w = out.masks.shape[-2:]
        rows = ((torch.arange(h, device=images.device) + 0.5) * (work_h / h)).long().clamp(max=work_h - 1)
        cols = ((torch.arange(w, device=images.device) + 0.5) * (work_w / w)).long().clamp(max=work_w - 1)
        masks = out.masks[:, :, rows[:, None], cols[None, :]]
        scores = out.iou_predictions.clamp(0, 1).to(images.dtype)
        return Segmentation(masks=masks, scores=scores, valid=out.valid)

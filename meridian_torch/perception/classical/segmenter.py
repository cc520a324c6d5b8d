"""The classical segmenter: Felzenszwalb or SLIC over-segmentation, then hierarchical merging of
adjacent regions on a region adjacency graph."""

from __future__ import annotations

import cv2
import numpy as np
import torch
from skimage.segmentation import slic

from meridian_torch.core.parallel import thread_map
from meridian_torch.perception.classical.felzenszwalb import felzenszwalb
from meridian_torch.perception.classical.pixel_features import check_images
from meridian_torch.perception.classical.region_merging import colour_steps, merge_regions
from meridian_torch.perception.protocols import Segmentation

__all__ = ["ClassicalSegmenter"]


class ClassicalSegmenter:
    """Scale-aware over-segmentation plus hierarchical region-adjacency merging.

    Aerial images are resampled to `working_meters_per_pixel`; all sizes are given in metres so
    the same scene at 0.15 or 0.6 m/px yields segments of similar area. Ground frames
    (meters_per_pixel None) are resampled so their longer side is `ground_working_size_px`, each
    working pixel is treated as `working_meters_per_pixel` wide, and the minimum segment area is
    `ground_min_segment_fraction` of the frame. The returned masks partition the image: they do
    not overlap and every pixel belongs to exactly one valid mask.

    Args:
        oversegmentation: "felzenszwalb" or "slic".
        working_meters_per_pixel: resolution at which aerial images are segmented.
        ground_working_size_px: longer side of resampled ground frames.
        felzenszwalb_scale_m2: Felzenszwalb scale, square metres.
        smoothing_sigma_m: Gaussian pre-smoothing of the over-segmentation, metres.
        superpixel_size_m: SLIC superpixel side, metres.
        slic_compactness: SLIC compactness.
        merge_threshold: final merge threshold on the region dissimilarity (Lab units).
        merge_levels: number of increasing thresholds of the hierarchical merging.
        lightness_weight: weight of Lab L differences relative to a/b differences.
        texture_weight: weight of local-contrast differences.
        boundary_weight: weight of the mean colour step along the shared border.
        min_segment_area_m2: minimum aerial segment area.
        ground_min_segment_fraction: minimum ground segment area as a fraction of the frame.
    """

    def __init__(
        self,
        *,
        oversegmentation: str,
        working_meters_per_pixel: float,
        ground_working_size_px: int,
        felzenszwalb_scale_m2: float,
        smoothing_sigma_m: float,
        superpixel_size_m: float,
        slic_compactness: float,
        merge_threshold: float,
        merge_levels: int,
        lightness_weight: float,
        texture_weight: float,
        boundary_weight: float,
        min_segment_area_m2: float,
        ground_min_segment_fraction: float,
    ) -> None:
        if oversegmentation not in ("felzenszwalb", "slic"):
            raise ValueError(f"oversegmentation must be 'felzenszwalb' or 'slic', got {oversegmentation!r}")
        self.oversegmentation = oversegmentation
        self.working_mpp = working_meters_per_pixel
        self.ground_working_size_px = ground_working_size_px
        self.felzenszwalb_scale_m2 = felzenszwalb_scale_m2
        self.smoothing_sigma_m = smoothing_sigma_m
        self.superpixel_size_m = superpixel_size_m
        self.slic_compactness = slic_compactness
        self.merge_threshold = merge_threshold
        self.merge_levels = merge_levels
        self.lightness_weight = lightness_weight
        self.texture_weight = texture_weight
        self.boundary_weight = boundary_weight
        self.min_segment_area_m2 = min_segment_area_m2
        self.ground_min_segment_fraction = ground_min_segment_fraction

    @torch.no_grad()
    def segment(self, images: torch.Tensor, meters_per_pixel: float | None = None) -> Segmentation:
        """Segment (B, 3, H, W) images in [0, 1]; see the class docstring for the scale handling."""
        check_images(images)
        if meters_per_pixel is not None and not meters_per_pixel > 0:
            raise ValueError(f"meters_per_pixel must be positive or None, got {meters_per_pixel}")
        bsz, _, h, w = images.shape
        rgb = images.detach().to("cpu", torch.float32).clamp(0, 1).permute(0, 2, 3, 1).numpy()
        labels, scores = zip(*thread_map(lambda i: self._segment_one(rgb[i], meters_per_pixel), range(bsz)),
                             strict=True)
        counts = [len(s) for s in scores]
        m = max(counts)
        label_t = torch.from_numpy(np.stack(labels)).to(images.device)
        # One-hot masks by scattering each pixel's label: a fraction of the cost of comparing
        # every pixel with every label.
        masks = torch.zeros(bsz, m, h, w, dtype=torch.bool, device=images.device)
        masks.view(bsz, m, h * w).scatter_(1, label_t.view(bsz, 1, h * w), True)
        valid = torch.arange(m, device=images.device)[None, :] < torch.tensor(counts, device=images.device)[:, None]
        score_t = torch.zeros(bsz, m, dtype=images.dtype, device=images.device)
        for i, s in enumerate(scores):
            score_t[i, : len(s)] = torch.from_numpy(s).to(score_t)
        return Segmentation(masks=masks, scores=score_t, valid=valid, labels=label_t)

    def _working_geometry(self, h: int, w: int, mpp: float | None) -> tuple[int, int, float]:
        """Working (height, width) and minimum segment area in working pixels."""
        if mpp is None:
            f = self.ground_working_size_px / max(h, w)
            wh, ww = max(1, round(h * f)), max(1, round(w * f))
            return wh, ww, self.ground_min_segment_fraction * wh * ww
        f = mpp / self.working_mpp
        wh, ww = max(1, round(h * f)), max(1, round(w * f))
        return wh, ww, self.min_segment_area_m2 / self.working_mpp**2

    def _segment_one(self, rgb: np.ndarray, mpp: float | None) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) float32 RGB -> ((H, W) int64 labels 0..M-1, (M,) float32 scores)."""
        h, w = rgb.shape[:2]
        wh, ww, min_px = self._working_geometry(h, w, mpp)
        shrink = wh * ww < h * w
        work = cv2.resize(rgb, (ww, wh), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        work = np.ascontiguousarray(work, dtype=np.float32)
        labels, scores = self._segment_working(work, min_px)
        full = cv2.resize(labels.astype(np.int32), (w, h), interpolation=cv2.INTER_NEAREST).astype(np.int64)
        # Nearest upsampling can drop a one-pixel region entirely; renumber to keep labels dense.
        present = np.flatnonzero(np.bincount(full.ravel(), minlength=len(scores)))  # np.unique without a sort
        if len(present) < len(scores):
            remap = np.zeros(len(scores), dtype=np.int64)
            remap[present] = np.arange(len(present))
            full, scores = remap[full], scores[present]
        return full, scores

    def _oversegment(self, rgb: np.ndarray, lab: np.ndarray, min_px: float) -> np.ndarray:
        px = self.working_mpp
        sigma = self.smoothing_sigma_m / px
        if self.oversegmentation == "felzenszwalb":
            # Lab/100 keeps the edge weights in a fixed, perceptual range; min_size keeps the
            # initial graph small without deciding anything the merging should decide. Our
            # compiled Felzenszwalb returns skimage's labels bit for bit in a third of its time.
            return felzenszwalb(
                lab / 100.0,
                scale=self.felzenszwalb_scale_m2 / px**2,
                sigma=sigma,
                min_size=max(4, int(min_px // 4)),
            )
        n = max(1, round(rgb.shape[0] * rgb.shape[1] * px**2 / self.superpixel_size_m**2))
        return slic(
            rgb, n_segments=n, compactness=self.slic_compactness, sigma=sigma, start_label=0, channel_axis=-1
        )

    def _segment_working(self, rgb: np.ndarray, min_px: float) -> tuple[np.ndarray, np.ndarray]:
        lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab)
        labels = self._oversegment(rgb, lab, min_px).astype(np.int64)
        # Local contrast = std of L over ~3x3 working pixels (about 1 m for aerial images).
        mean_l = cv2.blur(lab[..., 0], (3, 3))
        contrast = np.sqrt(np.maximum(cv2.blur(lab[..., 0] ** 2, (3, 3)) - mean_l**2, 0))
        feats = np.concatenate([lab, contrast[..., None]], axis=-1).astype(np.float64)
        smooth = cv2.GaussianBlur(lab, (0, 0), 0.7)
        wl = np.array([self.lightness_weight, 1.0, 1.0], dtype=np.float32)
        step_h, step_v = colour_steps(smooth, wl)
        lut, edges, weight, border_len = merge_regions(
            labels, feats, step_h, step_v, self.lightness_weight, self.texture_weight, self.boundary_weight,
            self.merge_threshold, self.merge_levels, min_px,
        )
        return lut[labels], self._scores(int(lut.max()) + 1, edges, weight, border_len)

    def _scores(self, n: int, edges: np.ndarray, weight: np.ndarray, length: np.ndarray) -> np.ndarray:
        """Border contrast per region in [0, 1): 1 - exp(-mean neighbour dissimilarity / threshold)."""
        if len(edges) == 0:
            return np.ones(n, dtype=np.float32)
        num = np.bincount(edges.ravel(), weights=np.repeat(weight * length, 2), minlength=n)
        den = np.bincount(edges.ravel(), weights=np.repeat(length, 2), minlength=n)
        return (1.0 - np.exp(-num / np.maximum(den, 1e-9) / self.merge_threshold)).astype(np.float32)

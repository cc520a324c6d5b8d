"""Classical perception back ends: partition masks, scale awareness, descriptors, batching, device/dtype."""

from __future__ import annotations

import pytest
import torch
from pydantic import ValidationError

from meridian_torch.config.perception import DescriptorConfig, GlobalDescriptorConfig, SegmenterConfig
from meridian_torch.perception.classical.describers import (
    masked_mean,
)
from meridian_torch.perception.classical.segmenter import ClassicalSegmenter
from meridian_torch.perception.factory import build_global_describer, build_segment_describer, build_segmenter
from meridian_torch.perception.protocols import GlobalDescriber, SegmentDescriber, Segmenter

SCENE_M = 48.0
# (centre x m, centre y m, radius m, RGB): a tree-green, a car-red, a roof-brown and a pond-blue disc.
DISCS = [
    (12.0, 12.0, 4.0, (0.15, 0.38, 0.12)),
    (34.0, 14.0, 3.0, (0.70, 0.12, 0.10)),
    (14.0, 34.0, 5.0, (0.55, 0.35, 0.30)),
    (35.0, 35.0, 4.0, (0.10, 0.20, 0.45)),
]
BACKGROUND = ((0.35, 0.52, 0.22), (0.32, 0.32, 0.34))  # grass left, asphalt right


def scene(meters_per_pixel: float, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(3, H, W) image of the disc scene at the given resolution, and (K, H, W) disc masks."""
    n = round(SCENE_M / meters_per_pixel)
    c = (torch.arange(n, dtype=torch.float64) + 0.5) * meters_per_pixel
    y, x = torch.meshgrid(c, c, indexing="ij")
    img = torch.empty(3, n, n, dtype=torch.float64)
    left = x < SCENE_M / 2
    for ch in range(3):
        img[ch] = torch.where(left, BACKGROUND[0][ch], BACKGROUND[1][ch])
    discs = []
    for cx, cy, r, rgb in DISCS:
        m = (x - cx) ** 2 + (y - cy) ** 2 <= r**2
        img[:, m] = torch.tensor(rgb, dtype=torch.float64)[:, None]
        discs.append(m)
    gen = torch.Generator().manual_seed(seed)
    img = img + 0.015 * torch.randn(img.shape, generator=gen, dtype=torch.float64)
    return img.clamp(0, 1).float(), torch.stack(discs)


def iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(K, H, W) x (M, H, W) bool -> (K, M) IoU."""
    a, b = a.flatten(1).float(), b.flatten(1).float()
    inter = a @ b.T
    return inter / (a.sum(1)[:, None] + b.sum(1)[None] - inter)


@pytest.fixture(scope="module")
def segmenter() -> ClassicalSegmenter:
    return build_segmenter(SegmenterConfig(backend="classical"))


@pytest.mark.parametrize("meters_per_pixel", [0.15, 0.4])
def test_one_segment_per_disc_at_two_scales(segmenter: ClassicalSegmenter, meters_per_pixel: float) -> None:
    img, discs = scene(meters_per_pixel)
    seg = segmenter.segment(img[None], meters_per_pixel)
    masks = seg.masks[0, seg.valid[0]]
    assert iou(discs, masks).max(dim=1).values.min() > 0.8
    # Both background halves survive as segments too (a sparse scene gives few segments).
    assert 6 <= len(masks) <= 10


def test_masks_partition_the_image(segmenter: ClassicalSegmenter) -> None:
    img, _ = scene(0.3)
    seg = segmenter.segment(img[None], 0.3)
    assert seg.masks.dtype == torch.bool and seg.valid.dtype == torch.bool
    assert seg.masks.shape[-2:] == img.shape[-2:]
    cover = seg.masks[0].sum(0)
    assert torch.equal(cover, torch.ones_like(cover))  # no overlap, nothing left out
    assert not seg.masks[0, ~seg.valid[0]].any()
    assert ((seg.scores >= 0) & (seg.scores <= 1)).all()
    assert torch.equal(seg.labels[0], seg.masks[0].to(torch.uint8).argmax(0))  # each pixel's mask
    assert int(seg.labels.max()) < int(seg.valid[0].sum())  # valid masks come first


def test_ground_frame_without_scale(segmenter: ClassicalSegmenter) -> None:
    img, _ = scene(0.3)
    frame = torch.nn.functional.interpolate(img[None], size=(90, 160), mode="bilinear", align_corners=False)
    seg = segmenter.segment(frame, None)
    assert seg.masks.shape[-2:] == (90, 160)
    assert torch.equal(seg.masks[0].sum(0), torch.ones(90, 160, dtype=torch.long))
    assert int(seg.valid.sum()) >= 4


def test_batch_equals_single_images(segmenter: ClassicalSegmenter) -> None:
    imgs = torch.stack([scene(0.5, seed=s)[0] for s in range(3)])
    imgs[1] = imgs[1].flip(-1)  # a different layout, so segment counts differ across the batch
    seg = segmenter.segment(imgs, 0.5)
    describer = build_segment_describer(DescriptorConfig(backend="classical"))
    desc = describer.describe(imgs, seg.masks, seg.valid)
    for i in range(3):
        one = segmenter.segment(imgs[i : i + 1], 0.5)
        m = int(one.valid.sum())
        assert torch.equal(seg.valid[i], torch.arange(seg.valid.shape[1]) < m)
        assert torch.equal(seg.masks[i, :m], one.masks[0])
        assert torch.equal(seg.scores[i, :m], one.scores[0])
        single = describer.describe(imgs[i : i + 1], one.masks, one.valid)[0]
        torch.testing.assert_close(desc[i, :m], single, atol=1e-5, rtol=1e-5)
        assert not desc[i, m:].any()


def test_masked_mean_equals_loop() -> None:
    gen = torch.Generator().manual_seed(0)
    feats = torch.rand(5, 12, 16, generator=gen, dtype=torch.float64)
    masks = torch.rand(4, 12, 16, generator=gen) > 0.6
    masks[3] = False  # an empty mask pools to zeros
    buffer = torch.full((4, 12, 16), float("nan"), dtype=torch.float64)  # stale contents must not leak
    for mask_buffer in (None, buffer):
        mean, area = masked_mean(feats, masks, mask_buffer)
        for m in range(4):
            sel = feats[:, masks[m]]
            expected = sel.mean(dim=1) if sel.shape[1] else torch.zeros(5, dtype=torch.float64)
            torch.testing.assert_close(mean[m], expected)
            assert area[m] == masks[m].sum()


def test_descriptors_unit_norm_and_colour_similarity(segmenter: ClassicalSegmenter) -> None:
    img, discs = scene(0.3)
    # Two dark-green discs of different brightness (sunlit vs shaded canopy), one red, one grey.
    x = img.clone()
    x[:, discs[1]] = x[:, discs[0]].mean(dim=1, keepdim=True) * 1.6  # same chromaticity, brighter
    masks = torch.stack([discs[0], discs[1], discs[2], torch.zeros_like(discs[0])])[None]
    valid = torch.tensor([[True, True, True, True]])
    masks[0, 2] = (x[1] < 0.34) & (x[0] < 0.34) & ~discs.any(0) & (torch.arange(x.shape[-1]) >= x.shape[-1] // 2)
    describer = build_segment_describer(DescriptorConfig(backend="classical"))
    d = describer.describe(x[None], masks, valid)[0]
    assert d.shape == (4, describer.dim)
    torch.testing.assert_close(d[:3].norm(dim=1), torch.ones(3))
    assert not d[3].any()  # empty mask -> zeros
    same = d[0] @ d[1]
    assert same > 0.9
    assert same > d[0] @ d[2] + 0.3


def test_global_descriptor_and_factories() -> None:
    seg = build_segmenter(SegmenterConfig())
    desc = build_segment_describer(DescriptorConfig())
    glob = build_global_describer(GlobalDescriptorConfig(pyramid_levels=2))
    assert isinstance(seg, Segmenter) and isinstance(desc, SegmentDescriber) and isinstance(glob, GlobalDescriber)
    imgs = torch.stack([scene(0.4, seed=s)[0] for s in range(2)])
    g = glob.describe(imgs)
    assert g.shape == (2, glob.dim) and glob.dim == 5 * desc.dim
    torch.testing.assert_close(g.norm(dim=1), torch.ones(2))
    assert g[0] @ g[1] > 0.95  # same scene, different noise
    with pytest.raises(ValidationError):
        SegmenterConfig.model_validate({"backend": "classical", "unknown": 1})
    with pytest.raises(ValueError):
        seg.segment(torch.rand(1, 4, 8, 8), 0.3)


def test_global_descriptor_batch_equals_single_images_and_a_batched_reference() -> None:
    glob = build_global_describer(GlobalDescriptorConfig(pyramid_levels=3))
    imgs = torch.stack([scene(0.4, seed=s)[0] for s in range(3)]).float()
    imgs[1] = imgs[1].flip(-1)
    batch = glob.describe(imgs)
    for i in range(3):  # one image at a time inside, so a batch changes no bit
        assert torch.equal(batch[i], glob.describe(imgs[i : i + 1])[0])
    # the definition, on the whole batch: GeM pooling over a 1 + 4 + 16 cell pyramid
    feats = glob.features(imgs).clamp(min=1e-6) ** glob.gem_p
    cells = torch.cat([
        (torch.nn.functional.adaptive_avg_pool2d(feats, 2**level) ** (1 / glob.gem_p)).flatten(2).transpose(1, 2)
        for level in range(3)
    ], dim=1)
    colour, texture = cells[..., : glob.features.colour_channels], cells[..., glob.features.colour_channels :]
    blocks = [torch.nn.functional.normalize(x - x.mean(dim=-1, keepdim=True), dim=-1) for x in (colour, texture)]
    joined = torch.cat([glob.colour_weight * blocks[0], glob.texture_weight * blocks[1]], dim=-1)
    expected = torch.nn.functional.normalize(torch.nn.functional.normalize(joined, dim=-1).flatten(1), dim=-1)
    torch.testing.assert_close(batch, expected, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]
)
def test_device_and_dtype_follow_input(segmenter: ClassicalSegmenter, device: str, dtype: torch.dtype) -> None:
    img = scene(0.5)[0].to(device, dtype)[None]
    seg = segmenter.segment(img, 0.5)
    assert seg.masks.device == img.device and seg.valid.device == img.device
    assert seg.scores.dtype == dtype and seg.scores.device == img.device
    d = build_segment_describer(DescriptorConfig(backend="classical")).describe(img, seg.masks, seg.valid)
    g = build_global_describer(GlobalDescriptorConfig(backend="classical")).describe(img)
    assert d.dtype == dtype and d.device == img.device
    assert g.dtype == dtype and g.device == img.device


@pytest.mark.parametrize("sigma", [0.7, 1.0, 3.0])
def test_shift_and_add_blur_equals_a_depthwise_convolution(sigma: float) -> None:
    """The blur's tap loop against the textbook separable convolution (replicate padding)."""
    import math

    import torch.nn.functional as F

    from meridian_torch.perception.classical.pixel_features import _gaussian_blur

    x = torch.rand(3, 2, 23, 31, generator=torch.Generator().manual_seed(1))
    r = max(1, math.ceil(3 * sigma))
    t = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    ref = F.pad(x, (r, r, r, r), mode="replicate")
    ref = F.conv2d(ref, k.view(1, 1, 1, -1).expand(2, 1, 1, -1), groups=2)
    ref = F.conv2d(ref, k.view(1, 1, -1, 1).expand(2, 1, -1, 1), groups=2)
    torch.testing.assert_close(_gaussian_blur(x, sigma), ref, atol=1e-6, rtol=0)


@pytest.mark.parametrize("circular", [True, False])
def test_soft_bins_equal_a_per_bin_loop(circular: bool) -> None:
    from meridian_torch.perception.classical.pixel_features import _soft_bins

    bins = 5
    value = torch.rand(2, 7, 9, generator=torch.Generator().manual_seed(2)) * (bins if circular else bins - 1)
    want = torch.zeros(2, bins, 7, 9)
    for c in range(bins):
        d = (value - c).abs()
        if circular:
            d = torch.minimum(d, bins - d)
        want[:, c] = (1 - d / 1.5).clamp(min=0)
    want /= want.sum(dim=1, keepdim=True)
    torch.testing.assert_close(_soft_bins(value, bins, circular), want, atol=1e-6, rtol=0)
    out = torch.empty(2, bins + 3, 7, 9)
    _soft_bins(value, bins, circular, out=out[:, 1 : bins + 1])
    torch.testing.assert_close(out[:, 1 : bins + 1], want, atol=1e-6, rtol=0)

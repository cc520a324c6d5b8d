"""Segment Anything back end: official checkpoint layout, equality with the official
`segment-anything` package (a test-only reference) on shared random weights, and the segmenter."""

from __future__ import annotations

import dataclasses
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from meridian_torch.config.perception import SegmenterConfig
from meridian_torch.errors import ConfigError, ModelWeightsError
from meridian_torch.perception.factory import build_segmenter
from meridian_torch.perception.neural.sam.automatic import (
    AutomaticMaskGenerator,
    mask_boxes,
    point_grid,
    upsample_logits,
    upsampling_taps,
)
from meridian_torch.perception.neural.sam.model import (
    SAM_ARCHITECTURES,
    SamArchitecture,
    SamImageEncoderExport,
    SamPromptDecoderExport,
    build_sam,
    load_sam,
    resize_8bit,
)
from meridian_torch.perception.protocols import Segmenter

segment_anything = pytest.importorskip("segment_anything")
from segment_anything import SamAutomaticMaskGenerator  # noqa: E402
from segment_anything.modeling import (  # noqa: E402
    ImageEncoderViT,
    MaskDecoder,
    PromptEncoder,
    Sam,
    TwoWayTransformer,
)

TINY = SAM_ARCHITECTURES["tiny"]
NO_FILTERS = dict(pred_iou_thresh=0.0, stability_score_thresh=0.0)  # 0 disables both, as in the official code


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    # Tiny models gain nothing from threads, and on a shared loaded machine thread
    # oversubscription made these tests ~10x slower.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _official_sam(a: SamArchitecture) -> Sam:
    """The official model with the sizes of `a` (as the official `_build_sam` wires them)."""
    e = a.embedding_size
    return Sam(
        image_encoder=ImageEncoderViT(
            depth=a.encoder_depth,
            embed_dim=a.encoder_embed_dim,
            img_size=a.image_size,
            mlp_ratio=4,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6),
            num_heads=a.encoder_num_heads,
            patch_size=a.patch_size,
            qkv_bias=True,
            use_rel_pos=True,
            global_attn_indexes=a.encoder_global_attn_indexes,
            window_size=a.encoder_window_size,
            out_chans=a.prompt_embed_dim,
        ),
        prompt_encoder=PromptEncoder(
            embed_dim=a.prompt_embed_dim,
            image_embedding_size=(e, e),
            input_image_size=(a.image_size, a.image_size),
            mask_in_chans=a.mask_in_chans,
        ),
        mask_decoder=MaskDecoder(
            num_multimask_outputs=3,
            transformer=TwoWayTransformer(
                depth=a.decoder_depth,
                embedding_dim=a.prompt_embed_dim,
                mlp_dim=a.decoder_mlp_dim,
                num_heads=a.decoder_num_heads,
            ),
            transformer_dim=a.prompt_embed_dim,
            iou_head_depth=3,
            iou_head_hidden_dim=a.iou_head_hidden_dim,
        ),
    ).eval()


@pytest.fixture(scope="module")
def official() -> Sam:
    """Tiny official SAM with random weights; the state dict is the official layout by construction."""
    torch.manual_seed(0)
    model = _official_sam(TINY)
    with torch.no_grad():
        # Default init gives nearly prompt-independent masks; a stronger decoder and point
        # embeddings make masks, scores and stabilities differ between prompts.
        for name, tensor in model.state_dict().items():
            if name.startswith("mask_decoder") and tensor.ndim >= 2:
                tensor.mul_(10**0.5)
            if "point_embeddings" in name or "not_a_point_embed" in name:
                tensor.mul_(10.0)
    return model


@pytest.fixture(scope="module")
def checkpoint(official: Sam, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("sam") / "sam_tiny.pth"
    torch.save(official.state_dict(), path)
    return path


@pytest.fixture(scope="module")
def ours(checkpoint: Path):
    return load_sam("tiny", checkpoint, None)


def _images(seed: int, count: int, h: int = 96, w: int = 128) -> np.ndarray:
    """(count, h, w, 3) uint8 images of 6 x 8 coloured blocks with noise."""
    rng = np.random.default_rng(seed)
    blocks = rng.integers(0, 256, (count, 6, 8, 3))
    images = blocks[:, np.arange(h) * 6 // h][:, :, np.arange(w) * 8 // w]
    return np.clip(images + rng.integers(-20, 21, (count, h, w, 3)), 0, 255).astype(np.uint8)


def _to_tensor(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0


# --- weights -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["vit_b", "vit_l", "vit_h", "tiny"])
def test_state_dict_layout_equals_official(name: str) -> None:
    # Key names and shapes of the official model (built on the meta device: no memory, no time).
    with torch.device("meta"):
        reference = _official_sam(SAM_ARCHITECTURES[name]).state_dict()
        mine = build_sam(name).state_dict()
    assert {k: tuple(v.shape) for k, v in mine.items()} == {k: tuple(v.shape) for k, v in reference.items()}


def test_official_checkpoint_loads_strictly(official: Sam, ours, checkpoint: Path) -> None:
    mine = ours.state_dict()
    assert all(torch.equal(mine[k], v) for k, v in official.state_dict().items())
    assert sum(p.numel() for p in ours.parameters()) == sum(p.numel() for p in official.parameters())


def test_missing_weights_file_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "sam_vit_l_0b3195.pth"
    with pytest.raises(ModelWeightsError, match="sam_vit_l_0b3195.pth"):
        load_sam("tiny", missing, None)


def test_checkpoint_of_another_architecture_is_rejected(official: Sam, tmp_path: Path) -> None:
    state = dict(official.state_dict())
    del state["mask_decoder.iou_token.weight"]
    path = tmp_path / "broken.pth"
    torch.save(state, path)
    missing_key = r"broken\.pth.*missing keys: mask_decoder\.iou_token\.weight"
    with pytest.raises(ModelWeightsError, match=missing_key):
        load_sam("tiny", path, None)
    torch.save(official.state_dict(), path)
    with pytest.raises(ModelWeightsError, match=r"broken\.pth.*wrong shapes: image_encoder\."):
        load_sam(dataclasses.replace(TINY, encoder_embed_dim=64), path, None)


# --- model equality --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("in_hw", "out_hw"), [((60, 80), (96, 128)), ((150, 200), (96, 128)), ((7, 5), (128, 91))]
)
def test_resize_8bit_equals_pillow(in_hw: tuple[int, int], out_hw: tuple[int, int]) -> None:
    from torchvision.transforms.functional import resize, to_pil_image

    image = _images(0, 1, *in_hw)[0]
    expected = np.array(resize(to_pil_image(image), list(out_hw)))
    actual = resize_8bit(torch.from_numpy(image).permute(2, 0, 1)[None].float(), out_hw)
    np.testing.assert_array_equal(actual[0].permute(1, 2, 0).numpy(), expected)


@pytest.mark.parametrize("hw", [(96, 128), (60, 80), (150, 200)])
def test_preprocess_equals_official_predictor(official: Sam, ours, hw: tuple[int, int]) -> None:
    from segment_anything import SamPredictor

    image = _images(1, 1, *hw)[0]
    predictor = SamPredictor(official)
    predictor.set_image(image)  # resizes the longer side to the encoder size, normalizes, pads
    with torch.no_grad():
        actual = ours.image_encoder(ours.preprocess(_to_tensor(image[None])))
    assert ours.input_size(*hw) == predictor.input_size
    torch.testing.assert_close(actual, predictor.features, rtol=1e-4, atol=1e-5)


def test_image_embeddings_equal_official(official: Sam, ours) -> None:
    x = torch.randn(2, 3, TINY.image_size, TINY.image_size, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        expected = official.image_encoder(x)
        actual = SamImageEncoderExport(ours)(x)
    assert actual.shape == (2, TINY.prompt_embed_dim, TINY.embedding_size, TINY.embedding_size)
    torch.testing.assert_close(actual, expected, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("multimask", [True, False])
def test_masks_and_iou_equal_official(official: Sam, ours, multimask: bool) -> None:
    g = torch.Generator().manual_seed(2)
    embeddings = torch.randn(2, TINY.prompt_embed_dim, TINY.embedding_size, TINY.embedding_size, generator=g)
    coords = torch.rand(6, 3, 2, generator=g) * TINY.image_size
    labels = torch.randint(0, 2, (6, 3), generator=g)
    image_of_prompt = torch.tensor([0, 0, 1, 1, 1, 0])
    decoder = SamPromptDecoderExport(ours, multimask_output=multimask)
    with torch.no_grad():
        # ours: prompts of both images in one call; official: one image at a time
        masks, iou = decoder(embeddings[image_of_prompt], coords, labels)
        for image in range(2):
            sel = image_of_prompt == image
            sparse, dense = official.prompt_encoder(points=(coords[sel], labels[sel]), boxes=None, masks=None)
            ref_masks, ref_iou = official.mask_decoder(
                embeddings[image : image + 1],
                official.prompt_encoder.get_dense_pe(),
                sparse,
                dense,
                multimask,
            )
            # float32 rounding differs (fused attention), so the tolerance follows the logit scale
            scale = float(ref_masks.abs().max())
            torch.testing.assert_close(masks[sel], ref_masks, rtol=0, atol=1e-5 * scale)
            torch.testing.assert_close(iou[sel], ref_iou, rtol=0, atol=1e-5 * float(ref_iou.abs().max()))
    assert masks.shape == (6, 3 if multimask else 1, 4 * TINY.embedding_size, 4 * TINY.embedding_size)


# --- generator pieces against obvious implementations -----------------------------------------


def test_point_grid_equals_official() -> None:
    from segment_anything.utils.amg import build_point_grid

    np.testing.assert_allclose(point_grid(5).numpy(), build_point_grid(5), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("input_hw", "output_hw"), [((96, 128), (96, 128)), ((96, 128), (37, 50)), ((128, 71), (300, 166))]
)
def test_upsampling_taps_equal_interpolation_chain(
    input_hw: tuple[int, int], output_hw: tuple[int, int]
) -> None:
    low = torch.randn(5, 32, 32, generator=torch.Generator().manual_seed(3))
    # the official postprocessing: to the encoder size, drop the padding, to the output size
    full = F.interpolate(low[:, None], (128, 128), mode="bilinear", align_corners=False)
    full = full[..., : input_hw[0], : input_hw[1]]
    expected = F.interpolate(full, output_hw, mode="bilinear", align_corners=False)[:, 0]
    taps_h = upsampling_taps(32, 128, input_hw[0], output_hw[0])
    taps_w = upsampling_taps(32, 128, input_hw[1], output_hw[1])
    torch.testing.assert_close(upsample_logits(low, taps_h, taps_w), expected, rtol=0, atol=1e-5)


def test_mask_boxes_equal_loop() -> None:
    masks = torch.rand(20, 17, 23, generator=torch.Generator().manual_seed(4)) > 0.97
    masks[3] = False
    for i, mask in enumerate(masks):
        rows, cols = np.nonzero(mask.numpy())
        expected = [0, 0, 0, 0] if len(rows) == 0 else [cols.min(), rows.min(), cols.max(), rows.max()]
        assert mask_boxes(masks)[i].tolist() == expected
    assert mask_boxes(masks[:0]).shape == (0, 4)


# --- automatic generator against the official one --------------------------------------------


def _official_records(official: Sam, image: np.ndarray, settings: dict) -> list[dict]:
    return SamAutomaticMaskGenerator(official, **settings).generate(image)


def _assert_same_masks(out, b: int, records: list[dict]) -> None:
    """The masks of image b equal the official records as a set (matched in predicted-IoU order).

    Our upsampling applies the official interpolation chain as one precomputed map, so logits
    differ by float32 rounding (~1e-6); a pixel whose logit sits that close to 0 or to +-offset
    may flip, which moves a stability score by one pixel's share. Hence the small tolerances.
    """
    valid = out.valid[b]
    assert int(valid.sum()) == len(records)
    order = np.argsort([-r["predicted_iou"] for r in records], kind="stable")
    ref_masks = np.stack([records[i]["segmentation"] for i in order])
    ref_iou = np.array([records[i]["predicted_iou"] for i in order])
    ref_stability = np.array([records[i]["stability_score"] for i in order])
    np.testing.assert_allclose(out.iou_predictions[b][valid].numpy(), ref_iou, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out.stability_scores[b][valid].numpy(), ref_stability, rtol=0, atol=1e-3)
    mismatched = (out.masks[b][valid].numpy() != ref_masks).sum(axis=(1, 2))
    assert (mismatched <= 0.001 * ref_masks[0].size).all(), mismatched
    assert not out.masks[b][~valid].any()


def test_generator_equals_official_without_filters(official: Sam, ours) -> None:
    images = _images(5, 2)
    # without filters, so box NMS alone reduces the 3 * 36 masks to a few
    settings = dict(
        points_per_side=6, points_per_batch=10, box_nms_thresh=0.95, stability_score_offset=1.0, **NO_FILTERS
    )
    # batch of two images encoded together; 10 prompts per call, so calls mix the images
    out = AutomaticMaskGenerator(ours, encoder_batch_size=2, **settings).generate(_to_tensor(images))
    for b in range(2):
        records = _official_records(official, images[b], settings)
        assert 1 < len(records) < 3 * 36 / 4
        _assert_same_masks(out, b, records)


def test_generator_equals_official_with_filters(official: Sam, ours) -> None:
    images = _images(6, 2, 60, 80)  # upsampled to the encoder size, like shrunk aerial images
    unfiltered = dict(
        points_per_side=6, points_per_batch=16, box_nms_thresh=1.0, stability_score_offset=1.0, **NO_FILTERS
    )
    everything = _official_records(official, images[0], unfiltered)
    assert len(everything) == 3 * 36  # no filter and no suppression keeps every multimask output
    # thresholds inside the observed ranges, so each filter removes some masks but not all
    iou_thresh = float(np.median([r["predicted_iou"] for r in everything]))
    stability = np.array([r["stability_score"] for r in everything])
    stability_thresh = float(np.median(stability[np.isfinite(stability) & (stability > 0)]))
    settings = dict(unfiltered, pred_iou_thresh=iou_thresh, stability_score_thresh=stability_thresh)
    out = AutomaticMaskGenerator(ours, encoder_batch_size=1, **settings).generate(_to_tensor(images))
    for b in range(2):
        records = _official_records(official, images[b], settings)
        assert 1 < len(records) < len(everything) / 2  # each filter alone removes about half
        assert all(r["predicted_iou"] > iou_thresh for r in records)
        assert all(r["stability_score"] >= stability_thresh for r in records)
        _assert_same_masks(out, b, records)


# --- the segmenter back end ------------------------------------------------------------------


def _sam_config(**overrides) -> SegmenterConfig:
    block = dict(architecture="tiny", random_weights_seed=0, points_per_side=6, **NO_FILTERS)
    return SegmenterConfig(backend="sam", sam={**block, **overrides})


def test_segmenter_returns_masks_at_input_size(checkpoint: Path) -> None:
    cfg = _sam_config(random_weights_seed=None, weights_path=str(checkpoint), downsample_factor=2.0)
    segmenter = build_segmenter(cfg)
    assert isinstance(segmenter, Segmenter)
    images = _to_tensor(_images(7, 2, 96, 128))
    images = F.interpolate(images, size=(192, 256), mode="nearest")
    seg = segmenter.segment(images, 0.1)
    assert seg.masks.shape[:2] == seg.valid.shape == seg.scores.shape
    assert seg.masks.shape[-2:] == (192, 256) and seg.masks.dtype == torch.bool
    assert bool(seg.valid.any()) and not seg.masks[~seg.valid].any()
    assert ((seg.scores >= 0) & (seg.scores <= 1)).all() and (seg.scores[~seg.valid] == 0).all()
    # each mask is the generator's mask on the half-size image, every working pixel a 2x2 block
    half = F.interpolate(images, size=(96, 128), mode="bilinear", align_corners=False)
    working = segmenter.generator.generate(half)
    torch.testing.assert_close(seg.masks[:, :, ::2, ::2], working.masks)
    torch.testing.assert_close(seg.masks[:, :, 1::2, 1::2], working.masks)


def test_segmenter_without_weights_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="segmenter.sam"):
        build_segmenter(_sam_config(random_weights_seed=None))


def test_default_generator_settings_are_the_reference_aerial_values() -> None:
    cfg = SegmenterConfig().sam
    assert (cfg.architecture, cfg.points_per_side, cfg.points_per_batch) == ("vit_l", 32, 64)
    assert (cfg.pred_iou_thresh, cfg.stability_score_thresh) == (0.85, 0.85)
    assert (cfg.box_nms_thresh, cfg.stability_score_offset, cfg.downsample_factor) == (0.7, 1.0, 5.0)


def test_segmenter_with_nothing_kept_returns_empty_padding() -> None:
    segmenter = build_segmenter(_sam_config(pred_iou_thresh=1e9))
    seg = segmenter.segment(torch.rand(2, 3, 50, 70, generator=torch.Generator().manual_seed(8)), None)
    assert seg.masks.shape == (2, 0, 50, 70) and seg.scores.shape == seg.valid.shape == (2, 0)
    assert seg.num_segments.tolist() == [0, 0]

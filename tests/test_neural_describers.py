"""DINOv2 describers: batched mask pooling against upsample-then-average, factory wiring, model sharing."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from meridian_torch.config.perception import DescriptorConfig, GlobalDescriptorConfig
from meridian_torch.errors import ConfigError, ModelWeightsError
from meridian_torch.perception.factory import build_global_describer, build_segment_describer
from meridian_torch.perception.neural.describers import bilinear_upsampling_matrix, masked_feature_pool
from meridian_torch.perception.protocols import GlobalDescriber, SegmentDescriber

TINY = {"architecture": "tiny", "random_weights_seed": 0}


def pool_loop(features: torch.Tensor, masks: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Upsample the features to the mask resolution, then average each mask's pixels (the reference)."""
    up = F.interpolate(features, size=masks.shape[-2:], mode="bilinear", align_corners=False)
    out = torch.zeros(*masks.shape[:2], features.shape[1], dtype=features.dtype)
    for b in range(masks.shape[0]):
        for m in range(masks.shape[1]):
            if valid[b, m] and masks[b, m].any():
                out[b, m] = F.normalize(up[b][:, masks[b, m]].mean(dim=1), dim=0)
    return out


@pytest.mark.parametrize(("grid", "image"), [((4, 6), (56, 84)), ((5, 7), (33, 101)), ((3, 3), (3, 3))])
def test_masked_pool_equals_upsample_then_average(grid, image) -> None:
    g = torch.Generator().manual_seed(0)
    features = torch.randn(2, 6, *grid, generator=g, dtype=torch.float64)
    masks = torch.rand(2, 5, *image, generator=g) > 0.7
    masks[1, 2] = False  # an empty mask
    valid = torch.tensor([[True, True, True, False, True], [True, True, True, True, False]])
    got = masked_feature_pool(features, masks, valid)
    torch.testing.assert_close(got, pool_loop(features, masks, valid))
    assert torch.all(got[0, 3] == 0) and torch.all(got[1, 2] == 0) and torch.all(got[1, 4] == 0)


@pytest.mark.parametrize(("n_out", "n_in"), [(10, 3), (7, 7), (3, 5), (100, 7)])
def test_upsampling_matrix_equals_interpolate(n_out: int, n_in: int) -> None:
    v = torch.randn(1, 2, n_in, dtype=torch.float64)
    expected = F.interpolate(v, size=n_out, mode="linear", align_corners=False)
    r = bilinear_upsampling_matrix(n_out, n_in, device=v.device, dtype=v.dtype)
    torch.testing.assert_close(v @ r.T, expected)


def test_segment_describer_on_tiny_random_weights() -> None:
    describer = build_segment_describer(DescriptorConfig(backend="dinov2", dinov2={**TINY, "short_side_px": 28}))
    assert isinstance(describer, SegmentDescriber) and describer.dim == 48
    images = torch.rand(2, 3, 40, 60, dtype=torch.float64)
    masks = torch.zeros(2, 3, 40, 60, dtype=torch.bool)
    masks[:, 0, :20], masks[:, 1, 20:], masks[0, 2, 5:9, 5:9] = True, True, True
    valid = torch.tensor([[True, True, True], [True, True, False]])
    desc = describer.describe(images, masks, valid)
    assert desc.dtype == torch.float64 and desc.shape == (2, 3, 48)  # follows the images' dtype
    torch.testing.assert_close(desc[valid].norm(dim=1), torch.ones(5, dtype=torch.float64))
    assert torch.all(desc[1, 2] == 0)
    # the top and bottom halves of an image see different content
    assert float(desc[0, 0] @ desc[0, 1]) < 0.999

    # same as pooling the dense features of the resized image ourselves (28 px short side -> 28 x 42)
    resized = F.interpolate(images, size=(28, 42), mode="bicubic", align_corners=False, antialias=True).clamp(0, 1)
    with torch.no_grad():
        dense = describer.features(resized)
    torch.testing.assert_close(desc, masked_feature_pool(dense, masks, valid))


def test_global_describers_share_the_backbone() -> None:
    seg = build_segment_describer(DescriptorConfig(backend="dinov2", dinov2=TINY))
    gem = build_global_describer(GlobalDescriptorConfig(backend="gem", gem={**TINY, "short_side_px": 42}))
    anyloc = build_global_describer(
        GlobalDescriptorConfig(backend="anyloc", anyloc={**TINY, "layer": 1, "num_clusters": 4})
    )
    assert seg.features.backbone is gem.features.backbone is anyloc.facet.backbone  # loaded once
    images = torch.rand(3, 3, 45, 60)
    for describer, dim in ((gem, 48), (anyloc, 4 * 48)):
        assert isinstance(describer, GlobalDescriber) and describer.dim == dim
        desc = describer.describe(images)
        assert desc.shape == (3, dim)
        torch.testing.assert_close(desc.norm(dim=1), torch.ones(3))
        torch.testing.assert_close(describer.describe(images[1:2]), desc[1:2], atol=1e-5, rtol=1e-5)  # batch-independent


def test_missing_weights_and_vocabulary_are_clear_errors(tmp_path: Path) -> None:
    absent = tmp_path / "dinov2_vitl14_pretrain.pth"
    with pytest.raises(ModelWeightsError, match="weights file not found") as info:
        build_segment_describer(DescriptorConfig(backend="dinov2", dinov2={"weights_path": str(absent)}))
    assert str(absent) in str(info.value)
    with pytest.raises(ConfigError, match="perception.descriptor.dinov2: set weights_path"):
        build_segment_describer(DescriptorConfig(backend="dinov2"))
    with pytest.raises(ConfigError, match="anyloc.layer: 31"):
        build_global_describer(GlobalDescriptorConfig(backend="anyloc", anyloc=TINY))
    torch.save(torch.randn(4, 32), tmp_path / "c_centers.pt")  # centres of another backbone
    with pytest.raises(ModelWeightsError, match="dimension 32"):
        build_global_describer(GlobalDescriptorConfig(
            backend="anyloc", anyloc={**TINY, "layer": 1, "num_clusters": 4, "vocabulary_path": str(tmp_path / "c_centers.pt")}
        ))


def test_aerial_map_builds_with_neural_describers() -> None:
    from meridian_torch.config import CONFIG_DIR, load_config
    from meridian_torch.io.ortho import Orthophoto
    from meridian_torch.mapping.aerial_map import AerialMapper, build_aerial_map
    from meridian_torch.sim.ortho_render import render_orthophoto
    from meridian_torch.sim.simulate import build_world

    cfg = load_config(CONFIG_DIR / "tiny_neural.yaml")
    full = render_orthophoto(build_world(cfg.sim), cfg.sim.ortho, 0)
    n = int(round(60.0 / full.meters_per_pixel))  # one 60 m patch
    ortho = Orthophoto(full.image[:n, :n].copy(), full.meters_per_pixel, full.origin_xy)
    aerial_map = build_aerial_map(ortho, AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives))
    prims = aerial_map.primitives
    assert aerial_map.global_descriptors.shape == (1, 4 * 48)
    assert prims.line_descriptors.shape[-1] == 48 and int(prims.point_valid.sum()) > 0
    norms = prims.point_descriptors[prims.point_valid].norm(dim=1)
    torch.testing.assert_close(norms, torch.ones_like(norms), atol=1e-4, rtol=0)

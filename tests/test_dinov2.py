"""DINOv2: official checkpoint layout, Hugging Face conversion, equality with timm, position embeddings."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from meridian_torch.errors import ModelWeightsError
from meridian_torch.perception.neural.dinov2 import (
    ARCHITECTURES,
    DinoVisionTransformer,
    bicubic_resampling_matrix,
    build_dinov2,
    convert_hf_state_dict,
    load_dinov2,
)

timm = pytest.importorskip("timm")


def official_shapes(
    dim: int, depth: int, *, swiglu_hidden: int | None = None, registers: int = 0, grid: int = 37
) -> dict[str, tuple[int, ...]]:
    """Key -> shape of a facebookresearch/dinov2 hub checkpoint (`dinov2_vit*14[_reg4]_pretrain.pth`)."""
    shapes: dict[str, tuple[int, ...]] = {
        "cls_token": (1, 1, dim),
        "pos_embed": (1, 1 + grid * grid, dim),
        "mask_token": (1, dim),
        "patch_embed.proj.weight": (dim, 3, 14, 14),
        "patch_embed.proj.bias": (dim,),
        "norm.weight": (dim,),
        "norm.bias": (dim,),
    }
    if registers:
        shapes["register_tokens"] = (1, registers, dim)
    for i in range(depth):
        b = f"blocks.{i}."
        for norm in ("norm1", "norm2"):
            shapes[b + norm + ".weight"] = shapes[b + norm + ".bias"] = (dim,)
        shapes[b + "attn.qkv.weight"], shapes[b + "attn.qkv.bias"] = (3 * dim, dim), (3 * dim,)
        shapes[b + "attn.proj.weight"], shapes[b + "attn.proj.bias"] = (dim, dim), (dim,)
        shapes[b + "ls1.gamma"] = shapes[b + "ls2.gamma"] = (dim,)
        if swiglu_hidden:
            shapes[b + "mlp.w12.weight"], shapes[b + "mlp.w12.bias"] = (2 * swiglu_hidden, dim), (2 * swiglu_hidden,)
            shapes[b + "mlp.w3.weight"], shapes[b + "mlp.w3.bias"] = (dim, swiglu_hidden), (dim,)
        else:
            shapes[b + "mlp.fc1.weight"], shapes[b + "mlp.fc1.bias"] = (4 * dim, dim), (4 * dim,)
            shapes[b + "mlp.fc2.weight"], shapes[b + "mlp.fc2.bias"] = (dim, 4 * dim), (dim,)
    return shapes


def random_state(shapes: dict[str, tuple[int, ...]], seed: int) -> dict[str, torch.Tensor]:
    """Random weights of a scale that makes every block matter (norm weights near 1, gammas near 0.5)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for key, shape in shapes.items():
        noise = torch.randn(shape, generator=g)
        if "norm" in key and key.endswith("weight"):
            out[key] = 1 + 0.1 * noise
        elif key.endswith("gamma"):
            out[key] = 0.5 + 0.1 * noise
        else:
            out[key] = 0.2 * noise
    return out


def official_to_timm(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Explicit mapping of the official layout onto timm's VisionTransformer.

    timm has no mask token, calls SwiGLU's packed projections fc1/fc2, and for register models
    keeps position embeddings for patches only (the CLS position is folded into the CLS token).
    """
    out = {}
    for key, value in state.items():
        if key == "mask_token":
            continue
        out[key.replace("mlp.w12.", "mlp.fc1.").replace("mlp.w3.", "mlp.fc2.")] = value
    if "register_tokens" in out:
        out["reg_token"] = out.pop("register_tokens")
        out["cls_token"] = out["cls_token"] + out["pos_embed"][:, :1]
        out["pos_embed"] = out["pos_embed"][:, 1:]
    return out


def official_to_hf(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The Hugging Face `Dinov2Model` names of an official state dict (written out independently)."""
    simple = {
        "cls_token": "embeddings.cls_token",
        "mask_token": "embeddings.mask_token",
        "pos_embed": "embeddings.position_embeddings",
        "register_tokens": "embeddings.register_tokens",
        "patch_embed.proj.weight": "embeddings.patch_embeddings.projection.weight",
        "patch_embed.proj.bias": "embeddings.patch_embeddings.projection.bias",
        "norm.weight": "layernorm.weight",
        "norm.bias": "layernorm.bias",
    }
    block_parts = {
        "norm1": "norm1", "norm2": "norm2", "attn.proj": "attention.output.dense",
        "mlp.fc1": "mlp.fc1", "mlp.fc2": "mlp.fc2", "mlp.w12": "mlp.weights_in", "mlp.w3": "mlp.weights_out",
    }
    out = {}
    for key, value in state.items():
        if key in simple:
            out[simple[key]] = value
            continue
        _, i, rest = key.split(".", 2)
        layer = f"encoder.layer.{i}."
        if rest.startswith("attn.qkv."):
            kind = rest.rsplit(".", 1)[1]
            for part, chunk in zip(("query", "key", "value"), value.chunk(3, dim=0)):
                out[f"{layer}attention.attention.{part}.{kind}"] = chunk.clone()
        elif rest in ("ls1.gamma", "ls2.gamma"):
            out[f"{layer}layer_scale{rest[2]}.lambda1"] = value
        else:
            module, kind = rest.rsplit(".", 1)
            out[f"{layer}{block_parts[module]}.{kind}"] = value
    return out


def _shape_table(model: torch.nn.Module) -> dict[str, tuple[int, ...]]:
    return {k: tuple(v.shape) for k, v in model.state_dict().items()}


@pytest.mark.parametrize(
    ("name", "dim", "depth", "swiglu_hidden"),
    [("vits14", 384, 12, None), ("vitb14", 768, 12, None), ("vitl14", 1024, 24, None), ("vitg14", 1536, 40, 4096)],
)
@pytest.mark.parametrize("registers", [0, 4])
def test_architectures_have_the_official_checkpoint_layout(name, dim, depth, swiglu_hidden, registers) -> None:
    with torch.device("meta"):  # shapes only: ViT-G would need 4.5 GB
        model = build_dinov2(name + ("_reg" if registers else ""))
    expected = official_shapes(dim, depth, swiglu_hidden=swiglu_hidden, registers=registers)
    assert _shape_table(model) == expected


def test_official_checkpoint_loads_strictly(tmp_path: Path) -> None:
    state = random_state(official_shapes(48, 3, registers=4, grid=4), seed=0)
    path = tmp_path / "dinov2_tiny_reg4_pretrain.pth"
    torch.save(state, path)
    model = load_dinov2("tiny_reg", path, None, "test")
    assert not model.training
    loaded = model.state_dict()
    assert all(torch.equal(loaded[k], v) for k, v in state.items())


def test_mismatching_checkpoint_is_rejected_naming_the_file(tmp_path: Path) -> None:
    state = random_state(official_shapes(48, 3, grid=4), seed=0)
    path = tmp_path / "plain.pth"
    torch.save(state, path)
    with pytest.raises(ModelWeightsError, match="missing keys: register_tokens") as info:
        load_dinov2("tiny_reg", path, None, "test")  # a checkpoint without registers
    assert str(path) in str(info.value)
    with pytest.raises(ModelWeightsError, match="weights file not found") as info:
        load_dinov2("tiny", tmp_path / "absent.pth", None, "test")
    assert str(tmp_path / "absent.pth") in str(info.value)


@pytest.mark.parametrize("registers", [0, 4])
@pytest.mark.parametrize("swiglu", [False, True])
def test_huggingface_layout_converts_to_the_official_one(tmp_path: Path, registers: int, swiglu: bool) -> None:
    state = random_state(official_shapes(48, 2, swiglu_hidden=128 if swiglu else None, registers=registers, grid=4), 1)
    hf = official_to_hf(state)
    assert "encoder.layer.1.attention.attention.value.weight" in hf
    for source in (hf, {f"dinov2.{k}": v for k, v in hf.items()}):
        converted = convert_hf_state_dict(source)
        assert converted.keys() == state.keys()
        assert all(torch.equal(converted[k], state[k]) for k in state)


def test_huggingface_safetensors_file_loads(tmp_path: Path) -> None:
    from safetensors.torch import save_file

    state = random_state(official_shapes(48, 3, grid=4), 2)
    path = tmp_path / "model.safetensors"
    save_file(official_to_hf(state), str(path))
    model = load_dinov2("tiny", path, None, "test")
    assert torch.equal(model.state_dict()["blocks.2.attn.qkv.weight"], state["blocks.2.attn.qkv.weight"])

    extra = {**official_to_hf(state), "pooler.dense.weight": torch.zeros(48, 48)}
    save_file(extra, str(path))
    with pytest.raises(ModelWeightsError, match="unexpected keys: pooler.dense.weight"):
        load_dinov2("tiny", path, None, "test")


def _pair(timm_name: str, *, registers: int = 0, swiglu: bool = False, img: tuple[int, int] = (56, 56), seed: int = 0):
    """Our model and timm's reference on the same random official-layout weights."""
    depth = 3
    ours = DinoVisionTransformer(
        embed_dim=48, depth=depth, num_heads=3, ffn="swiglu" if swiglu else "mlp", num_register_tokens=registers, pos_grid=4
    ).eval()
    state = random_state(official_shapes(48, depth, swiglu_hidden=128 if swiglu else None, registers=registers, grid=4), seed)
    ours.load_state_dict(state, strict=True)
    extra = {"mlp_ratio": 256 / 48 + 1e-6} if swiglu else {}  # timm packs both SwiGLU halves: 2 x 128
    ref = timm.create_model(
        timm_name, pretrained=False, img_size=img, embed_dim=48, depth=depth, num_heads=3, num_classes=0, **extra
    ).eval()
    timm_state = official_to_timm(state)
    if img != (56, 56):  # timm keeps a fixed grid: give it ours, resampled to this size
        grid = ours.patch_position_embedding(img[0] // 14, img[1] // 14)[None].detach()
        timm_state["pos_embed"] = grid if registers else torch.cat([state["pos_embed"][:, :1], grid], dim=1)
    ref.load_state_dict(timm_state, strict=True)
    return ours, ref


@pytest.mark.parametrize(
    ("timm_name", "registers", "swiglu"),
    [("vit_small_patch14_dinov2", 0, False), ("vit_small_patch14_reg4_dinov2", 4, False), ("vit_giant_patch14_dinov2", 0, True)],
)
def test_forward_equals_timm(timm_name: str, registers: int, swiglu: bool) -> None:
    ours, ref = _pair(timm_name, registers=registers, swiglu=swiglu)
    x = torch.randn(2, 3, 56, 56, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        dense = ours.dense_features(x)
        expected = ref.forward_features(x)[:, 1 + registers :].transpose(1, 2).reshape(2, 48, 4, 4)
        assert dense.shape == (2, 48, 4, 4)
        torch.testing.assert_close(dense, expected, atol=1e-5, rtol=1e-5)

        layers = ours.intermediate_layers(x, [0, 2], norm=True)
        expected_layers = ref.forward_intermediates(x, indices=[0, 2], norm=True, output_fmt="NCHW", intermediates_only=True)
        for got, want in zip(layers, expected_layers):
            torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


def test_without_layer_scale_equals_timm() -> None:
    ours = DinoVisionTransformer(embed_dim=48, depth=2, num_heads=3, pos_grid=4, layer_scale=False).eval()
    shapes = {k: v for k, v in official_shapes(48, 2, grid=4).items() if not k.endswith("gamma")}
    assert _shape_table(ours) == shapes
    state = random_state(shapes, 9)
    ours.load_state_dict(state, strict=True)
    ref = timm.create_model(
        "vit_small_patch14_dinov2", pretrained=False, img_size=56, embed_dim=48, depth=2, num_heads=3,
        num_classes=0, init_values=0.0,  # falsy: no LayerScale (timm drops None kwargs)
    ).eval()
    ref.load_state_dict(official_to_timm(state), strict=True)
    x = torch.randn(1, 3, 56, 56, generator=torch.Generator().manual_seed(10))
    with torch.no_grad():
        expected = ref.forward_features(x)[:, 1:].transpose(1, 2).reshape(1, 48, 4, 4)
        torch.testing.assert_close(ours.dense_features(x), expected, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("layer", [0, 1, 2])
def test_facets_equal_timm_blocks(layer: int) -> None:
    ours, ref = _pair("vit_small_patch14_reg4_dinov2", registers=4, seed=4)
    x = torch.randn(1, 3, 56, 56, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        tokens = ref._pos_embed(ref.patch_embed(x))
        for block in ref.blocks[:layer]:
            tokens = block(tokens)
        qkv = ref.blocks[layer].attn.qkv(ref.blocks[layer].norm1(tokens))[:, 5:]
        expected = {"query": qkv[..., :48], "key": qkv[..., 48:96], "value": qkv[..., 96:]}
        expected["token"] = ref.blocks[layer](tokens)[:, 5:]
        for facet, want in expected.items():
            torch.testing.assert_close(ours.facet(x, layer, facet), want, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("registers", [0, 4])
def test_forward_at_another_size_equals_timm_with_resampled_positions(registers: int) -> None:
    # 70 x 100 px: a 5 x 7 grid plus 2 px that the patch embedding drops, as the official model does
    name = "vit_small_patch14_reg4_dinov2" if registers else "vit_small_patch14_dinov2"
    ours, ref = _pair(name, registers=registers, img=(70, 98), seed=6)
    x = torch.randn(2, 3, 70, 100, generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        expected = ref.forward_features(x[..., :98])[:, 1 + registers :].transpose(1, 2).reshape(2, 48, 5, 7)
        torch.testing.assert_close(ours.dense_features(x), expected, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("offset", [0.1, 0.0])
@pytest.mark.parametrize("n_out", [1, 3, 4, 9, 37])
def test_bicubic_matrix_equals_torch_interpolate(offset: float, n_out: int) -> None:
    v = torch.randn(1, 2, 4, 4, generator=torch.Generator().manual_seed(n_out))
    expected = F.interpolate(v, scale_factor=((n_out + offset) / 4,) * 2, mode="bicubic", align_corners=False)
    a = bicubic_resampling_matrix(n_out, 4, torch.tensor(offset))
    torch.testing.assert_close(torch.einsum("ip,bcpq,jq->bcij", a, v, a), expected, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("grid", [(4, 4), (3, 6), (10, 7)])
def test_position_embedding_follows_the_official_interpolation(grid: tuple[int, int]) -> None:
    model = DinoVisionTransformer(embed_dim=8, depth=1, num_heads=2, pos_grid=4)
    with torch.no_grad():
        model.pos_embed.normal_(generator=torch.Generator().manual_seed(8))
    trained = model.pos_embed[0, 1:].reshape(1, 4, 4, 8).permute(0, 3, 1, 2)
    h, w = grid
    if grid == (4, 4):  # the official model skips interpolation at the trained size
        expected = trained
    else:  # official: bicubic with scale (n + 0.1) / 4 per axis
        expected = F.interpolate(trained, scale_factor=((h + 0.1) / 4, (w + 0.1) / 4), mode="bicubic", align_corners=False)
    got = model.patch_position_embedding(h, w).detach()
    torch.testing.assert_close(got, expected[0].permute(1, 2, 0).reshape(h * w, 8), atol=1e-5, rtol=1e-5)


def test_tiny_architecture_is_tiny() -> None:
    # a config that silently ignored the size would build a 300M-parameter model in CI
    assert sum(p.numel() for p in build_dinov2("tiny").parameters()) < 200_000
    assert ARCHITECTURES["tiny_reg"].num_register_tokens == 4


@pytest.mark.slow
def test_dense_features_export_with_dynamic_image_size() -> None:
    # The ONNX export relies on this: no shape-specializing guards, native and resampled grids alike.
    from meridian_torch.perception.neural.dinov2 import DinoDenseFeatures
    from meridian_torch.perception.neural.weights import initialize_weights

    model = DinoDenseFeatures(initialize_weights(build_dinov2("tiny_reg"), None, 0, "test")).eval()
    b, h, w = torch.export.Dim("b"), torch.export.Dim("h", min=1, max=100), torch.export.Dim("w", min=1, max=100)
    program = torch.export.export(
        model, (torch.rand(2, 3, 56, 84),), dynamic_shapes=({0: b, 2: 14 * h, 3: 14 * w},)
    )
    for shape in [(3, 3, 28, 140), (2, 3, 56, 56)]:  # another size, and the native 4 x 4 grid
        x = torch.rand(*shape)
        with torch.no_grad():
            torch.testing.assert_close(program.module()(x), model(x))

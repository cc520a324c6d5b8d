"""Validated configuration: one pydantic model per stage, composed in `MeridianConfig`.

Config files are YAML. A file may start from another with `extends: other.yaml` (resolved
relative to the file) and then overrides any subset of keys. Values of keys ending in `path`
that start with `./` or `../` are resolved relative to the file that sets them. Unknown keys and bad values are
`ConfigError`s that name the file and the dotted key. `overrides` are `a.b.c=value` strings
whose value is parsed as YAML.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, ValidationError

from meridian_torch.errors import ConfigError
from meridian_torch.mapping.config import PrimitiveConfig
from meridian_torch.matching.config import MatchConfig
from meridian_torch.perception.config import DescriptorConfig, GlobalDescriptorConfig, SegmenterConfig
from meridian_torch.sim.config import SimConfig, StrictModel

__all__ = [
    "RuntimeConfig",
    "PerceptionConfig",
    "AerialMapConfig",
    "GroundMapConfig",
    "BackendConfig",
    "EvaluationConfig",
    "MeridianConfig",
    "CONFIG_DIR",
    "load_config",
    "dump_config",
]

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


class RuntimeConfig(StrictModel):
    """Device and dtype are chosen once here and read from the tensors everywhere else."""

    device: str = Field(default="cpu", pattern=r"^(cpu|auto|cuda(:\d+)?)$")
    dtype: Literal["float32", "float64"] = "float32"
    num_threads: int = Field(default=0, ge=0, description="torch CPU threads; 0 = torch's default")


class PerceptionConfig(StrictModel):
    """Back ends of segmentation and description; aerial and ground share the describers so
    that their descriptors are comparable."""

    aerial_segmenter: SegmenterConfig = SegmenterConfig()
    ground_segmenter: SegmenterConfig = SegmenterConfig()
    descriptor: DescriptorConfig = DescriptorConfig()
    global_descriptor: GlobalDescriptorConfig = GlobalDescriptorConfig()


class AerialMapConfig(StrictModel):
    patch_size_m: float = Field(default=60.0, gt=0)
    patch_overlap: float = Field(default=0.5, ge=0, lt=1, description="50 % overlap = 30 m stride")
    segmentation_crop_m: float | None = Field(
        default=None, gt=0, description="segment each patch in square sub-crops of this size (None: whole patch)"
    )
    batch_size: int = Field(default=4, ge=1, description="patches segmented together")


class GroundMapConfig(StrictModel):
    submap_trigger_new_segments: int = Field(default=20, ge=1)
    submap_max_segments: int = Field(default=120, ge=1)
    submap_radius_m: float = Field(default=40.0, gt=0)


class BackendConfig(StrictModel):
    """Robust pose graph: loop-closure noise grows with the odometry path length l."""

    sigma_yaw_deg: float = Field(default=5.0, gt=0)
    sigma_yaw_deg_per_m: float = Field(default=0.02, ge=0)
    sigma_t_m: float = Field(default=2.0, gt=0)
    sigma_t_m_per_m: float = Field(default=0.05, ge=0)
    fix_min_inliers: int = Field(default=6, ge=1)
    fix_min_inlier_fraction: float = Field(default=0.5, gt=0, le=1)


class EvaluationConfig(StrictModel):
    success_translation_m: float = Field(default=5.0, gt=0)
    success_rotation_deg: float = Field(default=5.0, gt=0)
    success_rotation_deg_loose: float = Field(default=10.0, gt=0)


class MeridianConfig(StrictModel):
    runtime: RuntimeConfig = RuntimeConfig()
    sim: SimConfig = SimConfig()
    perception: PerceptionConfig = PerceptionConfig()
    primitives: PrimitiveConfig = PrimitiveConfig()
    aerial_map: AerialMapConfig = AerialMapConfig()
    ground_map: GroundMapConfig = GroundMapConfig()
    matching: MatchConfig = MatchConfig()
    backend: BackendConfig = BackendConfig()
    evaluation: EvaluationConfig = EvaluationConfig()


def _read_yaml(path: Path, chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    if path in chain:
        raise ConfigError(f"{path}: circular 'extends' chain")
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    _resolve_relative_paths(data, path.parent)
    base = data.pop("extends", None)
    if base is None:
        return data
    return _deep_merge(_read_yaml((path.parent / str(base)).resolve(), chain + (path,)), data)


def _resolve_relative_paths(node: dict[str, Any], folder: Path) -> None:
    for key, value in node.items():
        if isinstance(value, dict):
            _resolve_relative_paths(value, folder)
        elif str(key).endswith("path") and isinstance(value, str) and value.startswith(("./", "../")):
            node[key] = str((folder / value).resolve())


def _deep_merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _apply_override(data: dict[str, Any], override: str) -> None:
    key, sep, raw = override.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"override {override!r}: expected KEY=VALUE, e.g. sim.seed=3")
    parts = key.strip().split(".")
    node = data
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"override {override!r}: {part!r} is not a section")
        node = child
    try:
        node[parts[-1]] = yaml.safe_load(raw)
    except yaml.YAMLError as exc:
        raise ConfigError(f"override {override!r}: value is not valid YAML: {exc}") from None


def _format_validation_error(source: str, exc: ValidationError) -> str:
    lines = []
    for err in exc.errors():
        key = ".".join(str(p) for p in err["loc"]) or "(top level)"
        if err["type"] == "extra_forbidden":
            lines.append(f"{source}: unknown key '{key}'")
        else:
            lines.append(f"{source}: {key}: {err['msg']} (got {err.get('input')!r})")
    return "\n".join(lines)


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> MeridianConfig:
    """Load and validate a config file (default: configs/default.yaml) with KEY=VALUE overrides."""
    path = Path(path) if path is not None else CONFIG_DIR / "default.yaml"
    data = _read_yaml(path.resolve())
    for override in overrides:
        _apply_override(data, override)
    source = str(path) + (" with overrides" if overrides else "")
    try:
        return MeridianConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(source, exc)) from None


def dump_config(config: MeridianConfig) -> str:
    """The fully resolved config as YAML (every key, defaults included)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)

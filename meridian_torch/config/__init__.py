"""Validated configuration: one pydantic model per stage, composed in `MeridianConfig`.

Config files are YAML. A file may start from another with `extends: other.yaml` (resolved
relative to the file) and then overrides any subset of keys. Values of keys ending in `path`
that start with `./` or `../` are resolved relative to the file that sets them. Unknown keys and bad values are
`ConfigError`s that name the file and the dotted key. `overrides` are `a.b.c=value` strings
whose value is parsed as YAML.

Every stage's config model lives in this package, one module per stage (`sim`, `perception`,
`mapping` (aerial map, ground mapping, primitives), `matching`, `backend`) on the common
`base.StrictModel`; this module composes them in `MeridianConfig` and loads files. Config
modules import only pydantic and each other, so loading a config loads no stage code.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, ValidationError

from meridian_torch.config.backend import BackendConfig
from meridian_torch.config.base import StrictModel
from meridian_torch.config.mapping import (
    AerialMapConfig,
    CloudCleanupConfig,
    GroundMapConfig,
    GroundObservationConfig,
    GroundTrackingConfig,
    PrimitiveConfig,
)
from meridian_torch.config.matching import ClipperConfig, MatchConfig
from meridian_torch.config.perception import PerceptionConfig
from meridian_torch.config.sim import SimConfig
from meridian_torch.core.paths import shipped_dir
from meridian_torch.errors import ConfigError

__all__ = [
    "StrictModel",
    "RuntimeConfig",
    "PerceptionConfig",
    "PrimitiveConfig",
    "AerialMapConfig",
    "CloudCleanupConfig",
    "GroundObservationConfig",
    "GroundTrackingConfig",
    "GroundMapConfig",
    "ClipperConfig",
    "MatchConfig",
    "BackendConfig",
    "EvaluationConfig",
    "SimConfig",
    "MeridianConfig",
    "CONFIG_DIR",
    "load_config",
    "dump_config",
    "config_key",
]

CONFIG_DIR = shipped_dir("configs")  # the checkout's configs/, or a wheel's bundled copy


class RuntimeConfig(StrictModel):
    """Device and dtype are chosen once here and read from the tensors everywhere else."""

    device: str = Field(default="cpu", pattern=r"^(cpu|auto|cuda(:\d+)?)$")
    dtype: Literal["float32", "float64"] = "float32"
    num_threads: int = Field(
        default=0, ge=0,
        description="CPU threads: torch's, and our thread pools' (per-frame perception, matching's patch groups); "
        "0 = torch's default (one per core). While the ground mapper's pipeline runs, torch itself runs "
        "single-threaded and the pools keep this count",
    )
    blas_threads: int = Field(
        default=1, ge=0,
        description="threads of NumPy's, SciPy's and OpenCV's BLAS; 0 = the library's default (one per core)",
    )


class EvaluationConfig(StrictModel):
    success_translation_m: float = Field(default=5.0, gt=0, description="[paper] registration success < 5 m")
    success_rotation_deg: float = Field(default=5.0, gt=0, description="[paper] ... and < 5 deg")
    success_rotation_deg_loose: float = Field(default=10.0, gt=0, description="reference default, also reported")
    success_top_k: list[int] = Field(default=[1, 5, 10, 25], min_length=1, description="[paper] top-L success rates")
    max_time_difference_s: float = Field(
        default=0.01, ge=0, description="an estimate and a ground-truth pose pair up within this time (evo's default)"
    )


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


def config_key(*parts: Any) -> str:
    """A short hash of JSON-able config parts (and the package version): names cached products."""
    import hashlib
    import json

    from meridian_torch import __version__

    return hashlib.sha256(json.dumps([__version__, *parts], sort_keys=True).encode()).hexdigest()[:12]

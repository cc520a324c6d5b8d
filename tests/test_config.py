from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from meridian_torch.config import CONFIG_DIR, MeridianConfig, dump_config, load_config
from meridian_torch.errors import ConfigError

ALL_CONFIGS = sorted(CONFIG_DIR.glob("*.yaml"))


def _leaf_keys(data: dict, prefix: str = "") -> set[str]:
    keys = set()
    for key, value in data.items():
        if isinstance(value, dict) and value:
            keys |= _leaf_keys(value, f"{prefix}{key}.")
        else:
            keys.add(f"{prefix}{key}")
    return keys


@pytest.mark.parametrize("path", ALL_CONFIGS, ids=[p.name for p in ALL_CONFIGS])
def test_every_shipped_config_validates(path: Path) -> None:
    assert isinstance(load_config(path), MeridianConfig)


def test_default_yaml_is_explicit_and_equals_code_defaults() -> None:
    # Every default is visible in the file, and the file and the code never drift apart.
    raw = yaml.safe_load((CONFIG_DIR / "default.yaml").read_text())
    code = MeridianConfig().model_dump(mode="json")
    assert _leaf_keys(raw) == _leaf_keys(code)
    assert load_config(CONFIG_DIR / "default.yaml") == MeridianConfig()


def test_paper_defaults() -> None:
    cfg = load_config()
    assert (cfg.aerial_map.patch_size_m, cfg.aerial_map.patch_overlap) == (60.0, 0.5)
    assert (cfg.ground_map.submap_trigger_new_segments, cfg.ground_map.submap_max_segments) == (20, 120)
    assert cfg.ground_map.submap_radius_m == 40.0
    m = cfg.matching
    assert (m.place_recognition.k_global, m.associations.k_prim, m.hypotheses_per_patch) == (25, 20, 25)
    assert (m.affinity.sigma_t_m, m.affinity.sigma_theta_deg) == (2.0, 20.0)
    assert (m.affinity.epsilon_t_m, m.affinity.epsilon_theta_deg) == (2.0, 20.0)  # zero outside sigma
    assert (m.cluster_translation_m, m.cluster_rotation_deg) == (1.0, 5.0)
    assert (cfg.backend.sigma_yaw_deg, cfg.backend.sigma_yaw_deg_per_m) == (5.0, 0.02)
    assert (cfg.backend.sigma_t_m, cfg.backend.sigma_t_m_per_m) == (2.0, 0.05)
    assert (cfg.backend.fix_min_inliers, cfg.backend.fix_min_inlier_fraction) == (6, 0.5)


def test_unknown_key_is_named(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("sim:\n  world:\n    sizee_m: [10, 10]\n")
    with pytest.raises(ConfigError, match=r"unknown key 'sim\.world\.sizee_m'") as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_bad_value_is_named(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("matching:\n  place_recognition:\n    k_global: -3\n")
    with pytest.raises(ConfigError, match=r"matching\.place_recognition\.k_global.*-3"):
        load_config(path)


def test_extends_and_overrides(tmp_path: Path) -> None:
    base = tmp_path / "base.yaml"
    base.write_text("sim:\n  seed: 5\n  name: base\n")
    child = tmp_path / "child.yaml"
    child.write_text("extends: base.yaml\nsim:\n  name: child\n")
    cfg = load_config(child, ["sim.world.size_m=[50, 60]", "matching.place_recognition.k_global=3"])
    assert cfg.sim.seed == 5 and cfg.sim.name == "child"
    assert cfg.sim.world.size_m == (50.0, 60.0) and cfg.matching.place_recognition.k_global == 3


@pytest.mark.parametrize("override", ["nokey", "=3", "sim.seed.x=1"])
def test_malformed_override(override: str) -> None:
    with pytest.raises(ConfigError):
        load_config(None, [override])


def test_unknown_override_key_is_named() -> None:
    with pytest.raises(ConfigError, match=r"unknown key 'matching\.place_recognition\.k_globl'"):
        load_config(None, ["matching.place_recognition.k_globl=3"])


def test_dump_round_trip(tmp_path: Path) -> None:
    cfg = load_config(CONFIG_DIR / "tiny.yaml")
    path = tmp_path / "resolved.yaml"
    path.write_text(dump_config(cfg))
    assert load_config(path) == cfg


def test_circular_extends(tmp_path: Path) -> None:
    (tmp_path / "a.yaml").write_text("extends: b.yaml\n")
    (tmp_path / "b.yaml").write_text("extends: a.yaml\n")
    with pytest.raises(ConfigError, match="circular"):
        load_config(tmp_path / "a.yaml")


def test_relative_paths_resolve_against_the_file(tmp_path: Path) -> None:
    sub = tmp_path / "cfgs"
    sub.mkdir()
    (sub / "c.yaml").write_text("sim:\n  trajectory:\n    kind: file\n    path: ../data/gt.tum\n")
    cfg = load_config(sub / "c.yaml")
    assert Path(cfg.sim.trajectory.path) == (tmp_path / "data" / "gt.tum").resolve()


def _float_keys(data: dict, prefix: str = "") -> list[str]:
    keys = []
    for key, value in data.items():
        if isinstance(value, dict):
            keys += _float_keys(value, f"{prefix}{key}.")
        elif isinstance(value, float):
            keys.append(f"{prefix}{key}")
    return keys


FLOAT_KEYS = _float_keys(MeridianConfig().model_dump(mode="json"))


@pytest.mark.parametrize("value", ["inf", "-inf", "nan"])
def test_every_float_refuses_non_finite_values(value: str) -> None:
    """An infinite sigma or gate would silently disable what it bounds: every float is checked."""
    assert len(FLOAT_KEYS) > 50  # every stage's floats, not a handful
    for key in FLOAT_KEYS:
        with pytest.raises(ConfigError, match=re.escape(key) + ": .*finite"):
            load_config(CONFIG_DIR / "default.yaml", [f"{key}={value}"])

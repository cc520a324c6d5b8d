"""The live API: frames one at a time give what the folder pipeline gives on the same frames."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.errors import ConfigError
from meridian_torch.io.ortho import read_orthophoto
from meridian_torch.io.sequence import SequenceReader
from meridian_torch.mapping.aerial_map import AerialMapper, build_aerial_map
from meridian_torch.pipeline import LiveLocalizer, localize_sequence
from meridian_torch.runtime import resolve_runtime
from meridian_torch.sim.simulate import simulate_sequence

# A drive long enough for a global fix on the tiny world; frames one batch each, as live input comes.
CFG_OVERRIDES = ["sim.trajectory.length_m=400", "sim.world.size_m=[200.0,200.0]", "ground_map.batch_size=1"]
CFG = load_config(CONFIG_DIR / "tiny.yaml", CFG_OVERRIDES)


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("live") / "seq"
    simulate_sequence(CFG.sim, out)
    mapper = AerialMapper.from_config(CFG.aerial_map, CFG.perception, CFG.primitives)
    return SequenceReader(out), build_aerial_map(read_orthophoto(out), mapper)


@pytest.fixture(scope="module")
def live_run(world):
    reader, aerial_map = world
    live = LiveLocalizer(aerial_map, CFG, reader.camera, resolve_runtime(CFG.runtime))
    estimates = [live.add_frame(f.rgb, f.depth, f.T_odom_base, f.timestamp) for f in (reader[i] for i in range(len(reader)))]
    return estimates, live.finish()


@pytest.mark.slow
def test_frame_by_frame_equals_the_folder_pipeline(world, live_run) -> None:
    reader, aerial_map = world
    estimates, live_result = live_run
    folder = localize_sequence(reader, aerial_map, CFG, resolve_runtime(CFG.runtime)).result
    assert folder.localized and live_result.localized and folder.fix_submap_index is not None
    np.testing.assert_array_equal(live_result.T_world_base, folder.T_world_base)
    np.testing.assert_array_equal(live_result.T_world_base_incremental, folder.T_world_base_incremental)
    # what the robot was told at each frame is the folder run's online estimate at that frame
    told = np.stack([np.full((4, 4), np.nan) if e.T_world_base is None else e.T_world_base for e in estimates])
    np.testing.assert_array_equal(told, folder.T_world_base_incremental)
    assert [e.time for e in estimates] == reader.frame_times.tolist()
    assert sum(len(e.events) for e in estimates) + 1 >= len(folder.events) >= sum(len(e.events) for e in estimates)


@pytest.mark.slow
def test_the_estimate_carries_a_covariance_that_grows_between_updates(live_run) -> None:
    estimates, _ = live_run
    backend = CFG.backend
    fixed = [e for e in estimates if e.localized]
    assert fixed and all(e.state == "post" for e in fixed)
    assert all(e.covariance is None and e.state == "pre" for e in estimates[: estimates.index(fixed[0])])
    for e in fixed:
        assert np.allclose(e.covariance, e.covariance.T) and np.all(np.linalg.eigvalsh(e.covariance) > 0)
    # between two submap updates only odometry adds up: one odometry factor's yaw variance per frame,
    # its per-step term plus its per-metre term over the step (the estimate moves as the odometry)
    steps = [(first, second) for first, second in zip(fixed, fixed[1:]) if not second.events]
    assert steps
    for first, second in steps:
        length = np.linalg.norm(second.T_world_base[:2, 3] - first.T_world_base[:2, 3])
        step_var = (np.radians(backend.odom_rot_sigma_deg) ** 2
                    + np.radians(backend.odom_rot_sigma_deg_per_sqrt_m) ** 2 * length)
        assert second.covariance[2, 2] - first.covariance[2, 2] == pytest.approx(step_var, rel=1e-6)


def test_bad_frames_are_refused_naming_the_field(world) -> None:
    reader, aerial_map = world
    live = LiveLocalizer(aerial_map, CFG, reader.camera, resolve_runtime(CFG.runtime))
    f = reader[0]
    with pytest.raises(ValueError, match="rgb: expected"):
        live.add_frame(f.rgb[:, :, 0], f.depth, f.T_odom_base, f.timestamp)
    with pytest.raises(ValueError, match="depth: expected"):
        live.add_frame(f.rgb, f.depth[1:], f.T_odom_base, f.timestamp)
    with pytest.raises(ValueError, match="T_odom_base: expected"):
        live.add_frame(f.rgb, f.depth, np.full((4, 4), np.nan), f.timestamp)
    live.add_frame(f.rgb, f.depth, f.T_odom_base, f.timestamp)
    with pytest.raises(ValueError, match="strictly increasing"):
        live.add_frame(f.rgb, f.depth, f.T_odom_base, f.timestamp)


@pytest.mark.slow
def test_submaps_come_denser_from_the_fix_on(tmp_path: Path) -> None:
    # a longer drive than `world`'s, so that several submaps follow the fix
    cfg = load_config(CONFIG_DIR / "tiny.yaml", [*CFG_OVERRIDES, "sim.trajectory.length_m=700",
                                                 "ground_map.submap_spacing_after_fix="
                                                 "{trigger_path_m: 12, min_interval_s: 0, min_path_m: 12}"])
    simulate_sequence(cfg.sim, tmp_path / "seq")
    reader = SequenceReader(tmp_path / "seq")
    aerial_map = build_aerial_map(read_orthophoto(tmp_path / "seq"),
                                  AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives))
    run = localize_sequence(reader, aerial_map, cfg, resolve_runtime(cfg.runtime))
    fix = run.result.fix_submap_index
    assert fix is not None
    gaps = np.diff([s.path_length_m for s in run.submaps])
    before, after = gaps[:fix], gaps[fix:]
    assert len(after) >= 3
    # before the fix the default gates hold; after it, gaps those gates forbid, none below the new one
    assert before.min() >= cfg.ground_map.submap_min_path_m - 1e-9
    assert after.min() >= 12.0 - 1e-9 and (after < cfg.ground_map.submap_min_path_m).any()


def test_frame_descriptors_are_computed_only_when_place_recognition_reads_them(world) -> None:
    reader, aerial_map = world
    cases = (("auto", "auto", False), ("exhaustive", "auto", False), ("global", "auto", True),
             ("coarse", "auto", False), ("coarse", "always", True))  # the tiny map's descriptors are classical
    for mode, fusion, wanted in cases:
        cfg = load_config(CONFIG_DIR / "tiny.yaml", [*CFG_OVERRIDES, f"matching.place_recognition.mode={mode}",
                                                     f"matching.place_recognition.global_fusion={fusion}"])
        live = LiveLocalizer(aerial_map, cfg, reader.camera, resolve_runtime(cfg.runtime))
        assert live.mapper.frame_descriptors is wanted, (mode, fusion)
        # and no global describer (no model, no weights) is built for descriptors nothing reads
        assert (live.mapper.global_describer is not None) is wanted, (mode, fusion)


def test_descriptors_of_another_global_back_end_than_the_map_are_refused(world) -> None:
    reader, aerial_map = world
    perception = {**aerial_map.config["perception"], "global_descriptor": {"backend": "anyloc"}}
    anyloc_map = dataclasses.replace(aerial_map, config={**aerial_map.config, "perception": perception})
    assert anyloc_map.global_descriptor_backend == "anyloc" and aerial_map.global_descriptor_backend == "classical"
    coarse = [*CFG_OVERRIDES, "matching.place_recognition.mode=coarse"]
    with pytest.raises(ConfigError, match="'classical'.*'anyloc'"):
        LiveLocalizer(anyloc_map, load_config(CONFIG_DIR / "tiny.yaml", coarse), reader.camera,
                      resolve_runtime(CFG.runtime))
    # without fusion the map's descriptors are never read: nothing to refuse
    cfg = load_config(CONFIG_DIR / "tiny.yaml", [*coarse, "matching.place_recognition.global_fusion=never"])
    live = LiveLocalizer(anyloc_map, cfg, reader.camera, resolve_runtime(cfg.runtime))
    assert live.mapper.frame_descriptors is False


@pytest.mark.slow
def test_frames_above_the_mapping_rate_carry_odometry_in_both_paths(world) -> None:
    """At 3/4 of the frame rate, frame by frame and the folder pipeline map the same frames into the
    same submaps, and both trajectories still have a pose for every frame."""
    reader, aerial_map = world
    rate = 0.75 / float(np.median(np.diff(reader.frame_times)))
    cfg = load_config(CONFIG_DIR / "tiny.yaml", [*CFG_OVERRIDES, f"ground_map.mapping_rate_hz={rate!r}"])
    folder = localize_sequence(reader, aerial_map, cfg, resolve_runtime(cfg.runtime))
    live = LiveLocalizer(aerial_map, cfg, reader.camera, resolve_runtime(cfg.runtime))
    estimates = [live.add_frame(f.rgb, f.depth, f.T_odom_base, f.timestamp) for f in reader]
    result = live.finish()
    assert folder.frames_mapped == len(live.mapper.frames) == pytest.approx(0.75 * len(reader), abs=1)
    assert [e.time for e in estimates] == reader.frame_times.tolist()
    assert len(folder.result.T_world_base) == len(result.T_world_base) == len(reader)
    np.testing.assert_array_equal(result.T_world_base_incremental, folder.result.T_world_base_incremental)
    assert len(live.submaps) == len(folder.submaps) >= 2
    for a, b in zip(live.submaps, folder.submaps):
        assert a.time == b.time
        for name in a.primitives.__dataclass_fields__:
            assert torch.equal(getattr(a.primitives, name), getattr(b.primitives, name)), name

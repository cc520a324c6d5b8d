"""The same code on CUDA when `runtime.device` says so: matching, ground mapping and the localizer
give on the GPU what they give on the CPU. Skipped on machines without CUDA (CI has none)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.io.sequence import SequenceReader
from meridian_torch.mapping.ground_map import map_ground
from meridian_torch.matching.match import match_submap
from meridian_torch.runtime import resolve_runtime
from meridian_torch.sim.simulate import simulate_sequence
from meridian_torch.types import stack_primitive_sets

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def test_matching_on_cuda_recovers_the_planted_transform() -> None:
    from test_match import CFG, check_top, scene

    ground, patches, kp, kl = scene()
    batch = stack_primitive_sets(patches).to(device="cuda")
    hyp = match_submap(ground.to(device="cuda"), batch, config=CFG,
                       generator=torch.Generator(device="cuda").manual_seed(0))
    assert hyp.T_world_odom.device.type == "cuda" and hyp.probability.device.type == "cuda"
    check_top(dataclasses.replace(hyp, **{f.name: getattr(hyp, f.name).cpu() for f in dataclasses.fields(hyp)
                                          if isinstance(getattr(hyp, f.name), torch.Tensor)}),
              batch.points_xy.shape[1], kp, kl)


def test_ground_mapping_on_cuda_gives_the_cpus_submaps(tmp_path) -> None:
    cfg = load_config(CONFIG_DIR / "tiny.yaml")
    simulate_sequence(cfg.sim, tmp_path / "seq")
    reader = SequenceReader(tmp_path / "seq")
    on_cpu = map_ground(reader, cfg, resolve_runtime(cfg.runtime.model_copy(update={"device": "cpu"})))
    on_gpu = map_ground(reader, cfg, resolve_runtime(cfg.runtime.model_copy(update={"device": "cuda"})))
    assert len(on_gpu) == len(on_cpu) > 0
    for a, b in zip(on_cpu, on_gpu):
        # segmentation and description run on the GPU: float rounding may move a primitive a
        # little, never the submap's place or its make-up
        np.testing.assert_allclose(a.T_odom_base, b.T_odom_base)
        pa, pb = a.primitives, b.primitives.to(device="cpu")
        assert abs(len(pa.points_xy) - len(pb.points_xy)) <= max(1, len(pa.points_xy) // 10)
        assert abs(len(pa.line_endpoints) - len(pb.line_endpoints)) <= max(1, len(pa.line_endpoints) // 10)


def test_localizer_on_cuda_localizes_like_on_the_cpu() -> None:
    from test_backend_end_to_end import _check, _config, make_world

    from meridian_torch.backend.localizer import Localizer

    aerial, gt, odometry, submaps = make_world(n_frames=140, spacing_m=16.0)
    loc = Localizer(aerial.to("cuda"), _config("particles"), odometry, gt.timestamps, seed=0)
    events = [loc.add_submap(s) for s in submaps]
    _check(gt, submaps, events, loc.finalize())

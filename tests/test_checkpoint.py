"""Run checkpoints: recorded matching calls are replayed exactly; an interrupted localize resumes
with the result of an uninterrupted run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from meridian_torch.cli import app
from meridian_torch.config import CONFIG_DIR
from meridian_torch.errors import CheckpointError
from meridian_torch.matching.match import match_submap
from meridian_torch.pipeline.checkpoint import MatchingCheckpoint
from meridian_torch.types import stack_primitive_sets
from tests.test_match import CFG, scene


class Counting:
    """match_submap, counting the calls that really match."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return match_submap(*args, **kwargs)


def _calls(matcher, generator: torch.Generator):
    ground, patches, _, _ = scene(0)
    aerial = stack_primitive_sets(patches)
    return [matcher(ground, aerial, rotation_prior=prior, config=CFG, generator=generator) for prior in (None, 0.3)]


def test_recorded_calls_are_replayed_with_the_generator_state(tmp_path: Path) -> None:
    fresh, plain = Counting(), torch.Generator().manual_seed(5)
    want = _calls(fresh, plain)
    first = Counting()
    g1 = torch.Generator().manual_seed(5)
    got1 = _calls(MatchingCheckpoint(tmp_path / "ckpt", "run-a", first), g1)
    second = Counting()
    g2 = torch.Generator().manual_seed(5)
    replay = MatchingCheckpoint(tmp_path / "ckpt", "run-a", second)
    got2 = _calls(replay, g2)
    assert first.calls == 2 and second.calls == 0 and replay.replayed == 2
    for a, b, c in zip(want, got1, got2):
        for name in a.__dataclass_fields__:
            assert torch.equal(getattr(a, name), getattr(b, name)) and torch.equal(getattr(a, name), getattr(c, name))
    assert torch.equal(g2.get_state(), plain.get_state())  # the random stream goes on as without a checkpoint


def test_a_call_with_other_inputs_is_matched_again(tmp_path: Path) -> None:
    _calls(MatchingCheckpoint(tmp_path / "ckpt", "run-a"), torch.Generator().manual_seed(5))
    again = Counting()
    checkpoint = MatchingCheckpoint(tmp_path / "ckpt", "run-a", again)
    _calls(checkpoint, torch.Generator().manual_seed(6))  # another random state: nothing replayed
    assert again.calls == 2 and checkpoint.replayed == 0


def test_a_checkpoint_of_another_run_is_refused(tmp_path: Path) -> None:
    MatchingCheckpoint(tmp_path / "ckpt", "run-a")
    with pytest.raises(CheckpointError, match="another run"):
        MatchingCheckpoint(tmp_path / "ckpt", "run-b")


@pytest.mark.slow
def test_an_interrupted_localize_resumes_with_the_uninterrupted_result(tmp_path: Path) -> None:
    config = str(CONFIG_DIR / "tiny.yaml")
    sets = ["--set", "sim.trajectory.length_m=400", "--set", "sim.world.size_m=[200.0,200.0]"]
    runner = CliRunner()
    seq, mtm = tmp_path / "seq", tmp_path / "map.mtm"
    assert runner.invoke(app, ["simulate", "-o", str(seq), "-c", config, *sets]).exit_code == 0
    whole = runner.invoke(app, ["localize", str(seq), "-m", str(mtm), "-o", str(tmp_path / "whole"), "-c", config, *sets])
    assert whole.exit_code == 0, whole.output

    out = tmp_path / "resumed"
    command = [sys.executable, "-c", "from meridian_torch.cli import app; app()", "localize", str(seq), "-m", str(mtm),
               "-o", str(out), "-c", config, *sets]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    seen = []
    for line in proc.stdout:  # stop it once a few submaps were matched
        seen.append(line)
        if line.startswith("submap   2"):
            break
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=300)
    output = "".join(seen) + rest
    assert proc.returncode == 130, output
    assert "--resume continues from there" in output and not out.exists()
    checkpoint = tmp_path / ".resumed.checkpoint"
    assert len(list(checkpoint.glob("match-*.npz"))) >= 3

    resumed = runner.invoke(app, ["localize", str(seq), "-m", str(mtm), "-o", str(out), "-c", config, *sets, "--resume"])
    assert resumed.exit_code == 0, resumed.output
    replayed = int(resumed.output.split("resumed: ")[1].split()[0])
    assert replayed >= 3
    for name in ("trajectory.tum", "trajectory_incremental.tum", "covariance.csv", "covariance_incremental.csv",
                 "loop_closures.csv"):
        assert (out / name).read_text() == (tmp_path / "whole" / name).read_text(), name
    assert not checkpoint.exists(), "a complete run removes its checkpoint"

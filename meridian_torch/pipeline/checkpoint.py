"""Checkpoints of a localization run, so that an interrupted run resumes with the same result.

Matching is where a run spends its time (every submap against up to hundreds of patches before
the fix). `MatchingCheckpoint` wraps the matcher: each call's hypotheses are written to the
checkpoint folder as they are computed, with the solver's random state after the call. A resumed
run replays the whole pipeline (ground mapping, consistency and pose graphs are deterministic
and comparatively cheap) and takes the recorded result of every matching call whose inputs
(ground and aerial primitives, rotation prior, random state before the call) are exactly those
recorded, restoring the random state as the call left it. The result is therefore identical to
an uninterrupted run's, whatever was recorded. A checkpoint belongs to one run: `run_key` (the
config, the map and the sequence) must match, or it is refused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import shutil
from pathlib import Path

import numpy as np
import torch

from meridian_torch.backend.results import Matcher
from meridian_torch.errors import CheckpointError
from meridian_torch.io.atomic import write_bytes_atomic, write_text_atomic
from meridian_torch.matching.hypotheses import Hypotheses
from meridian_torch.matching.match import match_submap
from meridian_torch.types import PrimitiveBatch, PrimitiveSet

__all__ = ["MatchingCheckpoint", "run_key"]

_FORMAT = "meridian-torch localize checkpoint"
_META = "checkpoint.json"
_FIELDS = [f.name for f in dataclasses.fields(Hypotheses)]


def run_key(config_text: str, map_content_hash: str, sequence_files: list[Path]) -> str:
    """sha256 over what decides a run's result: the resolved config, the map and the sequence's
    frame list, odometry and camera files."""
    h = hashlib.sha256(config_text.encode())
    h.update(map_content_hash.encode())
    for path in sequence_files:
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _fingerprint(ground: PrimitiveSet, aerial: PrimitiveBatch, rotation_prior: object, state: torch.Tensor) -> str:
    h = hashlib.sha256()
    for part in (ground, aerial):
        for field in dataclasses.fields(part):
            t = getattr(part, field.name).detach().cpu().contiguous()
            h.update(f"{field.name}{tuple(t.shape)}{t.dtype}".encode())
            h.update(t.numpy().tobytes())
    prior = None if rotation_prior is None else torch.as_tensor(rotation_prior).detach().cpu().double().numpy()
    h.update(b"none" if prior is None else prior.tobytes())
    h.update(state.numpy().tobytes())
    return h.hexdigest()


class MatchingCheckpoint:
    """A `Matcher` that records every call in `folder` and replays recorded calls on a resumed run.

    Args:
        folder: the checkpoint folder (created; a folder of another run is refused).
        key: `run_key` of this run.
        matcher: the matcher that does the work (default `match_submap`).
    """

    def __init__(self, folder: Path, key: str, matcher: Matcher = match_submap) -> None:
        self.folder = Path(folder)
        self._matcher = matcher
        self._calls = 0
        self.replayed = 0  # calls answered from the checkpoint
        meta = self.folder / _META
        if meta.exists():
            try:
                stored = json.loads(meta.read_text())
            except (OSError, ValueError) as error:
                raise CheckpointError(f"{meta}: unreadable ({error}); delete {self.folder} to start afresh") from None
            if stored.get("format") != _FORMAT or stored.get("run") != key:
                raise CheckpointError(f"{self.folder}: a checkpoint of another run (other sequence, map or config); "
                                      "delete it, or run without --resume to start afresh")
        else:
            self.folder.mkdir(parents=True, exist_ok=True)
            write_text_atomic(meta, json.dumps({"format": _FORMAT, "run": key}) + "\n")

    @property
    def recorded(self) -> int:
        """Matching results in the folder."""
        return len(list(self.folder.glob("match-*.npz")))

    def discard(self) -> None:
        """Delete the checkpoint (the run is complete)."""
        shutil.rmtree(self.folder, ignore_errors=True)

    def __call__(
        self,
        ground: PrimitiveSet,
        aerial: PrimitiveBatch,
        *,
        rotation_prior: torch.Tensor | float | None,
        config: object,
        generator: torch.Generator | None,
    ) -> Hypotheses:
        if generator is None:
            raise ValueError("a checkpointed matcher needs the run's generator (its state is part of the record)")
        path = self.folder / f"match-{self._calls:06d}.npz"
        self._calls += 1
        key = _fingerprint(ground, aerial, rotation_prior, generator.get_state())
        recorded = self._read(path, key)
        if recorded is not None:
            hypotheses, state = recorded
            generator.set_state(state)
            self.replayed += 1
            return Hypotheses(**{name: t.to(aerial.points_xy.device) for name, t in hypotheses.items()})
        hypotheses = self._matcher(ground, aerial, rotation_prior=rotation_prior, config=config, generator=generator)
        buffer = io.BytesIO()
        np.savez(buffer, key=np.array(key), state=generator.get_state().numpy(),
                 **{name: getattr(hypotheses, name).detach().cpu().numpy() for name in _FIELDS})
        write_bytes_atomic(path, buffer.getvalue())
        return hypotheses

    @staticmethod
    def _read(path: Path, key: str) -> tuple[dict[str, torch.Tensor], torch.Tensor] | None:
        """The recorded call at `path` if its inputs were `key`; None when absent, other or damaged
        (then the call is computed again and the record replaced)."""
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["key"]) != key:
                    return None
                return {name: torch.from_numpy(z[name].copy()) for name in _FIELDS}, torch.from_numpy(z["state"].copy())
        except (OSError, ValueError, KeyError, EOFError):
            return None

"""What a run needs before its work starts: the output folder checked, the sequence opened and
checked, the aerial map loaded and checked, and the key its checkpoint belongs to."""

from __future__ import annotations

import json
from pathlib import Path

from meridian_torch.config import MeridianConfig, dump_config
from meridian_torch.errors import OutputExistsError
from meridian_torch.io.map_file import MapFileError, georeference_mismatches, load_aerial_map
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.io.run_info import RUN_FILE
from meridian_torch.io.sequence import SequenceReader
from meridian_torch.mapping.aerial_map import map_config_dict
from meridian_torch.pipeline.checkpoint import run_key
from meridian_torch.types import AerialMap

__all__ = ["checkpoint_key", "open_aerial_map", "open_sequence", "refuse_foreign_folder"]


def refuse_foreign_folder(out: Path, overwrite: bool, command: str | None = None) -> None:
    """An output folder that holds files is refused without --overwrite, unless `command` is given
    and the folder is that command's own earlier output (its run.json says so)."""
    if not out.exists():
        return
    if out.is_dir() and not any(out.iterdir()):
        return
    if overwrite:
        return
    if command is not None and out.is_dir():
        try:
            ours = json.loads((out / RUN_FILE).read_text()).get("command") == command
        except (OSError, ValueError, AttributeError):
            ours = False
        if ours:
            return
    raise OutputExistsError(f"{out}: already exists and holds files; pass --overwrite to replace it, or choose "
                            "another output folder")


def open_sequence(cfg: MeridianConfig, sequence: Path) -> tuple[SequenceReader, Orthophoto]:
    """The sequence reader and its orthophoto, checked before any work: the folder's files, odometry
    gaps, the orthophoto and its georeference (a problem found here costs seconds, not a run)."""
    reader = SequenceReader(sequence)
    reader.require_odometry_without_gaps(cfg.ground_map.max_odometry_gap_s)
    return reader, reader.ortho()


def open_aerial_map(cfg: MeridianConfig, map_path: Path, ortho_path: Path, ortho: Orthophoto | None = None
                    ) -> AerialMap:
    """The aerial map at `map_path`; its config must match, and its georeference that of `ortho`
    (the orthophoto of the sequence at `ortho_path`) when given."""
    map_config = map_config_dict(cfg.aerial_map, cfg.perception, cfg.primitives)
    aerial_map = load_aerial_map(map_path, expected_config=map_config)
    mismatches = [] if ortho is None else georeference_mismatches(aerial_map, ortho)
    if mismatches:
        raise MapFileError(f"{map_path}: built from another orthophoto than {ortho_path}'s ("
                           + "; ".join(mismatches) + "); rebuild it (choose another --map or delete this one)")
    return aerial_map


def checkpoint_key(cfg: MeridianConfig, aerial_map: AerialMap, sequence: Path) -> str:
    """What a checkpoint must belong to: the resolved config, the map and the sequence's files."""
    ground = sequence / "ground"
    return run_key(dump_config(cfg), aerial_map.content_hash,
                   [ground / "frames.csv", ground / "odometry.tum", ground / "camera.json"])

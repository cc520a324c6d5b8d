"""The map-ground output folder: the submaps (submaps.mts), the run's config and info, and a plot
per submap, over the orthophoto through the ground-truth pose when the sequence has one."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from meridian_torch.config import MeridianConfig
from meridian_torch.geometry.se3 import se3_inverse
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.io.run_info import write_run_info
from meridian_torch.io.sequence import SequenceReader
from meridian_torch.io.submap_file import save_ground_submaps
from meridian_torch.mapping.ground_map import GroundMapper, ground_map_config_dict
from meridian_torch.types import GroundSubmap

__all__ = ["write_ground_map_folder"]


def write_ground_map_folder(folder: Path, cfg: MeridianConfig, sequence: Path, reader: SequenceReader,
                            ortho: Orthophoto, mapper: GroundMapper, submaps: list[GroundSubmap], *,
                            plots: bool) -> None:
    """Write the submaps `mapper` made of `sequence` into `folder`, with the run info and, with
    `plots`, folder/plots/submap_NNN.png."""
    save_ground_submaps(submaps, folder / "submaps.mts", config=ground_map_config_dict(cfg),
                        source={"sequence": str(sequence.resolve())},
                        descriptor_dim=mapper.describer.dim, global_descriptor_dim=mapper.global_describer.dim)
    write_run_info(folder, cfg, "map-ground")
    if plots:
        from meridian_torch.evaluation.plots import plot_ground_submap

        for submap, geometry in zip(submaps, mapper.geometries, strict=True):
            T_world_odom = None
            if reader.groundtruth is not None and reader.groundtruth.covers(np.array([submap.time])):
                T_world_odom = reader.groundtruth.interpolate(np.array([submap.time]))[0] @ se3_inverse(
                    submap.T_odom_base)
            plot_ground_submap(submap, folder / "plots" / f"submap_{submap.index:03d}.png", geometry=geometry,
                               ortho=ortho if reader.groundtruth is not None else None, T_world_odom=T_world_odom)

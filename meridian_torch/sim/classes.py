"""Semantic classes of simulated worlds, with the colours the renderers start from."""

from __future__ import annotations

from enum import IntEnum

import numpy as np

__all__ = ["SimClass", "CLASS_NAMES", "BASE_COLOURS", "class_by_name", "OBJECT_CLASSES", "REGION_CLASSES"]


class SimClass(IntEnum):
    GRASS = 0
    SOIL = 1
    WATER = 2
    ROAD = 3
    PARKING = 4
    SIDEWALK = 5
    BUILDING = 6
    TREE = 7
    BUSH = 8
    ROCK = 9
    CAR = 10
    FENCE = 11


CLASS_NAMES: dict[int, str] = {c.value: c.name.lower() for c in SimClass}

# Linear RGB in [0, 1] seen from above (roofs, canopy, ground); renderers add texture and light.
BASE_COLOURS = np.array(
    [
        [0.30, 0.50, 0.20],  # grass
        [0.50, 0.40, 0.28],  # soil
        [0.12, 0.22, 0.32],  # water
        [0.28, 0.28, 0.30],  # road
        [0.38, 0.38, 0.40],  # parking
        [0.62, 0.60, 0.56],  # sidewalk
        [0.55, 0.35, 0.30],  # building roof
        [0.16, 0.36, 0.14],  # tree canopy
        [0.24, 0.42, 0.18],  # bush
        [0.52, 0.50, 0.48],  # rock
        [0.60, 0.10, 0.10],  # car
        [0.45, 0.38, 0.30],  # fence
    ],
    dtype=np.float32,
)

# Compact things that become point primitives vs. areas whose borders become lines.
OBJECT_CLASSES = (SimClass.BUILDING, SimClass.TREE, SimClass.BUSH, SimClass.ROCK, SimClass.CAR)
REGION_CLASSES = (SimClass.GRASS, SimClass.SOIL, SimClass.WATER, SimClass.ROAD, SimClass.PARKING, SimClass.SIDEWALK)


def class_by_name(name: str) -> SimClass:
    try:
        return SimClass[name.upper()]
    except KeyError:
        raise ValueError(f"unknown class {name!r}; known: {', '.join(CLASS_NAMES.values())}") from None

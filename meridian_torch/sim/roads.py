"""Road centrelines of any world: their junction graph and points sampled along them."""

from __future__ import annotations

import networkx as nx
import numpy as np
import shapely
from shapely.geometry import LineString
from shapely.ops import linemerge

from meridian_torch.errors import SimulationError

__all__ = ["road_graph", "road_samples"]


def road_graph(centrelines: list[np.ndarray]) -> nx.MultiGraph:
    """Junction graph of road centrelines: lines are split where they cross and merged through
    degree-2 points. Nodes carry `xy`; edges carry `xy` (K, 2) running from `start` node."""
    lines = [LineString(c) for c in centrelines if len(c) >= 2]
    if not lines:
        raise SimulationError("the world has no road centrelines")
    noded = shapely.union_all(lines)
    merged = linemerge(noded) if not isinstance(noded, LineString) else noded
    parts = list(merged.geoms) if hasattr(merged, "geoms") else [merged]
    g = nx.MultiGraph()
    index: dict[tuple[float, float], int] = {}

    def node(p: np.ndarray) -> int:
        key = (round(float(p[0]), 3), round(float(p[1]), 3))
        if key not in index:
            index[key] = len(index)
            g.add_node(index[key], xy=np.array(key))
        return index[key]

    for part in parts:
        xy = np.asarray(part.coords)[:, :2]
        if part.length < 1e-6:
            continue
        u, v = node(xy[0]), node(xy[-1])
        g.add_edge(u, v, xy=xy, start=u, length=float(part.length))
    return g


def road_samples(lines: list[np.ndarray], step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step` metres along all centrelines and their unit tangents."""
    pts, tans = [], []
    for line in lines:
        ls = LineString(line)
        s = np.arange(0.0, ls.length, step)
        p = shapely.get_coordinates(shapely.line_interpolate_point(ls, s))
        q = shapely.get_coordinates(shapely.line_interpolate_point(ls, np.minimum(s + 0.5, ls.length)))
        d = q - p
        d[-1] = d[-2] if len(d) > 1 else d[-1]
        pts.append(p)
        tans.append(d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9))
    return np.concatenate(pts), np.concatenate(tans)

"""onnxruntime inference: open a graph file, read its signature and metadata, run it. Used by the
ONNX back ends (perception) and by the exporter's parity checks; onnxruntime is imported inside
`open_session` only."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from meridian_torch.errors import ModelWeightsError

__all__ = ["Dim", "GraphSignature", "graph_metadata", "graph_signature", "open_session", "run_session"]

Dim = int | str  # a fixed ONNX dimension or the name of a symbolic one


@dataclass(frozen=True)
class GraphSignature:
    """Input and output names, shapes and element types of an ONNX graph."""

    inputs: dict[str, tuple[Dim, ...]]
    outputs: dict[str, tuple[Dim, ...]]
    input_types: dict[str, str]  # e.g. "tensor(float)"


def _shape_of(value_info: Any) -> tuple[Dim, ...]:
    dims = []
    for i, d in enumerate(value_info.shape):
        dims.append(d if isinstance(d, int) else (str(d) if d is not None else f"?{i}"))
    return tuple(dims)


def open_session(path: str | os.PathLike[str], what: str = "ONNX model") -> Any:
    """An onnxruntime CPU session for `path`; a missing or unreadable file is a ModelWeightsError naming it."""
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise ModelWeightsError(f"{what} not found: {path} (models are never downloaded; see models/README.md)")
    options = ort.SessionOptions()
    options.log_severity_level = 3  # errors only; the exporter's graphs trigger harmless warnings
    try:
        return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises several unrelated types for unusable files
        raise ModelWeightsError(f"{path}: not a usable ONNX model ({type(exc).__name__}: {exc})") from None


def graph_signature(session: Any) -> GraphSignature:
    """The names, shapes and types of a session's graph inputs and outputs."""
    return GraphSignature(
        inputs={i.name: _shape_of(i) for i in session.get_inputs()},
        outputs={o.name: _shape_of(o) for o in session.get_outputs()},
        input_types={i.name: i.type for i in session.get_inputs()},
    )


def run_session(session: Any, inputs: Mapping[str, np.ndarray]) -> list[np.ndarray]:
    """Run `session` on named numpy inputs and return every output in graph order."""
    return session.run(None, dict(inputs))


def graph_metadata(session: Any) -> dict[str, str]:
    """The key/value metadata stored in a session's model (empty for graphs exported elsewhere)."""
    return dict(session.get_modelmeta().custom_metadata_map)

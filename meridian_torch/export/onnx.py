"""Export torch modules to ONNX, checked against eager torch with onnxruntime before the file is written.

Exporter choice (torch 2.14, measured on our models): the legacy TorchScript exporter is the
default. It exports all five models (DINOv2 dense features and AnyLoc facet with dynamic batch and
image size, the VLAD head, the SAM encoder and decoder) with parity, 5-10x faster than the
torch.export-based ("dynamo") exporter, which fails on the SAM encoder's windowed attention (an
invalid view after decomposition). Dynamo stays selectable: it is the one that translates
antialiased bicubic `F.interpolate` with input-dependent sizes (timm-style ViT position-embedding
interpolation), which the legacy exporter rejects.

Every export runs onnxruntime on the example inputs and on each `check_inputs` set (a second
batch/image size when axes are dynamic, which also catches sizes the exporter silently fixed) and
compares with eager torch; only a file within tolerance is moved into place. onnx and
onnxruntime are imported inside the functions of this module only.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from meridian_torch.core.onnx_runtime import Dim, graph_signature, open_session, run_session
from meridian_torch.errors import ExportError

__all__ = [
    "ParityCheck",
    "ExportReport",
    "export_checked",
]

_log = logging.getLogger(__name__)

# Above this many bytes of weights the graph keeps them in FILE.onnx.data (protobuf's 2 GiB limit).
EXTERNAL_DATA_MIN_BYTES = 1 << 30

Exporter = Literal["legacy", "dynamo"]


@dataclass(frozen=True)
class ParityCheck:
    """onnxruntime vs eager torch on one set of inputs."""

    input_shapes: tuple[tuple[int, ...], ...]
    max_abs_diff: dict[str, float]  # per output name
    within_tolerance: bool


@dataclass(frozen=True)
class ExportReport:
    """What was exported and how closely onnxruntime reproduces eager torch."""

    path: Path
    exporter: Exporter
    inputs: dict[str, tuple[Dim, ...]]  # graph input shapes, symbolic dims by name
    outputs: dict[str, tuple[Dim, ...]]
    checks: tuple[ParityCheck, ...]
    atol: float
    rtol: float
    size_bytes: int  # model file plus external data, if any

    @property
    def max_abs_diff(self) -> float:
        """Largest absolute difference over every output of every check."""
        return max(d for c in self.checks for d in c.max_abs_diff.values())


def _as_tuple(outputs: Any) -> tuple[torch.Tensor, ...]:
    if isinstance(outputs, torch.Tensor):
        return (outputs,)
    if isinstance(outputs, (tuple, list)) and all(isinstance(o, torch.Tensor) for o in outputs):
        return tuple(outputs)
    raise TypeError(f"export needs a module returning a tensor or a tuple of tensors, got {type(outputs).__name__}")


def _compare(
    path: Path,
    session: Any,
    module: nn.Module,
    inputs: tuple[torch.Tensor, ...],
    input_names: Sequence[str],
    output_names: Sequence[str],
    atol: float,
    rtol: float,
) -> ParityCheck:
    with torch.no_grad():
        expected = _as_tuple(module(*inputs))
    feeds = {name: t.detach().cpu().numpy() for name, t in zip(input_names, inputs)}
    try:
        got = run_session(session, feeds)
    except Exception as exc:  # e.g. a dimension the exporter fixed although it was declared dynamic
        shapes = [tuple(t.shape) for t in inputs]
        raise ExportError(f"{path}: onnxruntime failed on inputs of shapes {shapes} (a dynamic size the exporter "
                          f"fixed?): {type(exc).__name__}: {exc}") from None
    diffs: dict[str, float] = {}
    ok = True
    for name, ref, out in zip(output_names, expected, got):
        ref_np = ref.detach().cpu().numpy()
        if out.shape != ref_np.shape:
            raise ExportError(f"{path}: output {name!r} has shape {out.shape} in onnxruntime but {ref_np.shape} in "
                              f"torch on inputs {[tuple(t.shape) for t in inputs]}")
        ref64, out64 = ref_np.astype(np.float64), out.astype(np.float64)
        err = np.abs(out64 - ref64)
        diffs[name] = float(err.max()) if err.size else 0.0
        ok &= bool(np.all(err <= atol + rtol * np.abs(ref64)))
    return ParityCheck(tuple(tuple(t.shape) for t in inputs), diffs, ok)


def _finalize(target: Path, metadata: Mapping[str, str]) -> None:
    """Store `metadata` in the model and gather any external weights into one `target.name + ".data"`.

    Exporters write weights beyond protobuf's 2 GiB limit next to the model, the legacy one as
    one file per tensor; a single data file is what users can move around.
    """
    import onnx

    others = [f for f in target.parent.iterdir() if f != target]
    if not metadata and not others:
        return
    model = onnx.load(str(target), load_external_data=bool(others))
    for key, value in metadata.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = str(key), str(value)
    if others:
        for f in others:
            f.unlink()
        onnx.save(model, str(target), save_as_external_data=True, all_tensors_to_one_file=True,
                  location=target.name + ".data")
    else:
        onnx.save(model, str(target))


def _export(
    module: nn.Module,
    example_inputs: tuple[torch.Tensor, ...],
    target: Path,
    input_names: Sequence[str],
    output_names: Sequence[str],
    dynamic_axes: Mapping[str, Sequence[int]],
    opset: int,
    exporter: Exporter,
    external_data: bool,
) -> None:
    if exporter == "dynamo":
        # one spec per positional input; an axis marked DYNAMIC stays symbolic unless the model fixes it
        shapes = tuple(
            {axis: torch.export.Dim.DYNAMIC for axis in dynamic_axes[name]} if name in dynamic_axes else None
            for name in input_names
        )
        torch.onnx.export(
            module, example_inputs, str(target), input_names=list(input_names), output_names=list(output_names),
            opset_version=opset, dynamo=True, dynamic_shapes=shapes, external_data=external_data, verbose=False,
        )
    else:
        axes = {name: {a: f"{name}_{a}" for a in dims} for name, dims in dynamic_axes.items()}
        torch.onnx.export(
            module, example_inputs, str(target), input_names=list(input_names), output_names=list(output_names),
            opset_version=opset, dynamo=False, dynamic_axes=axes or None,
        )


def export_checked(
    module: nn.Module,
    example_inputs: tuple[torch.Tensor, ...],
    path: str | os.PathLike[str],
    *,
    input_names: Sequence[str],
    output_names: Sequence[str],
    dynamic_axes: Mapping[str, Sequence[int]] | None = None,
    check_inputs: Sequence[tuple[torch.Tensor, ...]] = (),
    atol: float = 1e-4,
    rtol: float = 1e-3,
    opset: int = 18,
    exporter: Exporter = "legacy",
    metadata: Mapping[str, str] | None = None,
) -> ExportReport:
    """Export `module(*example_inputs)` to `path` and write it only if onnxruntime matches eager torch.

    Args:
        module: an eval-mode module on the CPU returning a tensor or a tuple of tensors.
        example_inputs: positional inputs used for tracing and the first parity check.
        path: destination `.onnx`; weights above 1 GiB go to `path` + ".data" next to it.
        input_names, output_names: graph names, one per input and output.
        dynamic_axes: input name -> axes that stay symbolic (e.g. {"images": [0, 2, 3]}).
        check_inputs: further input sets (other batch/image sizes) to check; required when
            `dynamic_axes` is set, since a dimension the exporter fixed shows only at another size.
        atol, rtol: every output element must satisfy |ort - torch| <= atol + rtol * |torch|.
        exporter: "legacy" (TorchScript) or "dynamo" (torch.export); see the module docstring.
        metadata: key/value strings stored in the model (what it is, which weights), which the
            onnxruntime back ends compare with their config.

    Returns:
        The report with per-check max abs differences. Raises ExportError (nothing is written) if
        the export fails, onnxruntime fails, or a difference is out of tolerance.
    """
    dynamic_axes = dict(dynamic_axes or {})
    if len(input_names) != len(example_inputs):
        raise ValueError(f"{len(input_names)} input names for {len(example_inputs)} example inputs")
    if unknown := set(dynamic_axes) - set(input_names):
        raise ValueError(f"dynamic_axes names unknown inputs {sorted(unknown)}")
    if dynamic_axes and not check_inputs:
        raise ValueError("dynamic_axes need check_inputs of another size to prove the axes really are dynamic")
    path = Path(path)
    module = module.eval()
    weight_bytes = sum(t.numel() * t.element_size() for t in module.state_dict().values())
    external_data = weight_bytes > EXTERNAL_DATA_MIN_BYTES
    path.parent.mkdir(parents=True, exist_ok=True)
    # Export into a hidden sibling folder under the final file name (external data references it
    # by name), check there, then rename into place: a failed check leaves `path` untouched.
    staging = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.tmp-"))
    try:
        target = staging / path.name
        try:
            with warnings.catch_warnings():  # tracing notes on constants are expected; parity is checked below
                warnings.simplefilter("ignore", torch.jit.TracerWarning)
                # legacy is chosen knowingly for torch 2.14 (module docstring): silence its deprecation notes
                warnings.simplefilter("ignore", DeprecationWarning)
                _export(module, example_inputs, target, input_names, output_names, dynamic_axes, opset, exporter,
                        external_data)
        except Exception as exc:  # the exporters raise many unrelated types
            raise ExportError(f"{path}: torch.onnx {exporter} export of {type(module).__name__} failed: "
                              f"{type(exc).__name__}: {exc}") from None
        _finalize(target, metadata or {})
        session = open_session(target)
        signature = graph_signature(session)
        if list(signature.inputs) != list(input_names) or list(signature.outputs) != list(output_names):
            raise ExportError(f"{path}: graph has inputs {list(signature.inputs)} and outputs "
                              f"{list(signature.outputs)}, expected {list(input_names)} and {list(output_names)}")
        for name, axes in dynamic_axes.items():
            fixed = [a for a in axes if isinstance(signature.inputs[name][a], int)]
            if fixed:
                raise ExportError(f"{path}: input {name!r} axes {fixed} were declared dynamic but the exporter fixed "
                                  f"them to {[signature.inputs[name][a] for a in fixed]} (use example sizes >= 2)")
        checks = tuple(
            _compare(path, session, module, tuple(inputs), input_names, output_names, atol, rtol)
            for inputs in (example_inputs, *check_inputs)
        )
        del session  # release the file before renaming (matters on Windows)
        for check in checks:
            if not check.within_tolerance:
                raise ExportError(f"{path}: onnxruntime differs from torch beyond atol={atol}, rtol={rtol} on inputs "
                                  f"{list(check.input_shapes)}: max abs differences {check.max_abs_diff}")
        size = sum(f.stat().st_size for f in staging.iterdir())
        data = staging / (path.name + ".data")
        if data.exists():
            os.replace(data, path.with_name(data.name))
        os.replace(target, path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    report = ExportReport(path, exporter, signature.inputs, signature.outputs, checks, atol,
                          rtol, size)
    _log.info("exported %s: max abs difference %.3g over %d checks", path, report.max_abs_diff, len(checks))
    return report

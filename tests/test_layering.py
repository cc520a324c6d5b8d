"""The package's layers import only downwards (ARCHITECTURE.md): statically over every import in
the source (module level and inside functions), and in fresh interpreters, where importing a
layer's modules must not load anything above it."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

import meridian_torch

PACKAGE = Path(meridian_torch.__file__).parent

# Lowest first; a unit may import its own layer's units and any layer below. Units are the
# top-level modules and sub-packages of meridian_torch ("" is the package itself: __version__).
LAYERS: list[set[str]] = [
    {"", "errors", "types", "core", "geometry", "config", "runtime"},  # foundations
    {"io"},  # file formats
    {"perception", "sim"},  # models; the simulator (writes sequences through io)
    {"mapping", "matching"},  # aerial and ground primitives; matching
    {"backend"},  # loop-closure pool, consistency, pose graph, localizer
    {"evaluation", "export"},  # metrics and reports; ONNX export of the perception models
    {"pipeline"},  # orchestration: live, sequence runs, output folders
    {"cli"},
]
# Known upward imports, each with why it is still there. Keep this list short; an entry that no
# longer occurs fails the test so that it is removed.
ALLOWED_UPWARD = {
    ("meridian_torch.perception.factory", "meridian_torch.export.tiny_yolo_seg"):
        "the tiny random FastSAM stand-in for tests is exported to ONNX before it can run (lazy import)",
}


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _layer(unit: str) -> int:
    return next(i for i, layer in enumerate(LAYERS) if unit in layer)


def _imports() -> list[tuple[str, str]]:
    """(importing module, imported meridian_torch module) for every import statement."""
    edges = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        module = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                targets = [node.module]
            elif isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                continue
            edges += [(module, t) for t in targets if t == "meridian_torch" or t.startswith("meridian_torch.")]
    return edges


def test_every_unit_has_a_layer() -> None:
    units = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()
             if (p.is_file() and p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").is_file()}
    placed = set().union(*LAYERS) - {""}
    assert units == placed, f"units without a layer: {sorted(units - placed)}; layers naming no unit: {sorted(placed - units)}"


def test_imports_only_go_down() -> None:
    upward, seen_allowed = [], set()
    for source, target in _imports():
        if _layer(_unit(target)) <= _layer(_unit(source)):
            continue
        if (source, target) in ALLOWED_UPWARD:
            seen_allowed.add((source, target))
        else:
            upward.append(f"{source} imports {target}")
    assert not upward, "imports that run upwards:\n" + "\n".join(upward)
    assert seen_allowed == set(ALLOWED_UPWARD), f"allowed upward imports no longer used: {set(ALLOWED_UPWARD) - seen_allowed}"


def test_no_cycles_between_units() -> None:
    graph: dict[str, set[str]] = {}
    for source, target in _imports():
        if (source, target) not in ALLOWED_UPWARD and _unit(source) != _unit(target):
            graph.setdefault(_unit(source), set()).add(_unit(target))

    def reach(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for nxt in graph.get(todo.pop(), ()):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    cycles = sorted(u for u in graph if u in reach(u))
    assert not cycles, f"units on an import cycle: {cycles}"


def _loaded_units(module: str) -> set[str]:
    code = ("import json, sys; import " + module + "; "
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith('meridian_torch'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return {_unit(m) for m in json.loads(out.splitlines()[-1])}


@pytest.mark.parametrize("module", [
    "meridian_torch.config",
    "meridian_torch.types",
    "meridian_torch.geometry.se3",
    "meridian_torch.io.results",
    "meridian_torch.io.map_file",
    "meridian_torch.io.sequence",
    "meridian_torch.evaluation.trajectory_metrics",
    "meridian_torch.matching.match",
    "meridian_torch.mapping.ground_map",
    "meridian_torch.backend.localizer",
    "meridian_torch.pipeline",
])
def test_a_fresh_interpreter_loads_nothing_above_the_layer(module: str) -> None:
    own = _layer(_unit(module))
    above = {u for u in _loaded_units(module) if _layer(u) > own}
    assert not above, f"importing {module} loads {sorted(above)}"


def test_trajectory_metrics_load_no_stage_code() -> None:
    """An ATE from two TUM files needs file formats and geometry, not the matcher or the models."""
    loaded = _loaded_units("meridian_torch.evaluation.trajectory_metrics")
    assert loaded <= LAYERS[0] | {"io", "evaluation"}, sorted(loaded)

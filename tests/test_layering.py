"""The package's layering, read from the source: no import cycles, and no module importing from a layer above it."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "udh_cli"

# Each layer may import from the layers listed before it, never after. Top-level modules not named here
# (errors, geometry, images, ...) form the base that every layer may use.
LAYERS = ["estimators", "mosaic", "bench", "train", "api", "cli", "cli_mosaic"]
TORCH_FREE = ["estimators", "mosaic", "bench", "api", "geometry", "images", "onnx_model", "synthetic", "flight_motion"]


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path) -> set[str]:
    """Every udh_cli module ``path`` imports, at module level or inside functions, outside TYPE_CHECKING."""
    tree = ast.parse(path.read_text())
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.startswith("udh_cli"))
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("udh_cli"):
            for alias in node.names:
                candidate = f"{node.module}.{alias.name}"
                found.add(candidate if (PACKAGE.parent / candidate.replace(".", "/")).with_suffix(".py").is_file() else node.module)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {name: {m for m in imports_of(path) if m in modules and m != name} for name, path in modules.items()}


def layer_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else None


def test_no_import_cycles(graph):
    cycles, state = [], {}

    def walk(node: str, stack: list[str]) -> None:
        state[node] = "open"
        for target in sorted(graph[node]):
            if state.get(target) == "open":
                cycles.append(stack[stack.index(target):] + [target])
            elif target not in state:
                walk(target, stack + [target])
        state[node] = "done"

    for start in sorted(graph):
        if start not in state:
            walk(start, [start])
    assert not cycles, cycles


def test_no_module_imports_from_a_layer_above_it(graph):
    wrong = []
    front_doors = {"udh_cli", "udh_cli.__main__"}  # the package's re-exports and `python -m udh_cli` sit above all
    for module, targets in graph.items():
        if module in front_doors:
            continue
        own = layer_of(module)
        for target in targets:
            other = layer_of(target)
            if other is None or own == other:
                continue
            if own is None or LAYERS.index(other) > LAYERS.index(own):
                wrong.append(f"{module} -> {target}")
    assert not wrong, wrong


def test_the_geometry_core_imports_nothing_of_udh(graph):
    assert graph["udh_cli.geometry"] == set()


def test_inference_never_imports_torch():
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        name = module_name(path)
        if any(name == f"udh_cli.{part}" or name.startswith(f"udh_cli.{part}.") for part in TORCH_FREE):
            if "import torch" in path.read_text() or "from torch" in path.read_text():
                offenders.append(name)
    assert not offenders, offenders

"""The package's layering, read from the source: no import cycles, and no module importing from a layer above it.

The graph holds every import of a udh_cli module: at module level, inside functions (a lazy import still ties the two
modules together when it runs) and under ``if TYPE_CHECKING:`` (a type checker follows it as an import).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "udh_cli"

# Each layer may import from the layers listed before it, never after. Top-level modules not named here
# (errors, geometry, images, ...) form the base that every layer may use.
LAYERS = ["estimators", "mosaic", "bench", "train", "api", "cli", "cli_mosaic", "cli_bench"]
# Inside udh_cli/mosaic/: the progress reporter, then the stage folders in this order (a folder may import its own
# modules and the folders before it), then the run's own modules (config, sidecar, its report page, run, the arrays API),
# then live mode over them.
MOSAIC_BASE = ["report"]
MOSAIC_STAGES = ["outputs", "inputs", "georef", "pairs", "solve", "render"]
MOSAIC_RUN = ["config", "sidecar", "report_page", "run", "arrays"]
MOSAIC_TOP = ["live"]
TORCH_FREE = ["estimators", "mosaic", "bench", "api", "geometry", "images", "onnx_model", "synthetic", "flight_motion"]


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path) -> set[str]:
    """Every udh_cli module ``path`` imports: at module level, inside functions and under TYPE_CHECKING."""
    tree = ast.parse(path.read_text())
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
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


def test_the_graph_holds_type_checking_and_function_level_imports(tmp_path):
    source = tmp_path / "module.py"
    source.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from udh_cli.errors import UdhError\n"
                      "def lazy():\n    from udh_cli import geometry\n")
    assert imports_of(source) == {"udh_cli.errors", "udh_cli.geometry"}


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


def mosaic_rank(module: str) -> tuple[int, str] | None:
    """Where a module of udh_cli.mosaic sits: (rank, its group); None outside the mosaic package or for its front door."""
    parts = module.split(".")
    if parts[:2] != ["udh_cli", "mosaic"] or len(parts) < 3:
        return None
    ordered = [*MOSAIC_BASE, *MOSAIC_STAGES, "run level", *MOSAIC_TOP]
    name = "run level" if parts[2] in MOSAIC_RUN else parts[2]
    assert name in ordered, f"{module}: not in the mosaic's layers; add its folder to MOSAIC_STAGES (or MOSAIC_RUN) in order"
    return ordered.index(name), name


def test_mosaic_stage_folders_import_only_earlier_stages(graph):
    wrong = []
    for module, targets in graph.items():
        own = mosaic_rank(module)
        if own is None:
            continue
        for target in targets:
            other = mosaic_rank(target)
            if other is None and target == "udh_cli.mosaic":
                wrong.append(f"{module} -> {target} (the package's front door)")
            elif other is not None and other[0] > own[0]:
                wrong.append(f"{module} -> {target}")
    assert not wrong, wrong


def test_stage_folders_never_import_the_run(graph):
    stages = [m for m in graph if (mosaic_rank(m) or (0, ""))[1] in MOSAIC_STAGES]
    assert len({mosaic_rank(m)[1] for m in stages}) >= 4
    run_level = {f"udh_cli.mosaic.{name}" for name in MOSAIC_RUN}
    assert not [f"{m} -> {t}" for m in stages for t in graph[m] if t in run_level]


def test_no_mosaic_module_is_longer_than_450_lines():
    long = {module_name(p): n for p in (PACKAGE / "mosaic").rglob("*.py") if (n := len(p.read_text().splitlines())) > 450}
    assert not long, long


def test_every_package_folder_is_listed_for_installation():
    import tomllib

    listed = set(tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {module_name(p) for p in PACKAGE.rglob("__init__.py")}
    assert folders <= listed, sorted(folders - listed)  # a folder left out is missing from `pip install .`

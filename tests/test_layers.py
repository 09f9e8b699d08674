"""The package's imports run one way: each module imports only from its own layer or the layers below, and no
group of modules imports itself in a circle.

The layers, bottom first (a module is placed by its longest listed prefix; a package's ``__init__`` belongs to the
package). Imports at any depth count, those inside functions too: a function-local import is still a dependency.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "occkit"

#: Bottom first. Within a layer modules may import each other, without cycles.
LAYERS: tuple[tuple[str, ...], ...] = (
    # plain values, shapes and the geometry every other layer computes with
    ("occkit.errors", "occkit.config", "occkit.classes", "occkit.types", "occkit.geometry", "occkit.label_space",
     "occkit.label_files", "occkit.arguments", "occkit.nuscenes", "occkit.figure", "occkit.weight_files",
     "occkit.archives", "occkit.outputs", "occkit.shipped", "occkit.machine"),
    # reading and writing datasets; the synthetic world writes what data reads, importing nothing of it; labels
    # built from a dataset's sensor data
    ("occkit.data", "occkit.sim", "occkit.labeling"),
    # what an experiment is: plain settings, no model code
    ("occkit.experiment",),
    # what a model is scored and trained against
    ("occkit.losses", "occkit.metrics"),
    ("occkit.models",),
    # names -> experiments and models; reference checkpoints -> an entry's weights (the engine's load_from uses it)
    ("occkit.zoo", "occkit.convert"),
    # training, evaluation, prediction; where a command's model comes from
    ("occkit.engine", "occkit.model_source"),
    # consumers of trained models
    ("occkit.bench", "occkit.export", "occkit.onnx_runtime", "occkit.quantization", "occkit.viz", "occkit.environment",
     "occkit.robustness"),
    ("occkit.demo",),
    ("occkit.cli", "occkit.commands", "occkit.__main__"),
)  # fmt: skip


#: Packages of one layer that never import each other.
INDEPENDENT: tuple[tuple[str, str], ...] = (("occkit.data", "occkit.sim"), ("occkit.labeling", "occkit.sim"))

#: Imports the layer order allows but the design does not: a model knows nothing of datasets or schedules (a zoo
#: entry, ``occkit/zoo/<family>.py``, pairs a model config with them).
FORBIDDEN: tuple[tuple[str, str], ...] = (
    ("occkit.models", "occkit.data.dataset"),
    ("occkit.models", "occkit.experiment"),
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module: str) -> int:
    if module == "occkit":  # the package's face: its version, nothing else
        return 0
    matches = [(len(prefix), index) for index, layer in enumerate(LAYERS) for prefix in layer
               if _within(module, prefix)]  # fmt: skip
    if not matches:
        raise AssertionError(f"{module} is in no layer: add it to LAYERS in {Path(__file__).name}")
    return max(matches)[1]


def _imports(path: Path, module: str) -> set[str]:
    """The occkit modules ``path`` imports (``from occkit.x import y`` counts ``occkit.x.y`` when that is a module)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolved against this module's package
                parent = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{parent}.{base}" if base else parent
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    modules = MODULES.keys()
    return {name for name in found if name in modules and name != module}


MODULES = {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def _graph() -> dict[str, set[str]]:
    return {module: _imports(path, module) for module, path in MODULES.items()}


def test_every_module_has_a_layer():
    for module in MODULES:
        _layer(module)


def test_imports_never_run_up_the_layers():
    # Layers numbered from 1, as docs/architecture.md numbers them.
    upward = [f"{module} (layer {_layer(module) + 1}) imports {target} (layer {_layer(target) + 1})"
              for module, targets in _graph().items() for target in sorted(targets)
              if _layer(target) > _layer(module)]  # fmt: skip
    assert not upward, "imports against the layer order of docs/architecture.md:\n" + "\n".join(upward)


def _within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def test_independent_packages_never_import_each_other():
    crossing = [f"{module} imports {target}" for module, targets in _graph().items() for target in sorted(targets)
                for a, b in INDEPENDENT for one, other in ((a, b), (b, a))
                if _within(module, one) and _within(target, other)]  # fmt: skip
    assert not crossing, "imports between independent packages:\n" + "\n".join(crossing)


def test_forbidden_imports_are_absent():
    found = [f"{module} imports {target}" for module, targets in _graph().items() for target in sorted(targets)
             for importer, imported in FORBIDDEN
             if _within(module, importer) and _within(target, imported)]  # fmt: skip
    assert not found, "imports the design forbids:\n" + "\n".join(found)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, groups = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in graph[node]:
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return groups


def test_no_import_cycles():
    graph = _graph()
    # A package's __init__ importing its own modules is not a cycle of the design.
    graph = {m: {t for t in ts if not (MODULES[m].name == "__init__.py" and t.startswith(m + "."))}
             for m, ts in graph.items()}  # fmt: skip
    assert not _cycles(graph), f"import cycles: {_cycles(graph)}"


@pytest.mark.parametrize(
    ("graph", "expected"),
    [({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}, [["a", "b", "c"]]), ({"a": {"b"}, "b": set()}, [])],
)
def test_the_cycle_finder(graph, expected):
    assert _cycles(graph) == expected


def test_the_documented_layers_are_the_tested_ones():
    """docs/architecture.md shows contributors the layer order; it must be the one this test enforces."""
    page = (PACKAGE.parent / "docs" / "architecture.md").read_text()
    section = page.split("## Layers", 1)[1].split("\n## ", 1)[0]
    rows = [line.split("|") for line in section.splitlines() if line.startswith("| ") and line[2:3].isdigit()]
    documented = tuple(tuple(re.findall(r"`([\w.]+)`", row[2])) for row in rows)
    assert documented == LAYERS, "docs/architecture.md's layer table differs from LAYERS"


#: Libraries no occkit module imports at its top level, and what importing them costs every command that would.
IMPORTED_WHERE_USED = {
    "torchvision": "torch._dynamo through torchvision.ops: 1.7 s (occkit.models.resnet is torchvision's ResNet)",
    "scipy.spatial": "0.3 s, for one rotation of one corruption",
}


def _top_level_imports(path: Path) -> set[str]:
    """The modules a file imports in its body (not inside a function or class)."""
    found = set()
    for node in ast.parse(path.read_text(), filename=str(path)).body:
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level:
            found.update({node.module or "", *(f"{node.module}.{alias.name}" for alias in node.names)})
    return found


def test_slow_libraries_are_imported_only_where_used():
    found = [f"{module} imports {name} at its top level ({why})" for module, path in MODULES.items()
             for name in sorted(_top_level_imports(path)) for library, why in IMPORTED_WHERE_USED.items()
             if _within(name, library)]  # fmt: skip
    assert not found, "\n".join(found)

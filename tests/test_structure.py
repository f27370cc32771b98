"""The import structure of ``isodream_rl``: no import loop between its modules, and no import that runs back up a
layer (docs/architecture.md). Read from the source with ``ast`` (nothing is imported): every ``import`` counts,
those inside functions and ``if TYPE_CHECKING:`` blocks too."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import isodream_rl

PACKAGE_DIR = Path(isodream_rl.__file__).parent
ROOT = PACKAGE_DIR.name

#: the layers, lowest first: a module may import its own layer's and lower layers' modules, never a higher one's.
#: Each entry is a subpackage or a top-level module of isodream_rl (the package's own ``__init__`` is the lowest).
LAYERS: tuple[frozenset[str], ...] = (
    # process-wide helpers
    frozenset({"__init__", "process_settings", "user_errors", "run_utils"}),
    # video prediction stands on the data sets and the run utilities only, beside the RL side's lowest layer
    frozenset({"envs", "data", "modules", "video_prediction"}),
    frozenset({"objectives"}),
    frozenset({"evaluation"}),
    frozenset({"trainers"}),
    frozenset({"baselines"}),
    # the console entry points and their configuration
    frozenset({"cli", "cli_demo", "cli_overrides", "configs"}),
)


def module_files(package_dir: Path = PACKAGE_DIR) -> dict[str, Path]:
    """``dotted module name -> file`` of every module of the package (a package is its ``__init__.py``)."""
    modules = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(package_dir.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def imported_modules(name: str, path: Path, known: set[str]) -> set[str]:
    """The modules of ``known`` that module ``name`` (at ``path``) imports, wherever in the file the import is.

    ``from P import x`` names the module ``P.x`` where that is a module, else ``P``; relative imports are resolved
    against the module's package. The parent packages Python runs first are not counted.
    """
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    found = set()

    def deepest(dotted: str) -> str | None:
        parts = dotted.split(".")
        while parts:
            candidate = ".".join(parts)
            if candidate in known:
                return candidate
            parts.pop()
        return None

    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [deepest(alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            targets = [
                f"{source}.{alias.name}" if f"{source}.{alias.name}" in known else deepest(source)
                for alias in node.names
            ]
        else:
            continue
        found.update(target for target in targets if target is not None and target != name)
    return found


def import_graph() -> dict[str, set[str]]:
    """``module -> the package's modules it imports`` over every module of the package."""
    files = module_files()
    known = set(files)
    return {name: imported_modules(name, path, known) for name, path in files.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (or a node importing itself), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(node: str) -> None:  # Tarjan's algorithm
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in graph.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1 or node in graph.get(node, ()):
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def unit_of(module: str) -> str:
    """The subpackage or top-level module of isodream_rl that ``module`` belongs to."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def layer_of(unit: str) -> int:
    return next(i for i, layer in enumerate(LAYERS) if unit in layer)


def test_every_subpackage_and_top_level_module_has_a_layer():
    units = {unit_of(module) for module in module_files()}
    placed = set().union(*LAYERS)
    assert units <= placed, f"place these in LAYERS: {sorted(units - placed)}"


def test_the_graph_sees_imports_inside_functions_and_relative_ones(tmp_path):
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub" / "__init__.py").write_text("from . import a\n")
    (package / "sub" / "a.py").write_text("def f():\n    from ..b import g\n    from pkg.sub import b\n")
    (package / "sub" / "b.py").write_text("")
    (package / "b.py").write_text("import pkg.sub.a as a\n")
    files = module_files(package)
    graph = {name: imported_modules(name, path, set(files)) for name, path in files.items()}
    assert graph["pkg.sub"] == {"pkg.sub.a"}
    assert graph["pkg.sub.a"] == {"pkg.b", "pkg.sub.b"}
    assert cycles(graph) == [["pkg.b", "pkg.sub.a"]]


def test_no_module_imports_another_that_imports_it_back():
    loops = cycles(import_graph())
    assert not loops, "import loops among these modules:\n" + "\n".join(" <-> ".join(loop) for loop in loops)


def test_no_module_imports_a_higher_layer():
    upward = sorted(
        f"{module} ({unit_of(module)}) imports {target} ({unit_of(target)})"
        for module, targets in import_graph().items()
        for target in targets
        if layer_of(unit_of(target)) > layer_of(unit_of(module))
    )
    assert not upward, "imports that run back up a layer:\n" + "\n".join(upward)


def test_no_two_subpackages_import_each_other():
    units: dict[str, set[str]] = defaultdict(set)
    for module, targets in import_graph().items():
        units[unit_of(module)].update(
            unit_of(target) for target in targets if unit_of(target) != unit_of(module)
        )
    loops = cycles(dict(units))
    assert not loops, "subpackages that import each other:\n" + "\n".join(
        " <-> ".join(loop) for loop in loops
    )

"""The layers of docs/architecture.md, read from the source: every import, also those inside functions.

An import under ``if TYPE_CHECKING:`` is not an arrow (it never runs).
"""
from __future__ import annotations

import ast
import pathlib
import sys

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "startrack"


def _modules() -> dict:
    """Dotted name -> path of every module of the package."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _imports(name: str, path: pathlib.Path) -> set:
    """Every module ``name`` imports (dotted; ``from a import b`` is ``a.b`` when that is a module, else ``a``)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()

    def visit(body):
        for node in body:
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.dump(node.test):
                continue
            if isinstance(node, ast.Import):
                found.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                    module = ".".join(base + ([node.module] if node.module else []))
                else:
                    module = node.module
                found.add(module)
                found.update(f"{module}.{a.name}" for a in node.names if f"{module}.{a.name}" in MODULES)
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.stmt):
                    visit([child])
                elif hasattr(child, "body") and isinstance(child.body, list):
                    visit(child.body)

    visit(ast.parse(path.read_text()).body)
    return found


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _third_party(imported: set) -> set:
    return {m.split(".")[0] for m in imported} - set(sys.stdlib_module_names) - {"startrack", "__future__"}


def test_the_reader_sees_imports_inside_functions():
    """The oracle below is not vacuous: imports at the top, inside functions and relative ones are read."""
    assert "startrack.identify.driver" in GRAPH["startrack.identify"]              # module level
    assert "startrack.patterns" in GRAPH["startrack.solve"]                         # inside a function
    assert "numba" in GRAPH["startrack._kernels._jit"]                              # inside a function
    assert "startrack.identify.verify" not in GRAPH["startrack.identify.algorithm"]  # TYPE_CHECKING only


def test_the_import_graph_has_no_cycle():
    """No arrow runs back up: the modules sort into layers (every import, also inside functions)."""
    graph = {m: {d for d in deps if d in MODULES and d != m} for m, deps in GRAPH.items()}
    done, active = set(), []

    def visit(m):
        if m in active:
            raise AssertionError("import cycle: " + " -> ".join(active[active.index(m):] + [m]))
        if m in done:
            return
        active.append(m)
        for d in sorted(graph[m]):
            visit(d)
        active.pop()
        done.add(m)

    for m in sorted(graph):
        visit(m)


def test_the_library_never_imports_click_nor_the_cli():
    for name, deps in GRAPH.items():
        if name.startswith("startrack.cli") or name == "startrack.__main__":
            continue
        assert "click" not in _third_party(deps), f"{name} imports click"
        assert not any(d.startswith("startrack.cli") for d in deps), f"{name} imports the CLI"


@pytest.mark.parametrize("name", sorted(m for m in MODULES if m.startswith("startrack._kernels")))
def test_kernels_import_only_numpy_numba_and_kernels(name):
    """_kernels/ is the bottom layer: numpy and the standard library; numba (and llvmlite) in _jit only."""
    deps = GRAPH[name]
    assert all(d.startswith("startrack._kernels") for d in deps if d.split(".")[0] == "startrack"), deps
    allowed = {"numpy", "numba", "llvmlite"} if name == "startrack._kernels._jit" else {"numpy"}
    assert _third_party(deps) <= allowed, _third_party(deps) - allowed


def test_identification_algorithms_sit_above_the_shared_parts_and_below_the_driver():
    """An algorithm module may use the interface, the parameters and the verification; never the driver
    (the driver runs the algorithms, through the registry), and the shared parts import no algorithm."""
    from startrack.identify import BUILTIN

    algorithms = {ref.partition(":")[0] for ref in BUILTIN}
    shared = {"startrack.identify.algorithm", "startrack.identify.params", "startrack.identify.verify",
              "startrack.identify.driver", "startrack.identify.catalog_match"}
    for name in algorithms:
        assert "startrack.identify.driver" not in GRAPH[name], name
        assert "startrack.identify" not in GRAPH[name], f"{name} imports the registry"
    for name in shared:
        assert not GRAPH[name] & algorithms, (name, GRAPH[name] & algorithms)


@pytest.mark.parametrize("name, may_use", [
    ("startrack.errors", set()),
    ("startrack.rotations", set()),
    ("startrack.records", {"startrack.rotations", "startrack.errors"}),
    ("startrack.camera", {"startrack.errors", "startrack.rotations", "startrack._kernels"}),
])
def test_the_records_and_geometry_use_no_stage(name, may_use):
    """Records, errors, rotations and the camera are below every stage (identify, solve, track, ...)."""
    used = {d for d in GRAPH[name] if d.split(".")[0] == "startrack" and d != name}
    assert all(any(d == m or d.startswith(m + ".") for m in may_use) for d in used), used

"""The package's dependencies point one way.

Every module's imports are read with ``ast`` — at module level and inside functions alike (an import hidden in a
function is still a dependency) — except those under ``if TYPE_CHECKING:``, which never run. An import of
``a.b.c`` also runs the ``__init__`` of ``a`` and ``a.b``, so it depends on them too (unless the importer lives
inside them). The resulting module graph must be acyclic, the control path (``adaptation/``) must not reach the
benchmark or the settle simulation, and the Lightning-free subpackages must not import Lightning.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = "lightning_bodyschema"
ROOT = Path(__file__).resolve().parents[2] / PACKAGE
NO_LIGHTNING = ("sim", "faults", "samplers", "evaluation", "adaptation", "solvers", "statics")


def module_files(root: Path = ROOT) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` of the package (packages named by their ``__init__``)."""
    files = {}
    for path in root.rglob("*.py"):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        files[".".join(parts)] = path
    return files


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """ids of the import nodes inside ``if TYPE_CHECKING:`` blocks."""
    skipped = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skipped.update(id(inner) for stmt in node.body for inner in ast.walk(stmt))
    return skipped


def imported_names(module: str, path: Path) -> set[str]:
    """Absolute dotted names ``module`` imports (``from x import y``: ``x.y`` and ``x``), runtime imports only."""
    tree = ast.parse(path.read_text())
    skipped = _type_checking_nodes(tree)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    names = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def internal_edges(files: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the package modules it makes Python run (the target and the ``__init__`` of its parents)."""
    graph = {}
    for module, path in files.items():
        edges = set()
        for name in imported_names(module, path):
            parts = name.split(".")
            for k in range(1, len(parts) + 1):
                target = ".".join(parts[:k])
                inside = module == target or module.startswith(target + ".")  # its own package: already running
                if target in files and not inside:
                    edges.add(target)
        graph[module] = edges
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of modules (first == last), or None."""
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(node: str):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)) is not None:
                return cycle
        state[node] = 2
        stack.pop()
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)) is not None:
            return cycle
    return None


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for nxt in graph.get(todo.pop(), ()):
            if nxt not in seen:
                seen.add(nxt)
                todo.append(nxt)
    return seen


@pytest.fixture(scope="module")
def graph():
    return internal_edges(module_files())


def test_the_reader_sees_hidden_imports(tmp_path):
    """The reader itself: an import inside a function is an edge, a TYPE_CHECKING one is not, a cycle is found."""
    pkg = tmp_path / PACKAGE
    (pkg / "a").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a" / "__init__.py").write_text("from .x import f\n")
    (pkg / "a" / "x.py").write_text("def f():\n    from ..b import g\n    return g\n")
    (pkg / "b.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import x\n")
    files = module_files(pkg)
    graph = internal_edges(files)
    assert graph[f"{PACKAGE}.a.x"] == {f"{PACKAGE}.b"} and graph[f"{PACKAGE}.b"] == set()
    assert find_cycle(graph) is None
    (pkg / "b.py").write_text("def g():\n    from .a.x import f\n")
    cycle = find_cycle(internal_edges(module_files(pkg)))
    assert cycle is not None and f"{PACKAGE}.b" in cycle


def test_no_import_cycle(graph):
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


def test_control_path_reaches_no_benchmark(graph):
    """``adaptation/`` (what a controller runs) imports nothing of ``evaluation/`` nor the settle simulation."""
    for module in (m for m in graph if m.startswith(f"{PACKAGE}.adaptation")):
        bad = {m for m in reachable(graph, module)
               if m.startswith((f"{PACKAGE}.evaluation", f"{PACKAGE}.sim.settle"))}
        assert not bad, f"{module} reaches {sorted(bad)}"


@pytest.mark.parametrize("subpackage", NO_LIGHTNING)
def test_no_lightning_below_the_shell(subpackage, graph):
    """``sim``, ``faults``, ``samplers``, ``evaluation``, ``adaptation`` and ``solvers`` import no Lightning, even
    indirectly."""
    files = module_files()
    for module in (m for m in graph if m.startswith(f"{PACKAGE}.{subpackage}")):
        for dependency in {module} | reachable(graph, module):
            lightning = {n for n in imported_names(dependency, files[dependency])
                         if n.split(".")[0] in ("lightning", "pytorch_lightning")}
            assert not lightning, f"{module} -> {dependency} imports {sorted(lightning)}"


DESIGN = ROOT.parent / "docs" / "design.md"


def subpackage_edges(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """First-level name (subpackage or top module) -> the other first-level names its modules import."""
    def top(module: str) -> str:
        return module.split(".")[1] if "." in module else ""

    edges: dict[str, set[str]] = {}
    for module, targets in graph.items():
        if top(module):
            edges.setdefault(top(module), set()).update(t for t in map(top, targets) if t and t != top(module))
    return edges


def documented_edges(text: str) -> dict[str, set[str]]:
    """The ``name <- a, b`` lines of docs/design.md's import table (after "Import arrows"; a trailing ``(...)``
    is a comment; ``(nothing)`` is no edge)."""
    block = text.split("Import arrows", 1)[1].split("```", 2)[1]
    edges = {}
    for line in block.strip().splitlines():
        name, _, rest = line.partition("<-")
        rest = rest.split("  (")[0].strip()
        edges[name.strip()] = set() if rest.startswith("(nothing") else {n.strip() for n in rest.split(",")}
    return edges


def test_the_design_docs_import_table_is_the_import_graph(graph):
    """docs/design.md's dependency table lists every first-level module and exactly the imports it has."""
    actual = subpackage_edges(graph)
    actual.update({name: set() for name in map(lambda m: m.split(".")[1], filter(lambda m: "." in m, graph))
                   if name not in actual})
    assert documented_edges(DESIGN.read_text()) == actual, "\n".join(
        f"{name:<12}<- {', '.join(sorted(deps)) or '(nothing)'}" for name, deps in sorted(actual.items()))
def test_solvers_stand_below_everything(graph):
    """``solvers/`` (the box QPs every path shares) reaches nothing of the package but the leaves ``errors``,
    ``status`` and ``_arrays`` (the numpy-or-torch switch), which themselves import nothing of it."""
    leaves = {f"{PACKAGE}.errors", f"{PACKAGE}.status", f"{PACKAGE}._arrays"}
    for module in (m for m in graph if m.startswith(f"{PACKAGE}.solvers")):
        outside = {m for m in reachable(graph, module) if not m.startswith(f"{PACKAGE}.solvers")}
        assert outside <= {PACKAGE} | leaves, f"{module} reaches {sorted(outside)}"
    for leaf in leaves:
        assert reachable(graph, leaf) <= {PACKAGE}, f"{leaf} reaches {sorted(reachable(graph, leaf))}"


def test_the_readmes_layout_names_every_package():
    """README's "Layout" names every subpackage (``name/``) and top-level module (``name.py``) of the package."""
    readme = (ROOT.parent / "README.md").read_text()
    layout = readme.split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]
    names = {p.name + "/" for p in ROOT.iterdir() if (p / "__init__.py").exists()}
    names |= {p.name for p in ROOT.glob("*.py") if p.name != "__init__.py"}
    missing = sorted(n for n in names if f"`{n}`" not in layout)
    assert not missing, f"README's Layout does not name {missing}"

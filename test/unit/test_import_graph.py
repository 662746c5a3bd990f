"""The package's modules import each other without a circle, and none is over MAX_LINES long.

The graph is read from the source (`ast`), every `import` and `from ... import` in a module,
at its top, inside a function (a deferred import closes a circle as surely, only later) or
under ``if TYPE_CHECKING:`` (an import for annotations only is still a dependency: the two
modules cannot be read, moved or split apart). An edge goes from a module to the module it
names (`from a.b import c` names `a.b.c` when that is a module, else `a.b`); the implicit import
of a module's parent packages is no edge (a package that re-exports its modules is not a
circle).
"""
from __future__ import annotations

import ast
from pathlib import Path

import art_guidance

PACKAGE = Path(art_guidance.__file__).resolve().parent
ROOT = PACKAGE.name
MAX_LINES = 450  # the longest a module of the package may be


def module_names() -> dict[str, Path]:
    """Dotted module name -> its file, for every module of the package."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = (ROOT, *path.relative_to(PACKAGE).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def imported(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that module `name` (file `path`) imports."""
    return imported_by_source(name, path.read_text(), modules, path.name == "__init__.py",
                              str(path))


def imported_by_source(name: str, source: str, modules: dict[str, Path] | set[str],
                       is_package: bool = False, filename: str = "<source>") -> set[str]:
    """The modules among `modules` that the source of module `name` imports (`is_package`:
    the source is the package's ``__init__``)."""
    package = name if is_package else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                       for alias in node.names]
        else:
            continue
        out.update(t for t in targets if t in modules and t != name)
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports."""
    modules = module_names()
    return {name: imported(name, path, modules) for name, path in modules.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_graph_sees_the_known_imports():
    graph = import_graph()
    assert "art_guidance.planning.request" in graph["art_guidance.planning.pipeline"]
    assert "art_guidance.optim.scp" in graph["art_guidance.optim"]


def test_an_import_for_annotations_only_is_an_edge():
    modules = {"pkg", "pkg.a", "pkg.b", "pkg.c", "pkg.d"}
    source = """
from typing import TYPE_CHECKING
import typing

from pkg import a

if TYPE_CHECKING:
    from pkg.b import Thing
if typing.TYPE_CHECKING:
    from . import c
else:
    import pkg.d
"""
    assert imported_by_source("pkg.e", source, modules) == {"pkg.a", "pkg.b", "pkg.c", "pkg.d"}


def test_a_circle_is_found():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert circles(graph) == [["a", "b", "c"]]


def test_no_module_of_the_package_imports_itself_through_others():
    found = circles(import_graph())
    assert found == [], f"{len(found)} import circle(s): " + "; ".join(
        " <-> ".join(circle) for circle in found)


def test_no_module_of_the_package_is_over_max_lines():
    long = {name: n for name, path in module_names().items()
            if (n := len(path.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def test_the_planner_middle_stays_small():
    """The plan's driver reads as its steps: `GuidancePipeline._plan` within 40 lines (its
    docstring included) and `planning/pipeline.py` within 350."""
    import inspect

    from art_guidance.planning.pipeline import GuidancePipeline

    lines = len(inspect.getsource(GuidancePipeline._plan).splitlines())
    assert lines <= 40, f"_plan is {lines} lines"
    path = PACKAGE / "planning" / "pipeline.py"
    assert len(path.read_text().splitlines()) <= 350


BENCHMARKS = PACKAGE.parent / "benchmarks"


def benchmark_graph() -> dict[str, set[str]]:
    """benchmarks/' modules (each on the path under its file's name) -> those of them it
    imports, deferred imports included."""
    files = {p.stem: p for p in sorted(BENCHMARKS.glob("*.py"))
             + sorted((BENCHMARKS / "analyses").glob("*.py"))}
    return {name: imported_by_source(name, path.read_text(), set(files), filename=str(path))
            for name, path in files.items()}


def test_the_benchmarks_import_each_other_without_a_circle():
    graph = benchmark_graph()
    assert "common" in graph["bench_closed_loop"]  # the graph sees them
    assert "sweep_candidates" in graph["decision_rule"]  # and the analyses
    found = circles(graph)
    assert found == [], f"{len(found)} import circle(s) in benchmarks/: " + "; ".join(
        " <-> ".join(circle) for circle in found)


def test_no_benchmark_loads_another_module_by_a_string():
    """A benchmark names the modules it uses in import statements (the graph above sees
    them), never through importlib with a string; `art-guidance bench` alone picks a benchmark
    by its name."""
    import re

    loads = {p.name for p in (*BENCHMARKS.glob("*.py"), *BENCHMARKS.glob("analyses/*.py"))
             if re.search(r"import_module\(|spec_from_file_location\(", p.read_text())
             and p.name != "common.py"}
    assert loads == set()


def test_the_planner_never_imports_the_guidance_loop():
    """`guidance/` (the receding-horizon loop) sits one floor above `planning/` (one plan)."""
    graph = import_graph()
    up = {(a, b) for a, targets in graph.items() if a.startswith(f"{ROOT}.planning")
          for b in targets if b.startswith(f"{ROOT}.guidance")}
    assert up == set()

"""One-way imports: the project's import graph (imports inside functions included) has no cycle, the library never
imports the pipeline's tools, and library code never reaches into another module's private helpers."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PIPELINE_TOOLS = ("prefect", "prefect_dask", "mlflow", "dvc", "dask", "distributed", "flows", "tasks")


def module_name(path: Path) -> str:
    """``src/weatheralign/lidar/fog.py`` -> ``weatheralign.lidar.fog``; a package's ``__init__`` is the package."""
    rel = path.relative_to(REPO / "src" if path.is_relative_to(REPO / "src") else REPO).with_suffix("")
    parts = list(rel.parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_modules() -> dict[str, Path]:
    return {module_name(p): p for folder in ("src/weatheralign", "flows", "tasks")
            for p in (REPO / folder).rglob("*.py")}


def imported_names(path: Path, name: str) -> list[tuple[str, list[str]]]:
    """(module imported from, names imported) for every import statement of ``path`` (relative ones resolved)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            out.append((base, [a.name for a in node.names]))
    return out


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the project modules it imports (``from a import b`` is an edge to ``a.b`` when that is a module)."""
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        edges = set()
        for base, names in imported_names(path, name):
            for target in [f"{base}.{n}" if f"{base}.{n}" in modules else base for n in names] or [base]:
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    edges.add(target)
        graph[name] = edges
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_cycle_finder_finds_a_cycle() -> None:
    """The check can fail: a made-up graph with a two-module and a three-module cycle."""
    graph = {"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"e"}, "e": {"c", "f"}, "f": set()}
    assert sorted(cycles(graph)) == [["a", "b"], ["c", "d", "e"]]


def test_no_import_cycle() -> None:
    found = cycles(import_graph(project_modules()))
    assert not found, f"import cycles (imports inside functions included): {found}"


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The library's subpackages (``weatheralign.lidar``; a top-level module is its own) and the ones they import."""
    def package(module: str) -> str:
        return ".".join(module.split(".")[:2])
    out: dict[str, set[str]] = {}
    for name, edges in graph.items():
        if name.startswith("weatheralign."):
            out.setdefault(package(name), set()).update(
                package(e) for e in edges if e.startswith("weatheralign.") and package(e) != package(name))
    return out


def test_no_cycle_between_the_library_packages() -> None:
    """One-way between packages too: ``weatheralign.ground`` may use ``weatheralign.lidar`` or the reverse, not
    both (a module-level cycle check passes while two packages import each other's modules)."""
    assert package_graph({"weatheralign.a.x": {"weatheralign.b.y"}, "weatheralign.b.y": set(),
                          "weatheralign.b.z": {"weatheralign.a.w"}, "weatheralign.a.w": set()}) == {
        "weatheralign.a": {"weatheralign.b"}, "weatheralign.b": {"weatheralign.a"}}
    found = cycles(package_graph(import_graph(project_modules())))
    assert not found, f"packages importing each other: {found}"


def test_library_never_imports_the_pipeline() -> None:
    """``pip install weatheralign`` comes without Prefect, MLflow, DVC and Dask: the library imports none of them."""
    offenders = []
    for name, path in project_modules().items():
        if name.startswith("weatheralign"):
            offenders += [f"{name}: {base}" for base, _ in imported_names(path, name)
                          if base.split(".")[0] in PIPELINE_TOOLS]
    assert not offenders, offenders


def test_library_never_uses_another_modules_private_helpers() -> None:
    """``from weatheralign.x import _helper`` only within the same package (a module's own family)."""
    offenders = []
    for name, path in project_modules().items():
        if not name.startswith("weatheralign"):
            continue
        for base, names in imported_names(path, name):
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            if private and base.startswith("weatheralign") and base.rpartition(".")[0] != name.rpartition(".")[0]:
                offenders.append(f"{name} imports {private} from {base}")
    assert not offenders, offenders

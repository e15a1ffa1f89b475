"""The packages import each other in one direction only (STYLE: layers pointing one way)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {
    "processing": {"drivers", "simulators", "experiments", "tests"},
    "drivers": {"simulators", "experiments", "tests"},
    "simulators": {"experiments", "tests"},
    "experiments": {"tests"},
}


def _layer(module: str) -> str:
    """The layer a dotted module name belongs to: ``skinstretch.drivers.x`` -> ``drivers``."""
    parts = module.split(".")
    return parts[1] if parts[0] == "skinstretch" and len(parts) > 1 else parts[0]


def _imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, _layer(alias.name)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.lineno, _layer(node.module)


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_imports_point_one_way(package):
    offences = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for lineno, top in _imports(path):
            if top in FORBIDDEN[package]:
                offences.append(f"{path.relative_to(ROOT)}:{lineno} imports {top}")
    assert not offences, "\n".join(offences)


FOLDERS = {"skinstretch": "skinstretch", "processing": "skinstretch.processing", "drivers": "skinstretch.drivers",
           "experiments": "skinstretch.experiments", "simulators": "skinstretch.simulators"}


def _module_files() -> dict[str, Path]:
    """Every module of the installed namespace by its dotted name (a package by its ``__init__``)."""
    modules = {}
    for folder, dotted in FOLDERS.items():
        for path in (ROOT / folder).rglob("*.py"):
            rel = path.relative_to(ROOT / folder).with_suffix("").parts
            rel = rel[:-1] if rel[-1] == "__init__" else rel
            modules[".".join([dotted, *rel])] = path
    return modules


def _import_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports anywhere in its text (deferred imports inside functions too;
    imports under ``if TYPE_CHECKING`` count as well: they are cheap to avoid)."""
    modules = _module_files()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        out = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                out |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join([*parts[: len(parts) - node.level + 1], *filter(None, [base])])
                for alias in node.names:  # ``from a import b``: the module a.b when b is one, else a
                    out.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
        graph[name] = {m for m in out if m in modules and m != name}
    return graph


def test_no_import_cycle_inside_the_package():
    """No module reaches itself through the modules it imports (Tarjan's strongly connected components)."""
    graph = _import_graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert len(graph) > 100  # the walk saw the package
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)

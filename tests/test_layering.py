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

"""Rules of the house that keep the repository easy to find one's way in (issue 19)."""

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = sorted((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"]


def test_the_readme_is_a_short_front_door():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 120
    assert any("./run demo" in line for line in lines) and any("./run test" in line for line in lines)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_and_module_names_in_the_docs_exist(doc):
    text = doc.read_text()
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if "://" not in target:
            assert (doc.parent / target).exists(), f"{doc.name}: broken link {target}"
    for dotted in set(re.findall(r"skinstretch(?:\.[A-Za-z_0-9]+)+", text)):
        assert _resolves(dotted), f"{doc.name}: {dotted} names nothing"


def _resolves(dotted: str) -> bool:
    """Whether ``dotted`` is a module, or an attribute chain of the longest module it starts with."""
    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        try:
            for name in parts[k:]:
                obj = getattr(obj, name)
        except AttributeError:
            return False
        return True
    return False


def test_no_processing_module_is_over_900_lines():
    sizes = {p.name: len(p.read_text().splitlines()) for p in (ROOT / "processing").glob("*.py")}
    assert max(sizes.values()) <= 900, sorted(sizes.items(), key=lambda kv: -kv[1])[:3]

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


def test_no_hand_written_validators_in_post_init():
    """Field checks are pydantic's (``@validated_dataclass``): a ``__post_init__`` may only derive state."""
    import ast

    offences = []
    for folder in ("processing", "drivers", "simulators", "experiments", "skinstretch"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.FunctionDef) and node.name == "__post_init__":
                    if any(isinstance(n, ast.Raise) for n in ast.walk(node)):
                        offences.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not offences, "__post_init__ raising (use field types or a model_validator): " + ", ".join(offences)


def test_validated_fields_name_nan_before_any_bound():
    from skinstretch.processing.errors import InvalidInputError
    from skinstretch.processing.texture_gate import TextureGateParams
    from skinstretch.simulators.prism_optics import PrismOptics

    with pytest.raises(InvalidInputError, match="black_level should be a finite number"):
        TextureGateParams(black_level=float("nan"))
    with pytest.raises(InvalidInputError, match="view_angle_deg should be a number, not NaN"):
        PrismOptics(view_angle_deg=float("nan"))

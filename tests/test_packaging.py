"""skinstretch installs exactly one namespace: the card's four folders become skinstretch.processing, ..."""

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"skinstretch": "skinstretch", "processing": "skinstretch.processing", "drivers": "skinstretch.drivers",
           "experiments": "skinstretch.experiments", "simulators": "skinstretch.simulators"}


def _declared() -> list[str]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]


def test_every_package_folder_is_declared():
    found = set()
    for folder, dotted in FOLDERS.items():
        for d in [ROOT / folder, *(p for p in (ROOT / folder).rglob("*") if p.is_dir())]:
            if "__pycache__" in d.parts:
                continue
            if any(d.glob("*.py")) or any(d.glob("*.yaml")) or any(d.glob("*.html")):
                rel = d.relative_to(ROOT / folder).parts
                found.add(".".join([dotted, *rel]))
    assert found == set(_declared())


def test_nothing_imports_the_bare_layer_names():
    import ast

    offences = []
    for folder in [*FOLDERS, "tests"]:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                    [node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else [])
                offences += [f"{path.relative_to(ROOT)}: {n}" for n in names if n.split(".")[0] in FOLDERS
                             and n.split(".")[0] != "skinstretch"]
    assert not offences, "\n".join(offences)


@pytest.mark.slow
def test_wheel_holds_only_the_skinstretch_namespace(tmp_path):
    # Built from a copy: setuptools writes its build/ folder into the tree it builds.
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".venv", ".git", "__pycache__", "*.egg-info", "build",
                                                             "demo-output", "bench-output", ".hypothesis"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", str(src), "-w", str(tmp_path)],
                   check=True, capture_output=True)
    (wheel,) = tmp_path.glob("skinstretch-*.whl")
    tops = {name.split("/")[0] for name in zipfile.ZipFile(wheel).namelist()}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"skinstretch"}
    names = zipfile.ZipFile(wheel).namelist()
    assert "skinstretch/simulators/scenes/flatL.yaml" in names
    assert "skinstretch/processing/extraction.py" in names


def test_installed_namespace_from_outside_the_repository(tmp_path):
    code = ("import skinstretch, skinstretch.processing, skinstretch.drivers, skinstretch.simulators, "
            "skinstretch.experiments; print(skinstretch.__version__)\n"
            "try:\n    import processing\nexcept ImportError:\n    print('no bare name')\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, check=True, capture_output=True, text=True)
    assert out.stdout.split() == [__import__("skinstretch").__version__, "no", "bare", "name"]


def test_version_on_the_command_line(capsys):
    from skinstretch.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"skinstretch {__import__('skinstretch').__version__}"

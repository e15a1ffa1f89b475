"""The public Python API: lazily exported names, and the runnable example of docs/python-api.md."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_public_names_import_lazily_and_exist():
    code = ("import sys, skinstretch as ss\n"
            "assert 'skinstretch.experiments' not in sys.modules and 'cv2' not in sys.modules\n"
            "missing = [n for n in ss.__all__ if not hasattr(ss, n)]\n"
            "assert not missing, missing\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    import skinstretch

    with pytest.raises(AttributeError, match="no attribute"):
        skinstretch.not_a_thing  # noqa: B018


def test_the_documented_example_runs(tmp_path):
    text = (ROOT / "docs" / "python-api.md").read_text()
    block = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    script = f"from pathlib import Path\nWORKDIR = Path({str(tmp_path)!r})\n" + block
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    assert "frames of" in out.stdout and "trajectories" in out.stdout and "stretch_profile.png" in out.stdout
    assert (tmp_path / "analysis" / "results.h5").exists() and (tmp_path / "figures" / "stretch_profile.png").exists()

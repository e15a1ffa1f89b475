"""Where a result came from: the versions of skinstretch and of the libraries that computed it, and the machine."""

from __future__ import annotations

import importlib
import os
import platform
import sys
from pathlib import Path

__all__ = ["machine_description", "software_versions"]

_LIBRARIES = {"numpy": "numpy", "scipy": "scipy", "opencv": "cv2", "scikit-image": "skimage", "h5py": "h5py",
              "numba": "numba", "pydantic": "pydantic", "matplotlib": "matplotlib"}


def software_versions() -> dict[str, str]:
    """Versions of skinstretch, Python, the platform and the scientific libraries (those importable)."""
    from skinstretch import __version__  # noqa: PLC0415

    out = {"skinstretch": __version__, "python": sys.version.split()[0], "platform": platform.platform()}
    for name, module in _LIBRARIES.items():
        try:
            out[name] = str(getattr(importlib.import_module(module), "__version__", "unknown"))
        except ImportError:
            continue
    return out


def _cpu_model() -> str:
    # Neither the standard library nor psutil names the CPU model on Linux; /proc/cpuinfo does.
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def machine_description() -> dict[str, str]:
    """The machine a measurement ran on: cores, CPU model, Python, platform, and the load average (1, 5, 15 min)."""
    try:
        load = " / ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:  # not available on this platform
        load = "unknown"
    return {
        "cores": str(os.cpu_count() or "unknown"),
        "cpu": _cpu_model(),
        "python": f"{platform.python_implementation()} {sys.version.split()[0]}",
        "platform": platform.platform(),
        "load average": load,
    }

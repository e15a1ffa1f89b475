"""Where a result came from: the versions of skinstretch and of the libraries that computed it, and the machine."""

from __future__ import annotations

import importlib.metadata
import os
import platform
import sys
from pathlib import Path

__all__ = ["machine_description", "software_versions"]

#: Library name -> (module, its possible distributions).
_LIBRARIES = {
    "numpy": ("numpy", ("numpy",)),
    "scipy": ("scipy", ("scipy",)),
    "opencv": ("cv2", ("opencv-contrib-python-headless", "opencv-python-headless", "opencv-contrib-python",
                       "opencv-python")),
    "scikit-image": ("skimage", ("scikit-image",)),
    "h5py": ("h5py", ("h5py",)),
    "numba": ("numba", ("numba",)),
    "pydantic": ("pydantic", ("pydantic",)),
    "matplotlib": ("matplotlib", ("matplotlib",)),
}


def software_versions() -> dict[str, str]:
    """Versions of skinstretch, Python, the platform and the scientific libraries (those installed).

    A library this process has imported gives its ``__version__``; one it has not, its installed distribution's
    version: importing a library only to read its version would cost the analysis its memory (~50 MB for
    scikit-image and matplotlib, which the analysing process never uses)."""
    from skinstretch import __version__  # noqa: PLC0415

    out = {"skinstretch": __version__, "python": sys.version.split()[0], "platform": platform.platform()}
    for name, (module, distributions) in _LIBRARIES.items():
        if module in sys.modules:
            out[name] = str(getattr(sys.modules[module], "__version__", "unknown"))
            continue
        for dist in distributions:
            try:
                out[name] = importlib.metadata.version(dist)
                break
            except importlib.metadata.PackageNotFoundError:
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

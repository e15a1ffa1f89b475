"""Where a result came from: the versions of skinstretch and of the libraries that computed it."""

from __future__ import annotations

import importlib
import platform
import sys

__all__ = ["software_versions"]

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

"""The public modules of a package, imported in name order: how the CLI finds its commands and bench its sections."""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType

__all__ = ["public_submodules"]


def public_submodules(package: ModuleType) -> list[ModuleType]:
    """Every module of ``package`` whose name does not start with an underscore, imported, sorted by name."""
    infos = sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name)
    return [importlib.import_module(f"{package.__name__}.{i.name}") for i in infos if not i.name.startswith("_")]

"""The project's exception hierarchy, rooted in :class:`SkinstretchError`, and the errors of computation.

Every layer raises subclasses of :class:`SkinstretchError`, so a caller (the command line first of all) can catch
it to report anything skinstretch reports on purpose in one line, and let real bugs propagate. Errors of devices
and session files live with the drivers (:mod:`skinstretch.drivers.errors`); :mod:`skinstretch.errors` gathers
them all for users.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Callable


@dataclass(frozen=True)
class Remedy:
    """Arguments that would avoid an error, kept apart from its message so that each caller names them its own
    way: Python code reads ``pass overwrite=True to replace it``, the command line ``pass --overwrite to
    replace it`` (:meth:`SkinstretchError.message_for`).

    Attributes
    ----------
    parameters : tuple of str
        Keyword arguments, any one of which is a remedy.
    purpose : str
        What passing it does, e.g. ``"to replace it"``.
    value : Any
        The value to pass when it is always the same (``True`` for a switch); None when the caller must choose.
    """

    parameters: tuple[str, ...]
    purpose: str
    value: Any = None

    def render(self, name_of: Callable[[str], str] = str) -> str:
        """``pass A or B <purpose>``, each parameter spelled by ``name_of`` (a CLI flag, a keyword...)."""
        names = []
        for p in self.parameters:
            name = name_of(p)
            if name == p:  # Python spelling
                names.append(f"{p}={self.value!r}" if self.value is not None else f"{p}=...")
            elif self.value is None or self.value is True:
                names.append(name)
            else:
                names.append(f"{name} {self.value}")
        return f"pass {' or '.join(names)} {self.purpose}"


class SkinstretchError(Exception):
    """Root of every error skinstretch raises on purpose.

    ``remedy`` (optional) names the arguments that would avoid the error; ``str(error)`` spells them as Python
    keywords, :meth:`message_for` as the caller's own names (the command line's flags).
    """

    def __init__(self, *args: Any, remedy: Remedy | None = None) -> None:
        super().__init__(*args)
        self.remedy = remedy

    def _base_message(self) -> str:
        return super().__str__()

    def __str__(self) -> str:
        return self.message_for(str)

    def message_for(self, name_of: Callable[[str], str]) -> str:
        """The message with its remedy's parameters named by ``name_of`` (which returns a parameter it does not
        know unchanged); a message that opens with a parameter it knows (``"fps must be positive"``, the style
        of every argument check) opens with that name instead (``"--fps must be positive"``)."""
        base = self._base_message()
        opening = _PARAMETER_OPENING.match(base)
        if opening is not None and name_of(opening.group(1)) != opening.group(1):
            base = name_of(opening.group(1)) + base[opening.end(1):]
        if self.remedy is None:
            return base
        return f"{base}; {self.remedy.render(name_of)}"


_PARAMETER_OPENING = re.compile(r"([A-Za-z_][A-Za-z0-9_]*) (?:must|should|is not|cannot) ")


class InvalidInputError(SkinstretchError, ValueError):
    """An argument has the wrong type, shape, dtype or value. The message names the parameter and the value."""


class InsufficientDataError(SkinstretchError):
    """A computation cannot produce a trustworthy result: too few features, degenerate geometry, no contact..."""


class CalibrationError(SkinstretchError):
    """A geometric calibration cannot be trusted (grid not found, too few dots, residuals too large)."""


class ConfigError(SkinstretchError, ValueError):
    """A scene, protocol, rig or parameter file is invalid. The message names the file, line and field where known."""

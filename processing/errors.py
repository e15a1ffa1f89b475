"""The project's exception hierarchy, rooted in :class:`SkinstretchError`, and the errors of computation.

Every layer raises subclasses of :class:`SkinstretchError`, so a caller (the command line first of all) can catch
it to report anything skinstretch reports on purpose in one line, and let real bugs propagate. Errors of devices
and session files live with the drivers (:mod:`skinstretch.drivers.errors`); :mod:`skinstretch.errors` gathers
them all for users.
"""

from __future__ import annotations


class SkinstretchError(Exception):
    """Root of every error skinstretch raises on purpose."""


class InvalidInputError(SkinstretchError, ValueError):
    """An argument has the wrong type, shape, dtype or value. The message names the parameter and the value."""


class InsufficientDataError(SkinstretchError):
    """A computation cannot produce a trustworthy result: too few features, degenerate geometry, no contact..."""


class CalibrationError(SkinstretchError):
    """A geometric calibration cannot be trusted (grid not found, too few dots, residuals too large)."""


class ConfigError(SkinstretchError, ValueError):
    """A scene, protocol, rig or parameter file is invalid. The message names the file, line and field where known."""

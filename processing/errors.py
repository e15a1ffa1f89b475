"""The project's exception hierarchy, rooted in :class:`SkinstretchError`.

Every package (processing, drivers, simulators, experiments) raises subclasses of these, so a caller can catch
``SkinstretchError`` to handle anything skinstretch reports on purpose, and let real bugs propagate.
"""

from __future__ import annotations


class SkinstretchError(Exception):
    """Root of every error skinstretch raises on purpose."""


class InvalidInputError(SkinstretchError, ValueError):
    """An argument has the wrong type, shape, dtype or value. The message names the parameter and the value."""


class InsufficientDataError(SkinstretchError):
    """A computation cannot produce a trustworthy result: too few features, degenerate geometry, no contact..."""


class SessionFileError(SkinstretchError):
    """A session or results file is missing, truncated, corrupt, foreign, or of an unsupported version."""


class CalibrationError(SkinstretchError):
    """A geometric calibration cannot be trusted (grid not found, too few dots, residuals too large)."""


class ConfigError(SkinstretchError, ValueError):
    """A scene, protocol or rig file is invalid. The message names the file, line and field where known."""


class DeviceError(SkinstretchError):
    """A device failed: link lost, timeout, protocol violation, fault reported by the firmware."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """A device did not answer within its deadline."""


class ProtocolError(DeviceError):
    """Bytes on a wire do not follow the protocol (bad framing, CRC, length, sequence)."""


class SafetyStop(DeviceError):
    """Playback was stopped to protect the subject (force ceiling, link failure); contactors were sent to rest."""

"""Errors of devices and session files (rooted in :class:`skinstretch.processing.errors.SkinstretchError`)."""

from __future__ import annotations

from skinstretch.processing.errors import InvalidInputError, SkinstretchError


class SessionFileError(SkinstretchError):
    """A session or results file is missing, truncated, corrupt, foreign, or of an unsupported version."""


class DiskFullError(SessionFileError):
    """The disk cannot take a recording (refused before it starts) or filled up while writing one."""


class DeviceError(SkinstretchError):
    """A device failed: link lost, timeout, protocol violation, fault reported by the firmware."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """A device did not answer within its deadline."""


class ProtocolError(DeviceError):
    """Bytes on a wire do not follow the protocol (bad framing, CRC, length, sequence)."""


class SafetyStop(DeviceError):
    """Playback was stopped to protect the subject (force ceiling, link failure); contactors were sent to rest."""


class InvalidTargetError(InvalidInputError):
    """A display target is not a safe request: NaN, inf, complex, not numeric or wrongly shaped. ``contactor``
    is the (row, column) of the first offending contactor (None when the whole array is wrong)."""

    def __init__(self, message: str, *, contactor: tuple[int, int] | None = None) -> None:
        super().__init__(message)
        self.contactor = contactor


class FrameFileError(SkinstretchError):
    """A video, TIFF stack or image folder cannot be read: missing, corrupt, truncated or of an unsupported kind."""

"""Every error skinstretch raises on purpose, in one place for users: catch :class:`SkinstretchError` for all."""

from skinstretch.drivers.errors import (
    DeviceError,
    DeviceTimeoutError,
    FrameFileError,
    ProtocolError,
    SafetyStop,
    SessionFileError,
)
from skinstretch.processing.errors import (
    CalibrationError,
    ConfigError,
    InsufficientDataError,
    InvalidInputError,
    SkinstretchError,
)

__all__ = [
    "SkinstretchError",
    "InvalidInputError",
    "InsufficientDataError",
    "CalibrationError",
    "ConfigError",
    "SessionFileError",
    "FrameFileError",
    "DeviceError",
    "DeviceTimeoutError",
    "ProtocolError",
    "SafetyStop",
]

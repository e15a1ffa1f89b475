"""Camera modes of the seed's Pulnix TM-6703 (seed 3.3), and the fields of view it was used with (seed 6.3.2)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import Float, PositiveInt, validated_dataclass


@validated_dataclass
class CameraMode:
    """A camera acquisition mode: image size in pixels and frame rate in Hz (``math.inf``: as fast as read, a replay)."""

    name: str
    width: PositiveInt
    height: PositiveInt
    fps: Annotated[Float, Field(gt=0)]

    @property
    def period_s(self) -> float:
        return 1.0 / self.fps


#: The three modes of the seed's camera (seed 3.3), 8-bit monochrome.
CAMERA_MODES: dict[str, CameraMode] = {
    "full": CameraMode("full", 640, 484, 60.0),
    "half": CameraMode("half", 640, 242, 120.0),
    "strip": CameraMode("strip", 640, 100, 220.0),
}

#: Field of view across the 640-pixel width (seed 6.3.2: ~10.3 mm full field, ~6.1 mm close-up).
FIELD_OF_VIEW_MM: dict[str, float] = {"full": 10.3, "closeup": 6.1}


def camera_mode(name: str) -> CameraMode:
    """Look up a camera mode by name; raise InvalidInputError naming the known modes."""
    try:
        return CAMERA_MODES[name]
    except KeyError:
        raise InvalidInputError(f"unknown camera mode {name!r}; known: {sorted(CAMERA_MODES)}") from None

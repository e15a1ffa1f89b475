"""How a point on the contact surface reaches a camera pixel.

Surface coordinates are millimetres *on the contact surface*, "unrolled" (seed 3.4): ``u`` across the ruled
surface (constant-height direction) and ``s`` the arc length along the direction in which the surface height
varies, both with their origin at the centre of the field of view. Image coordinates are pixels, ``x`` the column
and ``y`` the row, with the origin at the centre of the top-left pixel.

:class:`IdealOptics` is the flat, distortion-free, square-pixel view the seed's calibrated images approximate.
Optics with the prism's 45-degree perspective, lens distortion and a surface height profile implement the same
interface (see :mod:`skinstretch.simulators.prism_optics`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from skinstretch.processing.validated_dataclass import PositiveFloat, PositiveInt, validated_dataclass


class Optics(ABC):
    """Maps surface millimetres (u, s) to image pixels (x, y) and back. Arrays have a trailing axis of 2."""

    width: int
    height: int

    @property
    @abstractmethod
    def px_per_mm(self) -> float:
        """Nominal scale at the centre of the field of view."""

    @abstractmethod
    def surface_to_image(self, us_mm: np.ndarray) -> np.ndarray:
        """Image pixels (x, y) of surface points (u, s) in mm."""

    @abstractmethod
    def image_to_surface(self, xy_px: np.ndarray) -> np.ndarray:
        """Surface points (u, s) in mm seen at image pixels (x, y)."""

    @property
    def center_px(self) -> np.ndarray:
        return np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])


@validated_dataclass
class IdealOptics(Optics):
    """Orthographic, square-pixel view of the unrolled surface: ``x = cx + u * scale``, ``y = cy + s * scale``."""

    width: PositiveInt
    height: PositiveInt
    scale_px_per_mm: PositiveFloat

    @property
    def px_per_mm(self) -> float:
        return self.scale_px_per_mm

    def surface_to_image(self, us_mm: np.ndarray) -> np.ndarray:
        return np.asarray(us_mm, dtype=np.float64) * self.scale_px_per_mm + self.center_px

    def image_to_surface(self, xy_px: np.ndarray) -> np.ndarray:
        return (np.asarray(xy_px, dtype=np.float64) - self.center_px) / self.scale_px_per_mm

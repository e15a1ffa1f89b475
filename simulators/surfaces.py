"""The contact surfaces of the seed (seed 3.3, Figure 14): flat, and parallel-ruled Gaussian ridge and valley.

Axis convention
---------------
A ruled surface varies along one direction only. Its height ``h`` is a function of ``z``, the *flat* (projected)
coordinate in mm across the ruling; along the other direction it is constant. Following
:mod:`skinstretch.simulators.ideal_optics`, the unrolled surface coordinate ``s`` is the **arc length** along ``z`` and ``u`` runs
along the ruling. With :class:`skinstretch.simulators.ideal_optics.IdealOptics`, ``s`` is the image **row** (y) axis: the ridge or
valley is a horizontal band of the image and the finger crosses it by sliding in +y. (The seed's figures show the
same images rotated by 90 degrees, seed 3.4 footnote, where the finger slides "left to right".)

Profile
-------
``h(z) = sign * height * exp(-(z - center)^2 / (2 sigma^2))`` with ``sigma = width / 4``: the seed's "3 mm wide"
is read as the +/-2 sigma band holding 95 % of the bump, so sigma = 0.75 mm for the seed's surfaces. ``sign`` is +1
for a ridge and -1 for a valley; the seed's height is 0.5 mm. The steepest slope is then
``height / sigma * exp(-1/2)`` = 0.40 (22 degrees), shallow enough for FTIR with a diffuse source (seed 3.2).
"""

from __future__ import annotations

from functools import cached_property
from typing import Literal

import numpy as np

from skinstretch.processing.ruled_surface_rays import ArcLengthTable
from skinstretch.processing.validated_dataclass import FiniteFloat, NonNegativeFloat, PositiveFloat, validated_dataclass

SURFACE_KINDS = ("flat", "ridge", "valley")


@validated_dataclass
class RuledSurface:
    """A parallel-ruled contact surface, flat or with one Gaussian ridge or valley.

    Parameters
    ----------
    kind : {"flat", "ridge", "valley"}
    width_mm : float
        Width of the shape, read as 4 sigma of the Gaussian (seed: 3 mm).
    height_mm : float
        Height of the ridge or depth of the valley (seed: 0.5 mm).
    center_mm : float
        Flat coordinate ``z`` of the crest (ridge) or bottom (valley); ``z = 0`` is the centre of the field of view.

    Examples
    --------
    >>> r = RuledSurface(kind="ridge", width_mm=3.0, height_mm=0.5)
    >>> round(float(r.height(0.0)), 3), round(r.sigma_mm, 3)
    (0.5, 0.75)
    """

    kind: Literal["flat", "ridge", "valley"] = "flat"
    width_mm: PositiveFloat = 3.0
    height_mm: NonNegativeFloat = 0.5
    center_mm: FiniteFloat = 0.0

    @property
    def sigma_mm(self) -> float:
        """Standard deviation of the Gaussian profile: width / 4."""
        return self.width_mm / 4.0

    @property
    def sign(self) -> float:
        return {"flat": 0.0, "ridge": 1.0, "valley": -1.0}[self.kind]

    def height(self, z_mm: np.ndarray | float) -> np.ndarray:
        """Surface height (mm, positive towards the finger) at flat coordinate ``z_mm``."""
        z = np.asarray(z_mm, dtype=np.float64) - self.center_mm
        return self.sign * self.height_mm * np.exp(-0.5 * (z / self.sigma_mm) ** 2)

    def slope(self, z_mm: np.ndarray | float) -> np.ndarray:
        """dh/dz at flat coordinate ``z_mm`` (dimensionless)."""
        z = np.asarray(z_mm, dtype=np.float64) - self.center_mm
        return -z / self.sigma_mm**2 * self.sign * self.height_mm * np.exp(-0.5 * (z / self.sigma_mm) ** 2)

    @property
    def max_slope(self) -> float:
        """Largest |dh/dz| of the profile."""
        return abs(self.sign) * self.height_mm / self.sigma_mm * float(np.exp(-0.5))

    @cached_property
    def _arc(self) -> ArcLengthTable:
        # Arc length s(z) = integral sqrt(1 + h'^2) dz from z = 0 (the centre of the field of view, as the optics
        # convention asks), tabulated finely around the shape (the surface is flat 8 sigma away).
        if self.kind == "flat":
            return ArcLengthTable(None)
        half = 8.0 * self.sigma_mm
        return ArcLengthTable(self.slope, lo=self.center_mm - half, hi=self.center_mm + half, step=half / 4000)

    def arc_length(self, z_mm: np.ndarray | float) -> np.ndarray:
        """Arc length ``s`` (mm) from ``z = 0`` to flat coordinate ``z_mm`` along the profile."""
        return self._arc.s_of_v(z_mm)

    def flat_coordinate(self, s_mm: np.ndarray | float) -> np.ndarray:
        """Inverse of :meth:`arc_length`: flat coordinate ``z`` (mm) of arc length ``s_mm``."""
        return self._arc.v_of_s(s_mm)

    def slope_at_arc(self, s_mm: np.ndarray | float) -> np.ndarray:
        """dh/dz at the point of arc length ``s_mm``."""
        return self.slope(self.flat_coordinate(s_mm))

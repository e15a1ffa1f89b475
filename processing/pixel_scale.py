"""The calibration object every processing step uses to turn physical parameters into pixels.

Parameters throughout skinstretch are given in mm (and degrees, frames), as the seed gives them. A frozen
:class:`Calibration` converts them to pixels once, at the top of each processing function, so that nothing
downstream ever guesses a scale. The geometric mapping from image pixels to millimetres on the skin (seed 3.4)
is attached by :mod:`skinstretch.processing.geometric_calibration` when one was fitted (a
:class:`~skinstretch.processing.grid_mapping.GridMapping`); without one the image is taken as a flat, square-pixel view of the contact plane at ``px_per_mm``.
"""

from __future__ import annotations

from dataclasses import field
from typing import Any

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import PositiveFloat, validated_dataclass

#: A fingertip's median ridge period (mm; 0.39-0.46 mm interquartile): what scale-dependent reductions are sized by.
RIDGE_PERIOD_MM = 0.43
#: Fewest pixels per ridge period an image may keep when it is reduced (a pyramid level, a downsampled copy):
#: below it the ridges alias and a coarse registration locks onto a wrong ridge.
MIN_REDUCED_PERIOD_PX = 6.0


@validated_dataclass
class Calibration:
    """Pixel scale of an image sequence, and optionally a fitted pixel-to-skin mapping.

    Parameters
    ----------
    px_per_mm : float
        Pixels per millimetre on the contact surface (seed: ~62 px/mm for the 10.3 mm full field of view).
    mapping : object, optional
        A fitted geometric mapping (see :mod:`skinstretch.processing.geometric_calibration`) with ``image_to_surface`` and
        ``surface_to_image`` methods. ``None`` means the flat, square-pixel model.

    Examples
    --------
    >>> cal = Calibration(px_per_mm=62.0)
    >>> cal.px(2.0)
    124.0
    >>> cal.odd_px(2.0)
    125
    """

    px_per_mm: PositiveFloat
    mapping: Any = field(default=None, compare=False, repr=False)

    @classmethod
    def from_field_of_view(cls, width_px: int, width_mm: float) -> "Calibration":
        """Calibration of a camera whose ``width_px`` pixels span ``width_mm`` millimetres."""
        if width_px <= 0 or width_mm <= 0:
            raise InvalidInputError(f"field of view must be positive, got {width_px} px over {width_mm} mm")
        return cls(px_per_mm=width_px / width_mm)

    def px(self, mm: float) -> float:
        """A length in mm, in pixels."""
        return float(mm) * self.px_per_mm

    def mm(self, px: float) -> float:
        """A length in pixels, in mm."""
        return float(px) / self.px_per_mm

    def odd_px(self, mm: float, minimum: int = 1) -> int:
        """A window width in mm as an odd pixel count (windows are centred), at least ``minimum``."""
        n = int(round(self.px(mm)))
        n = max(n, minimum)
        return n if n % 2 == 1 else n + 1

    def px_int(self, mm: float, minimum: int = 0) -> int:
        """A length in mm rounded to whole pixels, at least ``minimum``."""
        return max(int(round(self.px(mm))), minimum)

    def resolvable_reduction(self, most: int, *, min_period_px: float = MIN_REDUCED_PERIOD_PX) -> int:
        """The largest integer downsampling factor, at most ``most``, that keeps a ridge period
        (:data:`RIDGE_PERIOD_MM`) at least ``min_period_px`` pixels long (1 at coarse scales).

        >>> Calibration(px_per_mm=62.0).resolvable_reduction(4), Calibration(px_per_mm=19.7).resolvable_reduction(4)
        (4, 1)
        """
        return max(1, min(int(most), int(self.px(RIDGE_PERIOD_MM) // float(min_period_px))))

    def resolvable_halvings(self, most: int) -> int:
        """The most pyramid halvings, at most ``most``, that keep a ridge period at least
        :data:`MIN_REDUCED_PERIOD_PX` pixels long (0 at coarse scales).

        >>> Calibration(px_per_mm=62.0).resolvable_halvings(5), Calibration(px_per_mm=19.7).resolvable_halvings(5)
        (2, 0)
        """
        period, levels = self.px(RIDGE_PERIOD_MM), 0
        while levels < int(most) and period / 2.0 ** (levels + 1) >= MIN_REDUCED_PERIOD_PX:
            levels += 1
        return levels

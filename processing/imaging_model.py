"""The imaging model a geometric calibration fits: a pinhole camera with radial distortion looking at a ruled surface.

This is the seed's 7.2.1 proposal, "a model of the surface and of the image acquisition system": a pinhole camera
(pose as a rotation vector and a translation, focal length in px, radial distortion k1, k2 about a fixed principal
point) looking at a parallel-ruled surface whose height profile is flat, Gaussian (a ridge or valley: amplitude,
width, position) or Gaussian plus a smooth cubic-spline correction (a machined shape is never quite Gaussian).
:class:`ImagingModel` maps the unrolled surface (u, s) mm to image pixels and back; the ray-surface intersection
and the arc length are :mod:`skinstretch.processing.ruled_surface_rays`'s. The model's fit is
:mod:`skinstretch.processing.grid_mapping_fit`; the mapping users hold is
:class:`skinstretch.processing.grid_mapping.GridMapping`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline
from scipy.spatial.transform import Rotation

from skinstretch.processing.ruled_surface_rays import ArcLengthTable, cast_rays, surface_points

__all__ = ["ImagingModel", "SplineBasis", "SurfaceProfile", "rotation_2d"]


def rotation_2d(phi: float) -> np.ndarray:
    """The 2x2 matrix of a rotation by ``phi`` radians."""
    return np.array([[math.cos(phi), -math.sin(phi)], [math.sin(phi), math.cos(phi)]])


@dataclass(frozen=True)
class SplineBasis:
    """Cubic B-spline correction to a Gaussian profile: uniform knots, zero (with its first two derivatives)
    outside them, so the surface stays flat away from the shape."""

    knots: tuple[float, ...]

    @property
    def n(self) -> int:
        """Number of coefficients."""
        return len(self.knots) - 4

    @classmethod
    def around(cls, center: float, sigma: float, *, step: float = 0.3, extent_sigmas: float = 5.0) -> "SplineBasis":
        """Knots every ``step`` mm over +/- ``extent_sigmas`` sigma about ``center``."""
        n_int = max(4, int(math.ceil(2 * extent_sigmas * sigma / step)))
        lo = center - 0.5 * n_int * step
        return cls(knots=tuple(float(lo + k * step) for k in range(n_int + 1)))


class SurfaceProfile:
    """Height profile across the rulings (Gaussian, optionally plus a B-spline correction) and its arc length."""

    def __init__(self, amplitude: float, sigma: float, center: float, knots: tuple = (), coefs: tuple = (), *,
                 step: float = 0.01) -> None:
        self.amplitude, self.sigma, self.center = float(amplitude), float(sigma), float(center)
        self.spline = BSpline(np.asarray(knots), np.asarray(coefs), 3, extrapolate=False) if len(coefs) else None
        self.dspline = self.spline.derivative() if self.spline is not None else None
        self.flat = self.amplitude == 0.0 and self.spline is None
        if self.flat:
            self.arc = ArcLengthTable(None)
            return
        # Tabulate where the surface is not flat (Gaussian beyond 8 sigma < 1e-13 mm; the spline has compact
        # support); outside, s - v is constant.
        lo, hi = min(center - 8 * sigma, -0.5), max(center + 8 * sigma, 0.5)
        if len(knots):
            lo, hi = min(lo, knots[0]), max(hi, knots[-1])
        self.arc = ArcLengthTable(self.slope, lo=lo, hi=hi, step=step)

    def height(self, v: np.ndarray) -> np.ndarray:
        if self.flat:
            return np.zeros_like(v)
        z = (v - self.center) / self.sigma
        h = self.amplitude * np.exp(-0.5 * z * z)
        if self.spline is not None:
            h = h + np.nan_to_num(self.spline(v), nan=0.0)
        return h

    def slope(self, v: np.ndarray) -> np.ndarray:
        if self.flat:
            return np.zeros_like(v)
        z = (v - self.center) / self.sigma
        d = -self.amplitude * z / self.sigma * np.exp(-0.5 * z * z)
        if self.dspline is not None:
            d = d + np.nan_to_num(self.dspline(v), nan=0.0)
        return d


@functools.lru_cache(maxsize=32)
def _cached_profile(amplitude: float, sigma: float, center: float, knots: tuple, coefs: tuple) -> SurfaceProfile:
    # A finite-difference Jacobian perturbs one parameter at a time: most evaluations reuse the same profile.
    return SurfaceProfile(amplitude, sigma, center, knots, coefs)


@dataclass
class ImagingModel:
    """Camera + ruled surface: unrolled surface frame (u, s) mm <-> image (x, y) px.

    ``rotvec`` and ``trans`` take surface-frame points into the camera frame (``R p + t``); ``principal`` is the
    distortion centre in px; ``amplitude``, ``sigma``, ``center`` (mm) the Gaussian profile (amplitude 0: flat);
    ``knots`` and ``coefs`` its optional cubic-spline correction.
    """

    rotvec: np.ndarray
    trans: np.ndarray
    focal_px: float
    k1: float
    k2: float
    principal: np.ndarray
    amplitude: float
    sigma: float
    center: float
    knots: tuple = ()
    coefs: tuple = ()

    def __post_init__(self) -> None:
        self.R = Rotation.from_rotvec(np.asarray(self.rotvec, dtype=np.float64)).as_matrix()
        self.profile = _cached_profile(
            float(self.amplitude), float(self.sigma), float(self.center),
            tuple(float(k) for k in self.knots), tuple(float(c) for c in self.coefs),
        )

    def project(self, us: np.ndarray) -> np.ndarray:
        """Image pixels (x, y) of unrolled surface points (u, s); (..., 2) -> (..., 2)."""
        cam = surface_points(us, self.profile, self.profile.arc) @ self.R.T + self.trans
        a, b = cam[..., 0] / cam[..., 2], cam[..., 1] / cam[..., 2]
        r2 = a * a + b * b
        rad = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        return np.stack([self.principal[0] + self.focal_px * a * rad, self.principal[1] + self.focal_px * b * rad], -1)

    def back_project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Surface (u, s) seen at pixels, and whether the ray met the surface in front of the camera."""
        ad = (xy[..., 0] - self.principal[0]) / self.focal_px
        bd = (xy[..., 1] - self.principal[1]) / self.focal_px
        a, b = ad.copy(), bd.copy()
        for _ in range(20):  # fixed point, then it is exact to ~1e-16 for percent-level distortion
            r2 = a * a + b * b
            rad = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
            a_new, b_new = ad / rad, bd / rad
            done = max(np.max(np.abs(a_new - a), initial=0.0), np.max(np.abs(b_new - b), initial=0.0)) < 1e-16
            a, b = a_new, b_new
            if done:
                break
        ray_c = np.stack([a, b, np.ones_like(a)], axis=-1)
        # R^T applied to each ray gives its surface-frame direction; the camera centre is -R^T t.
        return cast_rays(-self.R.T @ self.trans, ray_c @ self.R, self.profile, self.profile.arc)

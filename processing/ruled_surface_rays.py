"""Where a camera's rays meet a parallel-ruled contact surface, in the surface's unrolled coordinates (seed 3.4).

A parallel-ruled surface (seed appendix A) has a height ``h(v)`` across its rulings and none along them: in a
surface frame (U along the rulings, V across them, N the flat plane's normal) its points are ``(u, v, h(v))``. The
seed measures on the *unrolled* surface: ``u`` along the rulings and ``s``, the arc length of the profile curve
``(v, h(v))`` from ``v = 0``, across them.

Two models look at such a surface through a pinhole: the calibration's fitted imaging model
(:mod:`skinstretch.processing.imaging_model`) and the simulator's prism optics
(:mod:`skinstretch.simulators.prism_optics`). Both use this module for the two computations they share: the
arc-length table (:class:`ArcLengthTable`) and the ray-surface intersection by Newton's method
(:func:`cast_rays`), so there is one solve to trust and to fix.
"""

from __future__ import annotations

import math
from typing import Callable, Protocol

import numpy as np

__all__ = ["ArcLengthTable", "RuledProfile", "cast_rays", "surface_points"]

#: Newton's method on v stops when no ray's step exceeds this (mm), or after MAX_NEWTON_STEPS.
NEWTON_TOLERANCE_MM = 1e-13
MAX_NEWTON_STEPS = 40


class RuledProfile(Protocol):
    """A height profile across the rulings: ``height(v)`` (mm) and its derivative ``slope(v)``, vectorised."""

    def height(self, v: np.ndarray) -> np.ndarray: ...

    def slope(self, v: np.ndarray) -> np.ndarray: ...


class ArcLengthTable:
    """Arc length ``s(v)`` of a profile curve ``(v, h(v))`` from ``v = 0``, and its inverse ``v(s)``.

    Tabulated on a uniform grid of ``step`` mm over ``[lo, hi]`` (widened to hold ``v = 0``) with Simpson's rule per
    interval (exact to ~1e-15 mm at 0.01 mm steps for the seed's Gaussian shapes), interpolated linearly (error
    below ~1e-5 mm at 0.01 mm steps, ~1e-6 mm at 0.002 mm), and extended with unit slope outside, where the profile
    must be flat. ``slope=None`` is a flat profile: ``s = v``.
    """

    def __init__(self, slope: Callable[[np.ndarray], np.ndarray] | None, *, lo: float = 0.0, hi: float = 0.0,
                 step: float = 0.01) -> None:
        self.flat = slope is None
        if slope is None:
            return
        lo, hi = min(lo, -step), max(hi, step)
        v = np.linspace(lo, hi, int(math.ceil((hi - lo) / step)) + 1)
        g = np.sqrt(1.0 + slope(v) ** 2)
        gm = np.sqrt(1.0 + slope(0.5 * (v[1:] + v[:-1])) ** 2)
        s = np.concatenate([[0.0], np.cumsum((v[1] - v[0]) / 6.0 * (g[:-1] + 4.0 * gm + g[1:]))])
        self.v, self.s = v, s - np.interp(0.0, v, s)

    def s_of_v(self, v: np.ndarray) -> np.ndarray:
        """Arc length (mm) from ``v = 0`` to flat coordinate ``v`` (mm)."""
        return self._lookup(np.asarray(v, dtype=np.float64), self.v, self.s) if not self.flat else np.asarray(
            v, dtype=np.float64)

    def v_of_s(self, s: np.ndarray) -> np.ndarray:
        """Flat coordinate ``v`` (mm) at arc length ``s`` (mm): the inverse of :meth:`s_of_v`."""
        return self._lookup(np.asarray(s, dtype=np.float64), self.s, self.v) if not self.flat else np.asarray(
            s, dtype=np.float64)

    @staticmethod
    def _lookup(x: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        out = np.interp(x, xs, ys)
        # Beyond the table the profile is flat: one mm of v is one mm of arc.
        out = np.where(x < xs[0], ys[0] + (x - xs[0]), out)
        return np.where(x > xs[-1], ys[-1] + (x - xs[-1]), out)


def surface_points(us_mm: np.ndarray, profile: RuledProfile, arc: ArcLengthTable) -> np.ndarray:
    """3-D points (U, V, N components, mm) of unrolled surface points (u, s); (..., 2) -> (..., 3)."""
    v = arc.v_of_s(us_mm[..., 1])
    return np.stack([us_mm[..., 0], v, profile.height(v)], axis=-1)


def cast_rays(
    centre: np.ndarray, rays: np.ndarray, profile: RuledProfile, arc: ArcLengthTable
) -> tuple[np.ndarray, np.ndarray]:
    """Unrolled surface points (u, s) in mm where rays from ``centre`` meet the surface, and which rays met it.

    Parameters
    ----------
    centre : (3,) array
        The camera's centre of projection in the surface frame (U, V, N), mm.
    rays : (..., 3) array
        Ray directions in the surface frame (any length).
    profile, arc : RuledProfile, ArcLengthTable
        The surface's height profile and its arc-length table (``arc.flat``: the plane N = 0).

    Returns
    -------
    us : (..., 2) array
    ok : (..., ) bool array
        False where the ray runs along the rulings, misses the surface, or meets it behind the centre.

    Notes
    -----
    A point of the ray at flat coordinate ``v`` has height ``N(v) = c_N + (v - c_V) k`` with ``k = r_N / r_V``;
    Newton's method solves ``N(v) = h(v)`` from the ray's intersection with the flat plane. It converges to the one
    intersection when the view never grazes the surface (``|h'| tan(view angle) < 1``), in 4-6 steps.
    """
    c = centre
    ok = np.abs(rays[..., 1]) > 1e-9
    rv = np.where(ok, rays[..., 1], 1.0)
    k = rays[..., 2] / rv
    with np.errstate(divide="ignore", invalid="ignore"):
        v = c[1] - c[2] / np.where(np.abs(k) > 1e-12, k, np.nan)
        if not arc.flat:
            for _ in range(MAX_NEWTON_STEPS):
                g = c[2] + (v - c[1]) * k - profile.height(v)
                step = g / (k - profile.slope(v))
                v = v - step
                if np.nanmax(np.abs(step), initial=0.0) < NEWTON_TOLERANCE_MM:
                    break
    t = (v - c[1]) / rv
    ok &= np.isfinite(v) & (t > 0)
    u = c[0] + t * rays[..., 0]
    return np.stack([u, arc.s_of_v(v)], axis=-1), ok

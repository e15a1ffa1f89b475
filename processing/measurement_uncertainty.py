"""Predicted standard errors of measured displacements and of the strains computed from them.

As DIC tools report a sigma for every subset, every registered point carries the standard error its window
predicts: the residual variance per pixel ``s^2`` left after the registration (image noise and what the motion
model does not explain) over the window's gradient products ``T`` (its texture), covariance ``s^2 T^-1``. One
number per point, the larger axis of that covariance, bounds the error in any direction. Strain errors follow to
first order with each point's error independent (conservative for neighbours whose windows overlap).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["larger_axis_sigma", "window_match", "registration_check", "RegistrationCheck", "edge_change_sigma",
           "area_change_sigma", "MIN_MATCH", "MODEL_SIGMA_PX", "LOSSY_MODEL_SIGMA_PX", "RADIUS_95_2D",
           "RADIUS_95_1D"]

#: A registration whose windows match worse than this after the measured motion failed (``window_match``: 1 for
#: identical windows, 0 for unrelated ones of the same texture): its error is unbounded, its sigma infinite.
MIN_MATCH = 0.8
#: The error a window's residual does not show (px per axis, added in quadrature): the bilinear sampling's bias
#: and what stays of a registration's systematic error; the bench's coverage of the 95 % interval checks it.
MODEL_SIGMA_PX = 0.01
#: The same for frames from lossy video: the codec's error follows the motion from frame to frame, and a window's
#: residual shows little of it (``skinstretch bench --only conditions``, MP4 rows).
LOSSY_MODEL_SIGMA_PX = 0.03

#: A 2-D error vector with a standard error ``sigma`` per axis lies within this many ``sigma`` of the truth 95 %
#: of the time (chi-square, 2 degrees of freedom).
RADIUS_95_2D = 2.4477
#: The same for one number (a strain): the normal distribution's 97.5th percentile.
RADIUS_95_1D = 1.96


def larger_axis_sigma(txx, txy, tyy, s2) -> np.ndarray:
    """sqrt of the larger eigenvalue of ``s2 * inv([[txx, txy], [txy, tyy]])`` (px), element-wise: inf where the
    window has no texture in some direction (its smaller gradient eigenvalue is not positive), NaN where ``s2`` is
    unknown.

    >>> float(larger_axis_sigma(4.0, 0.0, 1.0, 0.25))  # weakest direction: 0.25 / 1
    0.5
    """
    txx, txy, tyy, s2 = (np.asarray(v, dtype=np.float64) for v in (txx, txy, tyy, s2))
    smallest = 0.5 * (txx + tyy - np.sqrt((txx - tyy) ** 2 + 4.0 * txy * txy))
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.sqrt(np.maximum(s2, 0.0) / smallest)
    return np.where(np.isnan(s2), np.nan, np.where(smallest > 0.0, out, np.inf))


def edge_change_sigma(sigma_a, sigma_b, length) -> np.ndarray:
    """Standard error of an edge's relative length change (``change``, a fraction) whose two end points' displacements
    have standard errors ``sigma_a`` and ``sigma_b`` (px per axis); ``length`` in frame a (px)."""
    sigma_a, sigma_b, length = (np.asarray(v, dtype=np.float64) for v in (sigma_a, sigma_b, length))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.hypot(sigma_a, sigma_b) / length


def area_change_sigma(vertices: np.ndarray, sigma: np.ndarray, area) -> np.ndarray:
    """Standard error of a triangle's relative area change from its vertices' displacement errors: moving vertex i
    by 1 px changes the area by at most half the opposite side. ``vertices`` (T, 3, 2) px in frame a, ``sigma``
    (T, 3) px per axis, ``area`` (T,) px^2 in frame a."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3, 2)
    sigma = np.asarray(sigma, dtype=np.float64).reshape(-1, 3)
    opposite = np.linalg.norm(v[:, [2, 0, 1]] - v[:, [1, 2, 0]], axis=2)  # side opposite vertex 0, 1, 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.sum((sigma * opposite) ** 2, axis=1)) / (2.0 * np.abs(np.asarray(area, dtype=np.float64)))


def window_match(residual_variance, texture_variance) -> np.ndarray:
    """How alike two windows are after the measured motion, ``1 - s^2 / (2 v)``: the residual variance per pixel
    over twice the first window's variance (the residual of two unrelated windows of that texture), as a
    correlation coefficient: 1 identical, 1 - noise^2 / texture^2 for a right registration, about 0 for a wrong
    one. NaN where the window has no texture."""
    residual_variance, texture_variance = (np.asarray(v, dtype=np.float64) for v in (residual_variance,
                                                                                      texture_variance))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(texture_variance > 0.0, 1.0 - residual_variance / (2.0 * texture_variance), np.nan)


class RegistrationCheck(NamedTuple):
    """Per registered point: ``sigma`` its predicted standard error per axis (px; inf, no bound, where its windows
    do not match, :data:`MIN_MATCH`, or no window fits in the images) and ``match`` its windows' likeness
    (:func:`window_match`; 0 where no window fits or the window has no texture)."""

    sigma: np.ndarray
    match: np.ndarray


def registration_check(txx, txy, tyy, residual_variance, texture_variance, *,
                       model_sigma_px: float = MODEL_SIGMA_PX) -> RegistrationCheck:
    """:class:`RegistrationCheck` from a window's gradient products, residual variance and texture variance (the
    sigma with ``model_sigma_px`` added in quadrature)."""
    match = np.nan_to_num(window_match(residual_variance, texture_variance), nan=0.0)
    sigma = np.hypot(larger_axis_sigma(txx, txy, tyy, residual_variance), model_sigma_px)
    return RegistrationCheck(np.where((match < MIN_MATCH) | np.isnan(sigma), np.inf, sigma), match)

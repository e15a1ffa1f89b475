"""Predicted standard errors of measured displacements and of the strains computed from them.

As DIC tools report a sigma for every subset, every registered point carries the standard error its window
predicts: the residual variance per pixel ``s^2`` left after the registration (image noise and what the motion
model does not explain) over the window's gradient products ``T`` (its texture), covariance ``s^2 T^-1``. One
number per point, the larger axis of that covariance, bounds the error in any direction.

A dense registration (the flow) also couples each node to its neighbours by a membrane: its error is the windows'
noise smoothed by that coupling, smaller than one window's and correlated between nodes whose windows overlap or
which the membrane ties together. :class:`Regularisation` models it locally as a uniform lattice (the window's
noise correlated in proportion to the windows' overlap, filtered by the membrane in Fourier space): the variance
factor of each node's error and the correlation of two nodes' errors at a given offset. Strain errors follow to
first order from the points' errors and that correlation (none between features: independent windows).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np

__all__ = ["larger_axis_sigma", "window_match", "registration_check", "RegistrationCheck", "edge_change_sigma",
           "area_change_sigma", "Regularisation", "variance_factor", "MIN_MATCH", "MODEL_SIGMA_PX",
           "LOSSY_MODEL_SIGMA_PX", "RADIUS_95_2D", "RADIUS_95_1D"]

#: A registration whose windows match worse than this after the measured motion failed (``window_match``: 1 for
#: identical windows, 0 for unrelated ones of the same texture): its error is unbounded, its sigma infinite.
MIN_MATCH = 0.8
#: The error a window's residual does not show (px per axis, added in quadrature): the bilinear sampling's bias
#: and what stays of a registration's systematic error; the bench's coverage of the 95 % interval checks it.
MODEL_SIGMA_PX = 0.01
#: The same for frames from lossy video whose codec's error the import did not measure (``source.codec_error``;
#: :mod:`skinstretch.experiments.codec_error`): the codec's error follows the motion, so a residual shows little of it.
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


def edge_change_sigma(sigma_a, sigma_b, length, correlation=0.0) -> np.ndarray:
    """Standard error of an edge's relative length change (``change``, a fraction) whose two end points' displacements
    have standard errors ``sigma_a`` and ``sigma_b`` (px per axis) and correlation ``correlation`` (per axis; 0:
    independent); ``length`` in frame a (px)."""
    sigma_a, sigma_b, length, rho = (np.asarray(v, dtype=np.float64) for v in (sigma_a, sigma_b, length, correlation))
    both = (rho > 0.0) & np.isfinite(sigma_a) & np.isfinite(sigma_b)  # an unbounded end stays unbounded
    with np.errstate(divide="ignore", invalid="ignore"):
        var = sigma_a**2 + sigma_b**2 - 2.0 * np.where(both, rho * sigma_a * sigma_b, 0.0)
        return np.sqrt(np.maximum(var, 0.0)) / length


def area_change_sigma(vertices: np.ndarray, sigma: np.ndarray, area, regularisation: "Regularisation | None" = None
                      ) -> np.ndarray:
    """Standard error of a triangle's relative area change from its vertices' displacement errors (first order:
    moving vertex i by e changes the area by g_i . e, g_i half the opposite side turned a right angle; the g_i sum
    to 0). ``vertices`` (T, 3, 2) px in frame a, ``sigma`` (T, 3) px per axis, ``area`` (T,) px^2 in frame a;
    ``regularisation``: the vertices' errors correlated as it says (None: independent)."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3, 2)
    sigma = np.asarray(sigma, dtype=np.float64).reshape(-1, 3)
    g = 0.5 * (v[:, [2, 0, 1]] - v[:, [1, 2, 0]])  # side opposite vertex 0, 1, 2 (halved; turned: same products)
    var = np.sum(sigma**2 * np.sum(g * g, axis=2), axis=1)
    if regularisation is not None:
        for i, j in ((0, 1), (1, 2), (2, 0)):
            rho = regularisation.correlation(v[:, j] - v[:, i], sigma[:, i], sigma[:, j])
            both = (rho > 0.0) & np.isfinite(sigma[:, i]) & np.isfinite(sigma[:, j])
            with np.errstate(invalid="ignore"):
                var = var + 2.0 * np.where(both, rho * sigma[:, i] * sigma[:, j] * np.sum(g[:, i] * g[:, j], axis=1),
                                           0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.maximum(var, 0.0)) / np.abs(np.asarray(area, dtype=np.float64))


@dataclass(frozen=True)
class Regularisation:
    """A dense registration's coupling of its nodes, for its errors: nodes ``grid_step_px`` apart, each registered
    with a window ``window_nodes`` grid steps wide, tied to its 4 neighbours by a membrane ``membrane`` times its
    data weight (the window's gradient products in the direction considered), on its deviation from a prior that
    is affine (``prior_nodes`` None) or the field itself Gaussian-smoothed over ``prior_nodes`` grid steps;
    ``independent_px`` of each point's sigma (the model term, px) is its own, not shared with its neighbours.

    Locally the lattice is taken as uniform: a node's data term is its window's noise, correlated with another
    node's in proportion to their windows' overlap; the membrane filters it, ``1 / (1 + r P(q))`` at wave vector
    ``q`` (``P`` the lattice Laplacian, times one minus the prior's smoothing). :func:`variance_factor` is the
    filtered over the unfiltered variance of a node (1 without membrane), :meth:`correlation` the correlation of two
    nodes' errors at an offset in px (bilinear between lattice offsets)."""

    grid_step_px: float
    window_nodes: float
    membrane: float
    prior_nodes: float | None = None
    independent_px: float = 0.0

    def correlation(self, offset_px, sigma_a=None, sigma_b=None) -> np.ndarray:
        """Correlation of the errors of two nodes ``offset_px`` (..., 2) px apart (0 beyond the model's lattice);
        given their sigmas (px), of their whole errors, the ``independent_px`` part of each not shared."""
        table = _correlation_table(float(self.window_nodes), float(self.membrane), self.prior_nodes)
        d = np.abs(np.asarray(offset_px, dtype=np.float64)) / float(self.grid_step_px)
        n = table.shape[0] - 1
        dx, dy = np.minimum(d[..., 0], n), np.minimum(d[..., 1], n)
        i0, j0 = np.minimum(dy.astype(np.int64), n - 1), np.minimum(dx.astype(np.int64), n - 1)
        ty, tx = dy - i0, dx - j0
        out = ((table[i0, j0] * (1 - tx) + table[i0, j0 + 1] * tx) * (1 - ty)
               + (table[i0 + 1, j0] * (1 - tx) + table[i0 + 1, j0 + 1] * tx) * ty)
        out = np.where(np.isfinite(d[..., 0]) & np.isfinite(d[..., 1]), out, 0.0)
        if sigma_a is None or sigma_b is None:
            return out
        sa, sb = (np.asarray(v, dtype=np.float64) for v in (sigma_a, sigma_b))
        m2 = float(self.independent_px) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            shared = np.sqrt(np.maximum(sa * sa - m2, 0.0) * np.maximum(sb * sb - m2, 0.0)) / (sa * sb)
        return out * np.where(np.isfinite(shared), shared, 0.0)


#: The model's lattice (nodes a side; the correlation table covers offsets up to half of it).
_LATTICE = 128
#: Membrane ratios of the variance factor's table (log-spaced; interpolated in log ratio, held beyond).
_RATIOS = np.geomspace(1e-3, 1e4, 57)


@lru_cache(maxsize=32)
def _spectra(window_nodes: float, prior_nodes: float | None) -> tuple[np.ndarray, np.ndarray]:
    """The windows' overlap spectrum (the data noise's covariance over the lattice) and the membrane's ``P(q)``."""
    q = 2.0 * np.pi * np.fft.fftfreq(_LATTICE)
    qx, qy = np.meshgrid(q, q)
    lap = 4.0 - 2.0 * np.cos(qx) - 2.0 * np.cos(qy)
    d = np.abs(np.fft.fftfreq(_LATTICE) * _LATTICE)
    tri = np.clip(1.0 - d / max(window_nodes, 1e-9), 0.0, None)
    overlap = np.real(np.fft.fft2(np.outer(tri, tri)))
    if prior_nodes is not None:  # the membrane acts on the field minus its smoothed self
        lap = lap * (1.0 - np.exp(-0.5 * prior_nodes**2 * lap))
    return np.maximum(overlap, 0.0), lap


@lru_cache(maxsize=32)
def _variance_table(window_nodes: float, prior_nodes: float | None) -> np.ndarray:
    overlap, lap = _spectra(window_nodes, prior_nodes)
    return np.array([np.mean(overlap / (1.0 + r * lap) ** 2) for r in _RATIOS]) / np.mean(overlap)


@lru_cache(maxsize=32)
def _correlation_table(window_nodes: float, membrane: float, prior_nodes: float | None) -> np.ndarray:
    overlap, lap = _spectra(window_nodes, prior_nodes)
    c = np.real(np.fft.ifft2(overlap / (1.0 + max(membrane, 0.0) * lap) ** 2))
    half = _LATTICE // 2
    return c[: half + 1, : half + 1] / c[0, 0]


def variance_factor(ratio, window_nodes: float, prior_nodes: float | None = None) -> np.ndarray:
    """A node's error variance with a membrane ``ratio`` times its data weight over its window's own (``s^2 / g``),
    element-wise (:class:`Regularisation`): 1 at ratio 0, falling as the membrane averages the neighbours in."""
    table = _variance_table(float(window_nodes), prior_nodes)
    r = np.clip(np.asarray(ratio, dtype=np.float64), _RATIOS[0], _RATIOS[-1])
    out = np.exp(np.interp(np.log(np.where(np.isfinite(r), r, _RATIOS[-1])), np.log(_RATIOS), np.log(table)))
    return np.where(np.asarray(ratio) > 0.0, out, 1.0)


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
                       model_sigma_px: float = MODEL_SIGMA_PX, membrane=None,
                       regularisation: Regularisation | None = None) -> RegistrationCheck:
    """:class:`RegistrationCheck` from a window's gradient products, residual and texture variances (the sigma with
    ``model_sigma_px`` added in quadrature). A dense registration gives its ``membrane`` weight per node (the units
    of the gradient products; scalar or per node) and its ``regularisation`` (window and prior): each principal
    direction's variance ``s^2 / g`` is then scaled by :func:`variance_factor` at ratio ``membrane / g``."""
    match = np.nan_to_num(window_match(residual_variance, texture_variance), nan=0.0)
    if membrane is None or regularisation is None:
        noise = larger_axis_sigma(txx, txy, tyy, residual_variance)
    else:
        txx, txy, tyy, s2 = (np.asarray(v, dtype=np.float64) for v in (txx, txy, tyy, residual_variance))
        spread = np.sqrt((txx - tyy) ** 2 + 4.0 * txy * txy)
        with np.errstate(divide="ignore", invalid="ignore"):
            variances = [np.maximum(s2, 0.0) / g * variance_factor(np.asarray(membrane) / g,
                                                                   regularisation.window_nodes,
                                                                   regularisation.prior_nodes)
                         for g in (0.5 * (txx + tyy + spread), 0.5 * (txx + tyy - spread))]
        smallest = 0.5 * (txx + tyy - spread)
        noise = np.where(np.isnan(s2), np.nan, np.where(smallest > 0.0, np.sqrt(np.maximum(*variances)), np.inf))
    sigma = np.hypot(noise, model_sigma_px)
    return RegistrationCheck(np.where((match < MIN_MATCH) | np.isnan(sigma), np.inf, sigma), match)

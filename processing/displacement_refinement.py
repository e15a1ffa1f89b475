"""Sub-pixel refinement of feature displacements by local image registration (beyond the seed, seed 7.2.2).

The seed located features to the pixel and smoothed trajectories to get sub-pixel coordinates (seed 5.1.2, 6.1:
"doubtful that the position of a feature could be known at a precision of more than +/- 1 pixel"). Here each
matched feature's frame-to-frame displacement is refined by pyramidal Lucas-Kanade registration of a small window
of the image around it, started from the displacement the feature matching found. The match guarantees the start
is within a pixel or two of the truth, which keeps the window from locking onto a neighbouring ridge (the failure
of purely local window methods on fingerprints).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from pydantic import Field

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.measurement_uncertainty import (
    MODEL_SIGMA_PX, RegistrationCheck, registration_check, window_match,
)
from skinstretch.processing.parameters import parameters
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.warp_registration import FASTMATH, second_order_kernel, shifted_window
from skinstretch.processing.jit import njit


@parameters
class SubpixelParams:
    """Options of :class:`SubpixelRefiner`, in mm (the evidence behind the defaults: docs/tuning-log.md).

    Parameters
    ----------
    window_mm, max_correction_mm : float
        Side of the square registration window (mm; about 1.4 ridge periods either side of the feature); largest
        change the refinement may make to the matched displacement (mm; beyond it the match is kept, flagged).
    pyramid_levels, normalize_sigma_mm : int, float or None
        Pyramid levels above full resolution of the registration (0: the match starts it within a pixel or two);
        scale of the local contrast normalisation of both images (:func:`local_normalize`; None: raw images).
    min_contrast, max_no_contact_fraction : float
        Grey-level standard deviation below which a pixel is out of contact; largest out-of-contact window fraction.
    wide_window_mm, target_precision_mm : float or None, float
        A second, wider window (None: none) for points whose predicted standard deviation (``s^2 T^-1`` of the first
        window) exceeds ``target_precision_mm``.
    span_window_mm, span_curvature_threshold : float
        Window (mm) :meth:`SubpixelRefiner.register_span` registers a span's two frames with; Wald statistic of the
        six second-order terms above which its second-order fit is kept (0: always).
    register_spans, span_direct_full : bool, float
        Whether the feature method also registers a longer span directly (``span_registration.SpanRegistration``;
        False: its chained motion alone); multiple of the threshold above at which it keeps that registration alone
        (its weight rises from 1/2 at the threshold).
    model_sigma_px : float
        The error a window's residual does not show (px per axis), added in quadrature to each predicted error.
    """

    window_mm: float = Field(0.6, gt=0)
    max_correction_mm: float = Field(0.05, gt=0)
    pyramid_levels: int = Field(0, ge=0, le=5)
    normalize_sigma_mm: float | None = Field(0.15, gt=0)
    min_contrast: float = Field(8.0, ge=0)
    max_no_contact_fraction: float = Field(0.05, ge=0, le=1)
    wide_window_mm: float | None = Field(0.8, gt=0)
    target_precision_mm: float = Field(0.0005, gt=0)
    span_window_mm: float = Field(0.8, gt=0)
    span_curvature_threshold: float = Field(30.0, ge=0)
    register_spans: bool = True
    span_direct_full: float = Field(8.0, gt=1)
    model_sigma_px: float = Field(MODEL_SIGMA_PX, ge=0)


#: Largest displacement gradient :meth:`SubpixelRefiner.register_span` accepts over a span (20 %: a failed fit).
_MAX_SPAN_GRADIENT = 0.2
#: A smaller window of :meth:`SubpixelRefiner.register_span` near the image edge keeps this much room in the second
#: image, px, for the warp's own reach beyond its start.
_SPAN_WARP_MARGIN_PX = 2
#: Gauss-Newton steps of :meth:`SubpixelRefiner.register_span` from the chained displacements (fewer when a step
#: moves no pixel by more than 1e-4 px): stopping there keeps the direct fit from chasing its own noise (11-frame
#: edge strain equal or lower than with 5 steps on every clip tried; evidence: docs/tuning-log.md).
SPAN_REGISTRATION_STEPS = 2


def local_normalize(image: np.ndarray, *, sigma_px: float) -> np.ndarray:
    """Local contrast normalisation ``(I - mean) / std`` over a Gaussian window, back to uint8 around 128.

    FTIR illumination is fixed to the prism, not to the skin (seed 3.5: darker light on the slopes of a ridge or
    valley, uneven lighting): as the finger slides, a skin point's brightness and contrast change, which biases
    any brightness-constancy registration. Removing the local mean and dividing by the local spread cancels
    smooth additive and multiplicative illumination changes.
    """
    if not sigma_px > 0:
        raise InvalidInputError(f"sigma_px must be positive, got {sigma_px!r}")
    f = np.asarray(image, dtype=np.float32)
    mean = _smooth(f, sigma_px)
    d = f - mean
    std = np.sqrt(np.maximum(_smooth(d * d, sigma_px), 0.0)) + 2.0  # box filters round a flat patch to -1e-7
    return np.clip(128.0 + 40.0 * d / std, 0, 255).astype(np.uint8)


def _smooth(f: np.ndarray, sigma_px: float) -> np.ndarray:
    """Two box filters of the same variance as a Gaussian of ``sigma_px``: constant cost whatever the scale."""
    w = max(1, int(round(np.sqrt(6.0 * sigma_px**2 + 1.0))))
    w += 1 - w % 2
    k = (w, w)
    return cv2.boxFilter(cv2.boxFilter(f, -1, k, borderType=cv2.BORDER_REFLECT), -1, k, borderType=cv2.BORDER_REFLECT)


def _smooth_half(f: np.ndarray, sigma_px: float) -> np.ndarray:
    """:func:`_smooth` computed at half resolution and interpolated back (the result varies over ~sigma, so
    half the samples carry it: a quarter of the box-filter work)."""
    h, w = f.shape
    if sigma_px < 4.0 or h < 8 or w < 8:
        return _smooth(f, sigma_px)
    half = cv2.resize(f, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    return cv2.resize(_smooth(half, sigma_px / 2.0), (w, h), interpolation=cv2.INTER_LINEAR)


@dataclass(frozen=True)
class RefinedDisplacements:
    """Result of a refinement: the displacement of every point, and whether it was refined."""

    displacement: np.ndarray  # (n, 2) float64, px (dx, dy)
    refined: np.ndarray  # (n,) bool: False -> the initial displacement was kept (see ``reason``)
    residual: np.ndarray  # (n,) float64, mean absolute grey-level residual of the registration (NaN if not refined)
    window_px: np.ndarray  # (n,) int64: side of the window that registered each point (the first one if not refined)


class SubpixelRefiner:
    """Refine frame-to-frame displacements of points by local Lucas-Kanade registration.

    Parameters
    ----------
    calibration : Calibration
        Pixel scale; the window and correction limits are converted once here.
    params : SubpixelParams, optional

    Examples
    --------
    >>> import numpy as np
    >>> from skinstretch.processing.pixel_scale import Calibration
    >>> rng = np.random.default_rng(0)
    >>> a = (rng.random((120, 120)) * 255).astype(np.uint8)
    >>> import cv2
    >>> a = cv2.GaussianBlur(a, (0, 0), 2)
    >>> b = np.roll(a, 1, axis=1)  # everything moves 1 px to the right
    >>> r = SubpixelRefiner(calibration=Calibration(px_per_mm=62.0))
    >>> out = r.refine(a, b, np.array([[60.0, 60.0]]), np.array([[0.6, 0.2]]))
    >>> (np.round(out.displacement, 2) + 0.0).tolist()  # + 0.0: no "-0.0"
    [[1.0, 0.0]]
    """

    def __init__(self, *, calibration: Calibration, params: SubpixelParams | None = None) -> None:
        self.params = params or SubpixelParams()
        self.calibration = calibration
        self._win = calibration.odd_px(self.params.window_mm, minimum=7)
        wide = self.params.wide_window_mm
        self._wide = calibration.odd_px(wide, minimum=7) if wide is not None else 0
        self._target_var = calibration.px(self.params.target_precision_mm) ** 2
        self._span_half = calibration.odd_px(self.params.span_window_mm, minimum=7) // 2
        self._max_corr = calibration.px(self.params.max_correction_mm)
        self._criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.002)

    @property
    def window_px(self) -> int:
        return self._win

    def prepare(self, image: np.ndarray, *, gradient: bool = True) -> "PreparedImage":
        """The image as :meth:`refine` wants it: normalised (when ``normalize_sigma_mm`` is set), with its
        out-of-contact map and, with ``gradient``, the gradient the uncertainty and wide-window steps use (a
        third of the time; computed on demand when left out). Call once per frame (thread-safe: the analysis
        calls it on the extraction threads)."""
        image = _as_gray(image, "image")
        sigma = self.calibration.px(self.params.normalize_sigma_mm or 0.15)
        f = image.astype(np.float32)
        d = f - _smooth_half(f, sigma)
        sq = np.multiply(d, d, out=f)
        var = _smooth_half(sq, sigma)
        # A flat field (glass, a saturated patch) smooths to a rounding error either side of 0: no NaN from it.
        std = np.sqrt(np.maximum(var, 0.0, out=var), out=var)
        # FTIR: skin out of contact shows no ridges, a flat bright field (seed 3.1).
        low = (std < self.params.min_contrast).view(np.uint8)
        integral = cv2.integral(low, sdepth=cv2.CV_32S)
        if self.params.normalize_sigma_mm is None:
            return PreparedImage(image, integral, image_gradient(image) if gradient else None)
        # 128 + 40 d / (std + 2), clipped, truncated to uint8 (in place: the same operations as written out).
        np.multiply(d, 40.0, out=d)
        np.divide(d, np.add(std, 2.0, out=std), out=d)
        np.add(d, 128.0, out=d)
        norm = np.clip(d, 0, 255, out=d).astype(np.uint8)
        return PreparedImage(norm, integral, image_gradient(norm) if gradient else None)

    def refine(
        self,
        prev_image,
        curr_image,
        points: np.ndarray,
        initial_displacement: np.ndarray,
    ) -> RefinedDisplacements:
        """Refine the displacement of ``points`` (frame ``prev_image``, (n, 2) x, y px) into ``curr_image``.

        The images should come from :meth:`prepare` (raw arrays work too: no normalisation, no contact test).
        Points whose window leaves the image or overlaps skin out of contact (by more than
        ``max_no_contact_fraction``) in either frame, whose registration fails to converge, or whose correction
        exceeds ``max_correction_mm`` keep their initial displacement and are flagged ``refined=False``.
        """
        prev_nc = curr_nc = None
        prev_given = prev_image
        if isinstance(prev_image, PreparedImage):
            prev_image, prev_nc = prev_image.image, prev_image.no_contact_integral
        if isinstance(curr_image, PreparedImage):
            curr_image, curr_nc = curr_image.image, curr_image.no_contact_integral
        prev_image = _as_gray(prev_image, "prev_image")
        curr_image = _as_gray(curr_image, "curr_image")
        if prev_image.shape != curr_image.shape:
            raise InvalidInputError(f"images differ in shape: {prev_image.shape} vs {curr_image.shape}")
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        init = _displacement_rows(initial_displacement, points, "initial_displacement")
        n = points.shape[0]
        if n == 0:
            return RefinedDisplacements(np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0), np.zeros(0, np.int64))
        disp, ok, residual = self._register(prev_image, curr_image, points, init, init, self._win, prev_nc, curr_nc)
        window = np.full(n, self._win, np.int64)
        if self._wide > self._win and ok.any():
            # Points the first window measures less precisely than the target: registered again, wider.
            var = self._predicted_variance(prev_given, curr_image, points, disp, self._win)
            again = np.flatnonzero(ok & ~(var <= self._target_var))
            if again.size:
                d2, ok2, r2 = self._register(prev_image, curr_image, points[again], disp[again], init[again],
                                             self._wide, prev_nc, curr_nc)
                take = again[ok2]
                disp[take], residual[take], window[take] = d2[ok2], r2[ok2], self._wide
        return RefinedDisplacements(disp, ok, residual, window)

    def _register(self, prev_image, curr_image, points, start, init, win, prev_nc, curr_nc):
        """One Lucas-Kanade pass with a ``win`` px window from ``start``; (displacement, ok, residual), the
        displacement ``init`` where not ok (see :meth:`refine`)."""
        p0 = points.astype(np.float32).reshape(-1, 1, 2)
        p1 = (points + start).astype(np.float32).reshape(-1, 1, 2)
        out, status, err = cv2.calcOpticalFlowPyrLK(
            prev_image,
            curr_image,
            p0,
            p1.copy(),
            winSize=(win, win),
            maxLevel=int(self.params.pyramid_levels),
            criteria=self._criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        d = out.reshape(-1, 2).astype(np.float64) - points
        ok = status.reshape(-1).astype(bool) & np.all(np.isfinite(d), axis=1)
        ok &= np.hypot(*(d - init).T) <= self._max_corr
        h, w = prev_image.shape
        half = win // 2
        inside = (
            (points[:, 0] >= half)
            & (points[:, 0] <= w - 1 - half)
            & (points[:, 1] >= half)
            & (points[:, 1] <= h - 1 - half)
        )
        q = points + np.where(np.isfinite(d), d, init)
        inside &= (q[:, 0] >= half) & (q[:, 0] <= w - 1 - half) & (q[:, 1] >= half) & (q[:, 1] <= h - 1 - half)
        ok &= inside
        # A window overlapping skin out of contact sees the prism's fixed, flat field there: biased toward zero.
        limit = self.params.max_no_contact_fraction
        for integral, where in ((prev_nc, points), (curr_nc, q)):
            if integral is not None:
                ok &= _window_fraction(integral, where, half) <= limit
        disp = np.where(ok[:, None], d, init)
        residual = np.where(ok, err.reshape(-1).astype(np.float64), np.nan)
        return disp, ok, residual

    def _window_halves(self, window_px: np.ndarray | None, n: int) -> np.ndarray:
        """Half-sides (n,) of the windows each point was registered with (``window_px``; default the first)."""
        if window_px is None:
            return np.full(n, self._win // 2, np.int64)
        halves = np.asarray(window_px, dtype=np.int64).reshape(-1) // 2
        if halves.shape[0] != n:
            raise InvalidInputError(f"window_px has {halves.shape[0]} rows for {n} points")
        return halves

    def _predicted_variance(self, prev_image, curr_image, points, disp, win) -> np.ndarray:
        """Predicted variance (px^2, trace of ``s^2 T^-1``) of each registered displacement: ``s^2`` the residual
        variance of the window after registration, ``T`` its structure tensor (NaN where it cannot be computed)."""
        cov = self.displacement_covariance(prev_image, curr_image, points, disp, np.full(len(points), win))
        return cov[:, 0, 0] + cov[:, 1, 1]

    def displacement_covariance(self, prev_image, curr_image, points: np.ndarray, displacement: np.ndarray,
                                window_px: np.ndarray | None = None) -> np.ndarray:
        """The covariance (n, 2, 2) px^2 of each registered displacement, ``s^2 T^-1``: ``s^2`` the residual
        variance of its window after registration (image noise and what the translation leaves), ``T`` the
        window's structure tensor. Parallel ridges make it long along them (the aperture problem). NaN where the
        window leaves an image or T is singular. ``window_px``: as :meth:`deformation_bias`."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        return _covariances(self._window_statistics(prev_image, curr_image, points, displacement,
                                                    self._window_halves(window_px, points.shape[0])))

    def covariance_and_match(self, prev_image, curr_image, points: np.ndarray, displacement: np.ndarray,
                             window_px: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`displacement_covariance` and each window's match after the motion
        (:func:`~skinstretch.processing.measurement_uncertainty.window_match`; NaN where it has no texture or
        leaves an image), from one pass over the windows."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        stats = self._window_statistics(prev_image, curr_image, points, displacement,
                                        self._window_halves(window_px, points.shape[0]))
        return _covariances(stats), window_match(stats[:, 3], stats[:, 4])

    def registration_check(self, prev_image, curr_image, points: np.ndarray,
                           displacement: np.ndarray) -> RegistrationCheck:
        """How well each displacement is known, from its window: predicted standard error and window match
        (:class:`~skinstretch.processing.measurement_uncertainty.RegistrationCheck`); NaN where the window leaves
        an image."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        txx, txy, tyy, s2, texture = self._window_statistics(prev_image, curr_image, points, displacement,
                                                             self._window_halves(None, points.shape[0])).T
        return registration_check(txx, txy, tyy, s2, texture, model_sigma_px=self.params.model_sigma_px)

    def _window_statistics(self, prev_image, curr_image, points: np.ndarray, displacement: np.ndarray,
                           halves: np.ndarray) -> np.ndarray:
        """:func:`_window_statistics_kernel`'s rows (Txx, Txy, Tyy, s^2, v) for ``points`` (n, 2) read at
        ``points + displacement`` in the second image."""
        a, gx, gy = _image_and_gradient(prev_image, "prev_image")
        b = _as_gray(curr_image.image if isinstance(curr_image, PreparedImage) else curr_image, "curr_image")
        displacement = _displacement_rows(displacement, points, "displacement")
        if points.shape[0] == 0:
            return np.zeros((0, 5))
        return _window_statistics_kernel(a, b, gx, gy, points, np.ascontiguousarray(displacement), halves)

    def span_residual_variance(self, prev_image, curr_image, points: np.ndarray,
                               displacement: np.ndarray) -> np.ndarray:
        """The residual variance (grey levels^2) of the :meth:`register_span` window around each point when
        ``curr_image`` is read at ``points + displacement`` (translation only, bilinear): how well that
        displacement explains the window, to compare two candidates for it. NaN where the window leaves an
        image."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        halves = np.full(points.shape[0], self._span_half, np.int64)
        return self._window_statistics(prev_image, curr_image, points, displacement, halves)[:, 3]

    def register_span(self, prev_image, curr_image, points: np.ndarray, displacement: np.ndarray, *,
                      min_window_mm: float | None = None) -> SpanFit:
        """The displacement of ``points`` from ``prev_image`` to a frame several frames later, ``curr_image``,
        registered directly: a second-order Lucas-Kanade registration (Gauss-Newton, up to
        :data:`SPAN_REGISTRATION_STEPS` steps) of the ``span_window_mm`` window around each point, started from
        ``displacement`` (the chained frame-to-frame displacements). Over a span the skin deforms by several per
        cent, which a translation-only window would read as noise and bias; an affine warp follows a uniform
        strain but reads a band of localized strain (a slip front) smoothed, its edges short; the second-order
        warp follows the band's curvature. Its six second-order terms are kept only where they are significant
        (``span_curvature_threshold``); elsewhere the affine model's estimate, less noisy, is kept. The
        displacement is that of the window's centre. Returns a :class:`SpanFit`: ``displacement`` as given where
        not ok (the window leaves an image, overlaps skin out of contact as :meth:`refine` judges it, the fit is
        singular, or it moves the point by more than ``max_correction_mm``), the Wald statistic of the curvature
        (0 where not ok). With ``min_window_mm``, a point whose window would leave an image is registered with the
        largest window around it that stays inside both, if at least that wide (noisier: for callers that average
        it, as the key frames' line does)."""
        prev_nc = prev_image.no_contact_integral if isinstance(prev_image, PreparedImage) else None
        curr_nc = curr_image.no_contact_integral if isinstance(curr_image, PreparedImage) else None
        a, gx, gy, b = _registration_pair(prev_image, curr_image)
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        init = _displacement_rows(displacement, points, "displacement")
        if points.shape[0] == 0:
            return SpanFit(np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0), np.zeros(0))
        halves = np.full(points.shape[0], self._span_half, np.int64)
        if min_window_mm is not None:
            h, w = a.shape
            room = np.full(points.shape[0], np.iinfo(np.int64).max)
            for where, margin in ((points, 0), (points + init, _SPAN_WARP_MARGIN_PX)):
                c = np.rint(np.nan_to_num(where, nan=-1e6)).clip(-1e6, 1e6).astype(np.int64)
                edge = np.minimum.reduce([c[:, 0], c[:, 1], w - 1 - c[:, 0], h - 1 - c[:, 1]])
                room = np.minimum(room, edge - margin)
            shrink = (room < halves) & (room >= self.calibration.odd_px(min_window_mm, minimum=7) // 2)
            halves[shrink] = room[shrink]
        d, ok, curvature = init.copy(), np.zeros(points.shape[0], bool), np.zeros(points.shape[0])
        sigma = np.full(points.shape[0], np.inf)
        limit = self.params.max_no_contact_fraction
        for half in np.unique(halves):
            sel = np.flatnonzero(halves == half)
            fit, ok_h = second_order_kernel(a, b, gx, gy, points[sel], init[sel], int(half), SPAN_REGISTRATION_STEPS)
            curved = fit[:, 8] > self.params.span_curvature_threshold
            delta = np.where(curved[:, None], fit[:, 0:2], fit[:, 6:8])
            d_h = init[sel] + delta
            ok_h &= np.all(np.isfinite(d_h), axis=1) & (np.hypot(*delta.T) <= self._max_corr)
            ok_h &= np.all(np.abs(fit[:, 2:6]) <= _MAX_SPAN_GRADIENT, axis=1)
            for integral, where in ((prev_nc, points[sel]), (curr_nc, points[sel] + init[sel])):
                if integral is not None:
                    ok_h &= _window_fraction(integral, where, int(half)) <= limit
            d[sel[ok_h]], ok[sel], curvature[sel[ok_h]] = d_h[ok_h], ok_h, fit[ok_h, 8]
            var = np.where(curved[:, None], fit[:, 9:11], fit[:, 11:13]).max(axis=1)
            sigma[sel[ok_h]] = np.sqrt(var[ok_h] + self.params.model_sigma_px ** 2)
        return SpanFit(d, ok, curvature, sigma)

    def deformation_bias(self, prev_image, points: np.ndarray, gradient: np.ndarray,
                         window_px: np.ndarray | None = None) -> np.ndarray:
        """The part of :meth:`refine`'s displacements at ``points`` that comes from the skin deforming inside the
        registration window, given the displacement gradient there (``gradient[i, j, l]``: d u_j / d x_l).

        A translation-only registration of a window whose content is stretched finds the displacement of the
        window's texture-weighted centre, not of its centre: with ``g`` the image gradient over the window,
        ``T = sum g g^T`` and ``u(x) = u(p) + G (x - p)``, it converges to ``u(p) + T^-1 sum g g^T G (x - p)``.
        The second term is returned (subtract it). It is small frame to frame (a strain of 0.3 % and a texture
        centre 5 px off: 0.015 px) but the same every frame, so it adds up along a trajectory (about a tenth of a
        pixel over 11 frames when the skin stretches, as much as all the noise). ``window_px``: the window each
        point was registered with (:attr:`RefinedDisplacements.window_px`; default the first window).
        """
        _, gx, gy = _image_and_gradient(prev_image, "prev_image")
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        gradient = np.asarray(gradient, dtype=np.float64).reshape(-1, 2, 2)
        if gradient.shape[0] != points.shape[0]:
            raise InvalidInputError(f"gradient has {gradient.shape[0]} rows for {points.shape[0]} points")
        if points.shape[0] == 0:
            return np.zeros((0, 2))
        halves = self._window_halves(window_px, points.shape[0])
        # The derivative operator of OpenCV's pyramidal Lucas-Kanade (Scharr); its scale cancels.
        return _deformation_bias_kernel(gx, gy, np.ascontiguousarray(points), np.ascontiguousarray(gradient), halves)




@njit(nogil=True, fastmath=FASTMATH)
def _deformation_bias_kernel(gx, gy, points, gradient, halves):
    """T^-1 sum_w g g^T G (x - p) per point, window half-side ``halves[i]`` (zero where the window leaves the image
    or T is singular)."""
    h, w = gx.shape
    out = np.zeros((points.shape[0], 2))
    for i in range(points.shape[0]):
        half = halves[i]
        px, py = points[i, 0], points[i, 1]
        c, r = int(np.round(px)), int(np.round(py))
        if c - half < 0 or r - half < 0 or c + half >= w or r + half >= h:
            continue
        g00, g01, g10, g11 = gradient[i, 0, 0], gradient[i, 0, 1], gradient[i, 1, 0], gradient[i, 1, 1]
        # sum g g^T G (x - p) from the moments of gx^2, gx gy, gy^2 times ox and oy (float32 row sums)
        txx = txy = tyy = 0.0
        mxx_x = mxx_y = mxy_x = mxy_y = myy_x = myy_y = 0.0
        ox0 = c - half - px
        for y in range(r - half, r + half + 1):
            oy = y - py
            gxr = gx[y, c - half:c + half + 1]
            gyr = gy[y, c - half:c + half + 1]
            z = np.float32(0.0)
            sxx = sxy = syy = sxx_x = sxy_x = syy_x = z
            for k in range(2 * half + 1):
                ox = np.float32(ox0 + k)
                ax = gxr[k]
                ay = gyr[k]
                pxx, pxy, pyy = ax * ax, ax * ay, ay * ay
                sxx += pxx
                sxy += pxy
                syy += pyy
                sxx_x += pxx * ox
                sxy_x += pxy * ox
                syy_x += pyy * ox
            txx += float(sxx)
            txy += float(sxy)
            tyy += float(syy)
            mxx_x += float(sxx_x)
            mxy_x += float(sxy_x)
            myy_x += float(syy_x)
            mxx_y += float(sxx) * oy
            mxy_y += float(sxy) * oy
            myy_y += float(syy) * oy
        bx = g00 * mxx_x + g01 * mxx_y + g10 * mxy_x + g11 * mxy_y
        by = g00 * mxy_x + g01 * mxy_y + g10 * myy_x + g11 * myy_y
        det = txx * tyy - txy * txy
        if det <= 1e-9 * (txx + tyy) ** 2 or det <= 0.0:
            continue
        out[i, 0] = (tyy * bx - txy * by) / det
        out[i, 1] = (txx * by - txy * bx) / det
    return out


@njit(nogil=True, fastmath=FASTMATH)
def _window_statistics_kernel(a, b, gx, gy, points, disp, halves):
    """Per point, rows (Txx, Txy, Tyy, s^2, v) over its window of half-side ``halves[i]``: T the structure tensor
    of ``a``, s^2 the variance of the residual ``b(x + d) - a(x)`` (bilinear), v the variance of ``a`` (its
    texture); NaN where the window leaves either image."""
    h, w = a.shape
    out = np.full((points.shape[0], 5), np.nan)
    for i in range(points.shape[0]):
        half = halves[i]
        c, r = int(np.round(points[i, 0])), int(np.round(points[i, 1]))
        if c - half < 0 or r - half < 0 or c + half >= w or r + half >= h:
            continue
        ix, iy, fx, fy, inside = shifted_window(b, c, r, half, disp[i, 0], disp[i, 1])
        if not inside:
            continue
        w00, w01 = np.float32((1.0 - fx) * (1.0 - fy)), np.float32(fx * (1.0 - fy))
        w10, w11 = np.float32((1.0 - fx) * fy), np.float32(fx * fy)
        txx = txy = tyy = 0.0
        rr = sa = saa = 0.0
        for y in range(r - half, r + half + 1):
            # float32 row sums (SIMD-wide), float64 window sums
            b0 = b[y + iy, c - half + ix:c + half + ix + 2]
            b1 = b[y + iy + 1, c - half + ix:c + half + ix + 2]
            ar = a[y, c - half:c + half + 1]
            gxr = gx[y, c - half:c + half + 1]
            gyr = gy[y, c - half:c + half + 1]
            z = np.float32(0.0)
            sxx = sxy = syy = srr = s1 = s2 = z
            for k in range(2 * half + 1):
                d = (b0[k] * w00 + b0[k + 1] * w01) + (b1[k] * w10 + b1[k + 1] * w11) - ar[k]
                ax = gxr[k]
                ay = gyr[k]
                sxx += ax * ax
                sxy += ax * ay
                syy += ay * ay
                srr += d * d
                s1 += ar[k]
                s2 += ar[k] * ar[k]
            txx += float(sxx)
            txy += float(sxy)
            tyy += float(syy)
            rr += float(srr)
            sa += float(s1)
            saa += float(s2)
        n = (2 * half + 1) ** 2
        out[i, 0] = txx
        out[i, 1] = txy
        out[i, 2] = tyy
        out[i, 3] = rr / (n - 2)
        out[i, 4] = max(saa / n - (sa / n) ** 2, 0.0)
    return out


def _covariances(stats: np.ndarray) -> np.ndarray:
    """``s^2 T^-1`` (n, 2, 2) from :func:`_window_statistics_kernel`'s rows; NaN where T is singular or unknown."""
    txx, txy, tyy, s2 = stats[:, :4].T
    det = txx * tyy - txy * txy
    ok = np.isfinite(det) & (det > 0.0) & (det > 1e-9 * (txx + tyy) ** 2)
    out = np.full((stats.shape[0], 2, 2), np.nan)
    k = s2[ok] / det[ok]
    out[ok, 0, 0], out[ok, 1, 1] = k * tyy[ok], k * txx[ok]
    out[ok, 0, 1] = out[ok, 1, 0] = -k * txy[ok]
    return out


class SpanFit(NamedTuple):
    """What :meth:`SubpixelRefiner.register_span` measured of each point: ``displacement`` (n, 2) px, ``ok`` (n,),
    ``curvature`` (n,), the Wald statistic of the window's second-order terms (compare with
    ``SubpixelParams.span_curvature_threshold``), and ``sigma`` (n,) px, the predicted standard error of the
    displacement along its less certain axis (the fit's residual variance over its Hessian, with ``model_sigma_px``
    in quadrature; inf where not ok)."""

    displacement: np.ndarray
    ok: np.ndarray
    curvature: np.ndarray
    sigma: np.ndarray


@dataclass(frozen=True)
class PreparedImage:
    """A frame ready for :meth:`SubpixelRefiner.refine`: registration image and integral of its no-contact mask."""

    image: np.ndarray
    no_contact_integral: np.ndarray  # int32 integral image of the no-contact mask
    gradient: tuple[np.ndarray, np.ndarray] | None = None  # float32 (gx, gy) of ``image`` (:func:`image_gradient`)


def _window_fraction(integral: np.ndarray, points: np.ndarray, half: int) -> np.ndarray:
    """Fraction of the (2 half + 1)^2 window around each point that is set in the mask of ``integral``."""
    return _window_fraction_kernel(integral, np.ascontiguousarray(points, dtype=np.float64), int(half))


@njit(nogil=True)
def _window_fraction_kernel(integral, points, half):
    h, w = integral.shape[0] - 1, integral.shape[1] - 1
    out = np.empty(points.shape[0])
    for i in range(points.shape[0]):
        # np.round: half to even, as numpy rounds
        c = min(max(int(np.round(points[i, 0])), 0), w - 1)
        r = min(max(int(np.round(points[i, 1])), 0), h - 1)
        r0, r1 = min(max(r - half, 0), h), min(max(r + half + 1, 0), h)
        c0, c1 = min(max(c - half, 0), w), min(max(c + half + 1, 0), w)
        total = integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]
        out[i] = total / max((r1 - r0) * (c1 - c0), 1)
    return out


def image_gradient(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grey-level gradient (gx, gy), float32 grey levels per pixel, of a uint8 image: Scharr, as OpenCV's
    Lucas-Kanade differentiates (/32). Computed once per frame by :meth:`SubpixelRefiner.prepare`."""
    a = image.astype(np.float32)
    return (cv2.Scharr(a, cv2.CV_32F, 1, 0, scale=1.0 / 32.0), cv2.Scharr(a, cv2.CV_32F, 0, 1, scale=1.0 / 32.0))


def _registration_pair(prev_image, curr_image) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(a, gx, gy, b): the first image with its gradient, and the second, grey and of the same shape (prepared
    images or arrays)."""
    a, gx, gy = _image_and_gradient(prev_image, "prev_image")
    if isinstance(curr_image, PreparedImage):
        curr_image = curr_image.image
    b = _as_gray(curr_image, "curr_image")
    if a.shape != b.shape:
        raise InvalidInputError(f"images differ in shape: {a.shape} vs {b.shape}")
    return a, gx, gy, b


def _displacement_rows(displacement, points: np.ndarray, name: str) -> np.ndarray:
    """``displacement`` as (n, 2) float64 rows, one per row of ``points``, or an error naming it."""
    rows = np.ascontiguousarray(displacement, dtype=np.float64).reshape(-1, 2)
    if rows.shape != points.shape:
        raise InvalidInputError(f"{name} has shape {rows.shape}, expected {points.shape}")
    return rows


def _image_and_gradient(image, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(uint8 image, gx, gy) of a :class:`PreparedImage` (its stored gradient) or of a raw image."""
    if isinstance(image, PreparedImage):
        if image.gradient is not None:
            return image.image, image.gradient[0], image.gradient[1]
        image = image.image
    image = _as_gray(image, name)
    gx, gy = image_gradient(image)
    return image, gx, gy


def _as_gray(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2:
        raise InvalidInputError(f"{name} must be a 2-D grey image, got shape {image.shape}")
    if image.dtype != np.uint8:
        if not np.issubdtype(image.dtype, np.number):
            raise InvalidInputError(f"{name} must be numeric, got {image.dtype}")
        image = np.clip(image, 0, 255).astype(np.uint8)
    return image

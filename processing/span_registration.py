"""The motion of tracked points over a longer span, registered directly between the span's two frames (beyond the
seed): :class:`SpanRegistration` for the features, :class:`SpanFrames` shared with the flow's ``SpanRefiner``, and
the predicted standard error of a sample's points (:class:`SampleUncertainty`)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from skinstretch.processing.displacement_refinement import SubpixelRefiner
from skinstretch.processing.measurement_uncertainty import MIN_MATCH, RegistrationCheck
from skinstretch.processing.tracking import MotionSample


class SpanFrames:
    """Frames prepared once for the spans that use them, in increasing first frame (the features'
    :class:`SpanRegistration` and the flow's ``SpanRefiner``): a frame is prepared as the second frame of a span,
    reused as the first frame of later ones, and dropped once the spans have passed it. ``frame(j)`` gives frame j,
    ``prepare`` turns it into what the registration takes. Safe to share between threads."""

    def __init__(self, frame: Callable[[int], np.ndarray], prepare: Callable[[np.ndarray], Any], *,
                 keep: int = 0) -> None:
        self._frame = frame
        self._prepare = prepare
        self._keep = int(keep)
        self._prepared: dict[int, Any] = {}
        self._lock = threading.RLock()

    def pair(self, k0: int, k1: int) -> tuple[Any, Any]:
        """Frames ``k0`` and ``k1`` prepared; frames more than ``keep`` before ``k0`` are dropped (no later span
        starts before them)."""
        with self._lock:
            for j in [j for j in self._prepared if j < k0 - self._keep]:
                del self._prepared[j]
            return self.get(k0), self.get(k1)

    def get(self, j: int) -> Any:
        with self._lock:
            if j not in self._prepared:
                self._prepared[j] = self._prepare(self._frame(j))
            return self._prepared[j]


class SpanRegistration:
    """The motion of tracked points over a longer span (the 11-frame strain), measured twice and combined (beyond
    the seed).

    A span's chained motion (:meth:`Trajectories.motion`) sums its frame-to-frame displacements, and with them
    their errors: random, and the part of each step's deformation bias that
    :meth:`~skinstretch.processing.displacement_refinement.SubpixelRefiner.deformation_bias` leaves, all one way
    where the shear changes within a window. Registering the span's two frames directly
    (:meth:`~skinstretch.processing.displacement_refinement.SubpixelRefiner.register_span`, an affine or, where the
    displacement is curved, a second-order window started from the chained motion) has neither, but the noise of one
    registration across a larger deformation. On real and simulated prints the two err about equally and mostly
    independently (either one alone is worse than their mean on some prints and fields), so their mean is kept,
    except where the window's displacement is plainly curved: there the chained frame-to-frame windows each
    smoothed the curvature, all one way, and the direct registration's weight rises to 1 (:func:`direct_weight`,
    ``SubpixelParams.span_direct_full``). A point the direct registration cannot measure keeps its chained motion.
    ``frame(j)`` gives frame j, each prepared once (:class:`SpanFrames`: call :meth:`refine` in increasing
    ``frame_a``).
    """

    def __init__(self, refiner: SubpixelRefiner, frame: Callable[[int], np.ndarray], *,
                 frames: SpanFrames | None = None) -> None:
        self.refiner = refiner
        self._frames = frames if frames is not None else SpanFrames(frame, refiner.prepare)
        self.seconds = 0.0  # spent in refine and refine_all (the stage's share of the analysis' time)

    def refine(self, sample: MotionSample) -> MotionSample:
        """``sample`` (chained, ``frame_b`` > ``frame_a`` + 1) with each point's displacement the chained one and
        the direct registration's combined (their mean, or mostly the direct one where the displacement is
        curved)."""
        if len(sample) == 0:
            return sample
        t0 = time.perf_counter()
        out = self._registered(sample, self._frames.pair(int(sample.frame_a), int(sample.frame_b)))
        self.seconds += time.perf_counter() - t0
        return out

    def refine_all(self, samples: Sequence[MotionSample], *, threads: int = 1) -> list[MotionSample]:
        """:meth:`refine` of each of ``samples`` (in increasing ``frame_a``), in order; the registrations run on
        ``threads`` threads (the kernel releases the GIL), the frames are prepared in this one."""
        t0 = time.perf_counter()
        try:
            return self._refine_all(samples, threads)
        finally:
            self.seconds += time.perf_counter() - t0

    def _refine_all(self, samples: Sequence[MotionSample], threads: int) -> list[MotionSample]:
        pairs = [self._frames.pair(int(s.frame_a), int(s.frame_b)) if len(s) else None for s in samples]

        def one(sample: MotionSample, pair: tuple[Any, Any] | None) -> MotionSample:
            return sample if pair is None else self._registered(sample, pair)

        if threads <= 1 or len(samples) <= 1:
            return list(map(one, samples, pairs))
        with ThreadPoolExecutor(min(int(threads), len(samples)), thread_name_prefix="span-registration") as pool:
            return list(pool.map(one, samples, pairs))

    def _registered(self, sample: MotionSample, pair: tuple[Any, Any]) -> MotionSample:
        fit = self.refiner.register_span(pair[0], pair[1], sample.points, sample.displacement)
        weight = direct_weight(fit.curvature, self.refiner.params.span_curvature_threshold,
                               self.refiner.params.span_direct_full)[:, None]
        disp = np.where(fit.ok[:, None], weight * fit.displacement + (1.0 - weight) * sample.displacement,
                        sample.displacement)
        return checked(MotionSample(int(sample.frame_a), int(sample.frame_b), sample.points, disp, sample.ids),
                       self.refiner.registration_check(pair[0], pair[1], sample.points, disp))


class SampleUncertainty:
    """Each point's predicted standard error (``MotionSample.sigma``, px) of a measured sample, from the
    registration window around it in the sample's two frames (``SubpixelRefiner.registration_check``): what a
    window registration of that displacement would leave as residual, over the window's texture. ``frames``: the
    prepared frames, shared with :class:`SpanRegistration` (call in increasing ``frame_a``)."""

    def __init__(self, refiner: SubpixelRefiner, frames: SpanFrames) -> None:
        self.refiner = refiner
        self._frames = frames

    def __call__(self, sample: MotionSample) -> MotionSample:
        if len(sample) == 0 or sample.sigma is not None:
            return sample
        a, b = self._frames.pair(int(sample.frame_a), int(sample.frame_b))
        return checked(sample, self.refiner.registration_check(a, b, sample.points, sample.displacement))


def checked(sample: MotionSample, check: RegistrationCheck) -> MotionSample:
    """``sample`` with each point's sigma and match (``check``), doubted as a whole when most of its windows do not
    match after the measured motion (a self-check: a chain gone astray, a mislinked pair of frames)."""
    match = float(np.median(check.match)) if check.match.size else float("nan")
    doubt = sample.doubt
    if not doubt and match < MIN_MATCH:
        doubt = f"the frames do not match after the measured motion (median window match {match:.2f} < {MIN_MATCH})"
    return MotionSample(int(sample.frame_a), int(sample.frame_b), sample.points, sample.displacement, sample.ids,
                        check.sigma, check.match, doubt)


def direct_weight(curvature: np.ndarray, threshold: float, full: float) -> np.ndarray:
    """The weight of a span's direct registration against its chained motion, from the Wald statistic of the
    window's curvature: 1/2 up to ``threshold``, rising linearly to 1 at ``full`` times it
    (``SubpixelParams.span_direct_full``); a statistic that is not a number counts as no curvature.

    >>> direct_weight(np.array([0.0, 30.0, 135.0, 240.0, np.inf, np.nan]), 30.0, 8.0).tolist()
    [0.5, 0.5, 0.75, 1.0, 1.0, 0.5]
    """
    curvature = np.nan_to_num(np.asarray(curvature, dtype=np.float64), nan=0.0, posinf=np.inf)
    if threshold <= 0.0:
        return np.where(curvature > 0.0, 1.0, 0.5)
    return 0.5 + 0.5 * np.clip((curvature / threshold - 1.0) / (full - 1.0), 0.0, 1.0)

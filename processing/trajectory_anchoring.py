"""Trajectories anchored to key frames by direct registration (beyond the seed): the drift of a chain of
frame-to-frame steps, corrected.

A trajectory's positions are the running sum of its frame-to-frame displacements (seed 5.1.2), and with them the
sum of their errors. What digital image correlation does against this, incremental correlation against a
reference frame replaced when it has aged, is done here at key frames: every ``interval`` frames and at the
sequence's last frame, each point of a linked run is registered directly from its reference key frame
(:meth:`~skinstretch.processing.displacement_refinement.SubpixelRefiner.register_span`, started from the chained
motion); the difference from the chained position is the drift, smoothed over ``smoothing`` neighbouring key
frames (their registrations' noise) and spread linearly over the frames between. A reference serves for
``reference_span`` frames (then the key frame reached replaces it), or until a registration from it fails: then
the key frame before, at its anchored position, serves, and the failed key frame is chained on from it. Each
anchored position carries its variance relative to the run's first key frame: the registrations' predicted
variances (``SpanFit.sigma``) summed along its chain of references.

On plain glass the corrections follow the drift closely (a line over :data:`GLASS_SMOOTHING_KEY_FRAMES`); over a
ridge or valley whose shading was removed each registration also carries what that step leaves of the glass-fixed
patterns, averaged by a line over :data:`SHAPE_SMOOTHING_KEY_FRAMES`; where a shape's shading stayed in, the
analysis plan leaves the trajectories chained. A registration that jumps from its chained guess
(:data:`MAX_CORRECTION_STEP_SPREADS`) is not taken. The measurements behind these choices: docs/tuning-log.md.

Hand-written: no library anchors feature trajectories to key frames (OpenCV's and scikit-image's trackers chain).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from skinstretch.processing.displacement_refinement import SubpixelRefiner
from skinstretch.processing.errors import InvalidInputError

__all__ = [
    "EDGE_WINDOW_MM",
    "GLASS_SMOOTHING_KEY_FRAMES",
    "KeyframeAnchoring",
    "KeyframeCorrections",
    "MAX_CORRECTION_STEP_SPREADS",
    "MIN_CORRECTION_STEP_PX",
    "MIN_JUMP_RESIDUAL_RATIO",
    "SHAPE_SMOOTHING_KEY_FRAMES",
]

#: A key frame's registration that moves a point by more than this many robust spreads (1.4826 x the median over
#: the points sharing its reference) from its chained guess is not taken: the point is chained on. Between key
#: frames the drift changes little; a window whose parallel ridges leave its motion along them ill-determined can
#: slide along them. On flatL (40 frames, ~165 points a key frame) good steps reached 7.0 spreads, such a slide 8.2-15.6
#: (0.33-0.54 px); a good step not taken is taken up at the next key frame, a bad one taken moves its trajectory.
MAX_CORRECTION_STEP_SPREADS = 8.0
#: ... and by more than this, px: where the drift is the same everywhere the spread is near 0.
MIN_CORRECTION_STEP_PX = 0.05
#: Such a jump is taken all the same where the chained guess leaves this many times the residual variance of the
#: registration in its window (translation only): where the chain itself went astray. In a copy compressed by a
#: video codec a point's consecutive steps can all read short (valleyL at crf 12: a tenth of a pixel a frame, 4 px
#: off after 40 frames); its registrations then fit 1.1-6 times better than its chained guesses, while the slides
#: along ridges fit 0.8-0.98 times as well as their guesses (flatL and its copies, 40 frames; the good steps'
#: ratios 0.96-1.08, 5th to 95th percentile).
MIN_JUMP_RESIDUAL_RATIO = 1.1
#: The key frames a correction's line is fitted to on plain glass: the drift followed closely (3 against 7 on the
#: four flat fields, 36 clips: 11-frame edge strain 0.100 against 0.102 % mean; module docstring).
GLASS_SMOOTHING_KEY_FRAMES = 3
#: ... and over a ridge or valley, where each registration also carries what the glass-shading step leaves of the
#: glass-fixed patterns: a line over a reference's span (18 clips: 11-frame edge strain 0.164 % mean against 0.186
#: with 3 key frames, 0.174 chained).
SHAPE_SMOOTHING_KEY_FRAMES = 9
#: Near the image edge, where the span window (0.8 mm) would leave it, a point is registered with the largest window
#: that fits, if at least this wide, mm: else it could only be chained (a point 20 px from the edge drifted 0.7 px
#: in 40 frames over valleyL, 2.7 px in a crf-12 copy). Over the module docstring's clips: 11-frame edge strain
#: 0.101 -> 0.099 % mean on the flat fields (24 of 36 clips better, worst 0.144 -> 0.145 %), 0.1645 -> 0.1638 % over
#: the shapes; our print's drift 0.083 -> 0.078 px (flat), 0.073 -> 0.071 px (shapes).
EDGE_WINDOW_MM = 0.4


@dataclass(frozen=True)
class KeyframeCorrections:
    """Per run (``group``) and key frame: the correction (``dx``, ``dy`` px) to add to its chained positions, and the
    variance (px^2 per axis) of the anchored position relative to the run's first key frame (the key frames'
    registrations along its chain of references; inf where one could not be used); sorted by (group, frame).
    :meth:`at` and :meth:`variance_at` interpolate between a run's key frames."""

    group: np.ndarray  # (m,) int64
    frame: np.ndarray  # (m,) int64
    dx: np.ndarray  # (m,) float64
    dy: np.ndarray  # (m,) float64
    variance: np.ndarray | None = None  # (m,) float64 px^2; None: zeros

    def at(self, group: np.ndarray, frame: np.ndarray) -> np.ndarray:
        """(n, 2) corrections of rows (``group``, ``frame``): linear between the run's key frames on either side,
        the nearest one's before its first and after its last, 0 for a run without key frames."""
        c = np.column_stack([self.dx, self.dy])
        return self._interpolated(group, frame, c)

    def variance_at(self, group: np.ndarray, frame: np.ndarray) -> np.ndarray:
        """(n,) variances of rows (``group``, ``frame``), interpolated as :meth:`at` (an upper bound between key
        frames: their errors are not independent of each other's)."""
        v = np.zeros(self.group.size) if self.variance is None else self.variance
        with np.errstate(invalid="ignore"):  # inf * 0 where a row sits on the other key frame
            out = self._interpolated(group, frame, np.where(np.isinf(v), 1e300, v)[:, None])[:, 0]
        return np.where(out >= 1e250, np.inf, out)

    def _interpolated(self, group: np.ndarray, frame: np.ndarray, c: np.ndarray) -> np.ndarray:
        group = np.asarray(group, dtype=np.int64)
        frame = np.asarray(frame, dtype=np.int64)
        out = np.zeros((group.size, c.shape[1]))
        if self.group.size == 0 or group.size == 0:
            return out
        span = int(max(int(self.frame.max()), int(frame.max()))) + 2
        keys = self.group * span + self.frame
        q = group * span + frame
        hi = np.searchsorted(keys, q, side="left")  # first key frame at or after the row, any run
        lo = hi - 1
        hi_c = np.minimum(hi, keys.size - 1)
        lo_c = np.maximum(lo, 0)
        has_hi = (hi < keys.size) & (self.group[hi_c] == group)
        has_lo = (lo >= 0) & (self.group[lo_c] == group)
        both = has_hi & has_lo
        f0, f1 = self.frame[lo_c], self.frame[hi_c]
        t = np.where(both, (frame - f0) / np.maximum(f1 - f0, 1), 0.0)[:, None]
        out[both] = ((1.0 - t) * c[lo_c] + t * c[hi_c])[both]
        only_hi = has_hi & ~has_lo
        out[only_hi] = c[hi_c][only_hi]
        only_lo = has_lo & ~has_hi
        out[only_lo] = c[lo_c][only_lo]
        return out


class KeyframeAnchoring:
    """Key-frame corrections of chained trajectories (module docstring). Feed the key frames in increasing order
    (:meth:`add`: frame k, a multiple of ``interval``, with the runs present and their chained positions), then
    take :meth:`corrections`. ``frame(j)`` gives frame j as the refiner registers it (prepared here, a key frame at
    a time; only the key frames still some run's reference are kept)."""

    def __init__(self, refiner: SubpixelRefiner, frame: Callable[[int], np.ndarray], *, interval: int,
                 reference_span: int, smoothing: int = GLASS_SMOOTHING_KEY_FRAMES) -> None:
        if int(interval) < 2 or int(reference_span) < int(interval) or int(smoothing) < 2:
            raise InvalidInputError(f"key frames need an interval >= 2, a reference span >= it and a smoothing of "
                                    f">= 2 key frames, got {interval}, {reference_span} and {smoothing}")
        self.refiner = refiner
        self.interval = int(interval)
        self.reference_span = int(reference_span)
        self.smoothing = int(smoothing)
        self._frame = frame
        self._prepared: dict[int, Any] = {}
        # per run: reference frame, anchored position there, last key frame seen and chained / anchored there
        self._ref = np.zeros(0, np.int64)
        self._ref_xy = np.zeros((0, 2))
        self._ref_var = np.zeros(0)  # variance of the anchored position at the reference (module docstring)
        self._last_var = np.zeros(0)
        self._last = np.full(0, -1, np.int64)
        self._last_chained = np.zeros((0, 2))
        self._last_anchored = np.zeros((0, 2))
        self._rows: list[tuple[np.ndarray, int, np.ndarray, np.ndarray]] = []  # (groups, frame, corrections, var)
        self._previous = -1
        self._final = False
        self.seconds = 0.0  # spent in add (the stage's share of the analysis' time)

    def _grow(self, n: int) -> None:
        have = self._ref.size
        if n <= have:
            return
        n = max(n, 2 * have)
        self._ref = np.concatenate([self._ref, np.full(n - have, -1, np.int64)])
        self._last = np.concatenate([self._last, np.full(n - have, -1, np.int64)])
        for name in ("_ref_xy", "_last_chained", "_last_anchored"):
            setattr(self, name, np.concatenate([getattr(self, name), np.zeros((n - have, 2))]))
        for name in ("_ref_var", "_last_var"):
            setattr(self, name, np.concatenate([getattr(self, name), np.zeros(n - have)]))

    def add(self, k: int, group: np.ndarray, chained: np.ndarray, *, final: bool = False) -> None:
        """Key frame ``k``: the runs present (``group``, distinct ids >= 0) and their chained positions (n, 2) px.
        ``final``: the sequence's last frame, a key frame whatever its number (the drift after the last multiple of
        the interval is corrected too); no key frame follows it."""
        t0 = time.perf_counter()
        k = int(k)
        if self._final or k <= self._previous or (k % self.interval and not final):
            raise InvalidInputError(f"key frames come in increasing multiples of {self.interval}, then the last "
                                    f"frame: got {k} after {self._previous}")
        previous, self._previous, self._final = self._previous, k, bool(final)
        group = np.asarray(group, dtype=np.int64)
        chained = np.asarray(chained, dtype=np.float64).reshape(-1, 2)
        if group.size:
            self._grow(int(group.max()) + 1)
        # A run seen at the previous key frame continues; any other starts here, with this frame as reference.
        cont = (self._last[group] == previous) & (previous >= 0)
        start = ~cont
        anchored = chained.copy()
        g = group[cont]
        guess = self._last_anchored[g] + chained[cont] - self._last_chained[g]
        refs = self._ref[g]
        fitted = guess.copy()
        failed = np.zeros(g.size, bool)
        fit_var = np.full(g.size, np.inf)  # a chained guess's error is not known here
        for r in np.unique(refs):
            sel = np.flatnonzero(refs == r)
            origin = self._ref_xy[g[sel]]
            reference, current = self._image(int(r)), self._image(k)
            fit = self.refiner.register_span(reference, current, origin, guess[sel] - origin,
                                             min_window_mm=EDGE_WINDOW_MM)
            fitted[sel] = np.where(fit.ok[:, None], origin + fit.displacement, guess[sel])
            failed[sel] = ~fit.ok
            fit_var[sel] = np.where(fit.ok, fit.sigma ** 2, np.inf)
            jumped = np.flatnonzero(_jumped(fitted[sel] - guess[sel], fit.ok))
            if jumped.size:  # kept where the registration explains the key frame clearly better than the chain
                at = origin[jumped]
                chain = self.refiner.span_residual_variance(reference, current, at, guess[sel[jumped]] - at)
                registered = self.refiner.span_residual_variance(reference, current, at, fitted[sel[jumped]] - at)
                jumped = jumped[~(chain >= MIN_JUMP_RESIDUAL_RATIO * registered)]
                fitted[sel[jumped]] = guess[sel[jumped]]
                fit_var[sel[jumped]] = np.inf
        anchored[cont] = fitted
        var = np.zeros(group.size)
        var[cont] = self._ref_var[g] + fit_var
        self._rows.append((group, k, anchored - chained, var))
        # References: a new run's is this frame, an aged one moves to this frame; after a failed registration (this
        # frame black or saturated, the window out of view or out of contact) the previous key frame serves.
        here = start.copy()
        here[np.flatnonzero(cont)[~failed & (k - refs >= self.reference_span)]] = True
        self._ref[group[here]] = k
        self._ref_xy[group[here]] = anchored[here]
        self._ref_var[group[here]] = var[here]
        back = np.flatnonzero(cont)[failed]
        self._ref[group[back]] = previous
        self._ref_xy[group[back]] = self._last_anchored[group[back]]
        self._ref_var[group[back]] = self._last_var[group[back]]
        self._last[group] = k
        self._last_var[group] = var
        self._last_chained[group] = chained
        self._last_anchored[group] = anchored
        live = set(self._ref[self._last == k].tolist()) | {k}
        for j in [j for j in self._prepared if j not in live]:
            del self._prepared[j]
        self.seconds += time.perf_counter() - t0

    def _image(self, j: int) -> Any:
        if j not in self._prepared:
            self._prepared[j] = self.refiner.prepare(self._frame(j))
        return self._prepared[j]

    def corrections(self) -> KeyframeCorrections:
        """The corrections of every run at its key frames, smoothed along the run (:func:`_line_fits` over
        ``smoothing`` key frames: the registrations' noise averaged, a steady drift kept); a run's first key frame
        keeps 0."""
        group = np.concatenate([np.zeros(0, np.int64)] + [g for g, _, _, _ in self._rows])
        if group.size == 0:  # no key frame, or no run present at any
            z = np.zeros(0)
            return KeyframeCorrections(group, group.copy(), z, z, z)
        frame = np.concatenate([np.full(g.size, k, np.int64) for g, k, _, _ in self._rows])
        c = np.concatenate([d for _, _, d, _ in self._rows])
        var = np.concatenate([v for _, _, _, v in self._rows])
        order = np.lexsort((frame, group))
        group, frame, c, var = group[order], frame[order], c[order], var[order]
        smoothed = _line_fits(group, frame / self.interval, c, self.smoothing)
        smoothed[np.r_[True, group[1:] != group[:-1]]] = 0.0  # a run's first key frame is its reference
        return KeyframeCorrections(group, frame, *smoothed.T.copy(), var)


def _jumped(step: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Which registered points (``ok``) moved from their chained guesses by ``step`` (n, 2) px more than
    :data:`MAX_CORRECTION_STEP_SPREADS` robust spreads of the others and :data:`MIN_CORRECTION_STEP_PX`."""
    size = np.hypot(*step.T)
    if int(ok.sum()) < 8:
        return np.zeros(size.shape, bool)
    bound = max(MAX_CORRECTION_STEP_SPREADS * 1.4826 * float(np.median(size[ok])), MIN_CORRECTION_STEP_PX)
    return ok & (size > bound)


def _line_fits(group: np.ndarray, time: np.ndarray, c: np.ndarray, window: int) -> np.ndarray:
    """Each key frame's correction (rows of ``c`` sorted by run, then ``time``, in intervals) from a line in time
    fitted to the ``window`` nearest key frames of its run: centred on it inside the run, shifted inside at the
    run's ends (the line's end there), the whole run where it is shorter (a run of two as measured). A steady drift
    is kept, the registrations' noise averaged; with 3 evenly spaced key frames: an inner one's mean with its two
    neighbours, a run's last (5 c[j] + 2 c[j-1] - c[j-2]) / 6. Prefix sums over the rows: every fit at once."""
    n = group.size
    start = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    length = np.diff(np.r_[start, n])
    run_start = np.repeat(start, length)
    run_len = np.repeat(length, length)
    j = np.arange(n) - run_start  # index inside the run
    w = np.minimum(window, run_len)
    lo = np.clip(j - window // 2, 0, run_len - w)
    t = np.asarray(time, dtype=np.float64) - time[run_start]  # from the run's first: the prefix sums stay small
    a, b = run_start + lo, run_start + lo + w

    def window_sum(v: np.ndarray) -> np.ndarray:
        p = np.concatenate([np.zeros((1,) + v.shape[1:]), np.cumsum(v, axis=0)])
        return p[b] - p[a]

    s0, s1, s2 = w.astype(np.float64), window_sum(t), window_sum(t * t)
    sc, stc = window_sum(c), window_sum(t[:, None] * c)
    mean_t = s1 / s0
    sxx = s2 - s1 * mean_t
    flat = sxx <= 1e-9  # a window of one key frame
    slope = np.where(flat[:, None], 0.0, (stc - mean_t[:, None] * sc) / np.where(flat, 1.0, sxx)[:, None])
    return sc / s0[:, None] + slope * (t - mean_t)[:, None]

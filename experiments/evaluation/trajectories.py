"""Trajectories against the truth displacement field: how far each tracked point drifts from the skin point it
started on. Needs no feature truth, so it scores real-print scenes (see
:mod:`skinstretch.simulators.print_texture`) the same way as synthetic ones.

For a trajectory first seen at ``p0`` in frame ``k0``, its position in a later frame k is compared with
``p0 + d(k0 -> k)``, the true motion of the skin point at ``p0`` (:class:`TruthField.between`). The error grows with
the span when tracking drifts; a wrong match shows as a jump of about a ridge period.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from skinstretch.drivers.session_file import SessionTruth
from skinstretch.experiments.analysis.density import FractionKept, fraction_kept
from skinstretch.experiments.evaluation.features import BORDER_MM, contact_edge_distance
from skinstretch.experiments.evaluation.tracking import TruthField
from skinstretch.experiments.results_file import Results

FEATURE_TRUTH_ATTR = "feature_truth"


def feature_truth_known(truth: SessionTruth) -> tuple[bool, str]:
    """Whether the session's true features are known (a synthetic print), and if not, why (a real print)."""
    note = str(truth.attrs.get(FEATURE_TRUTH_ATTR, "exact"))
    if note.startswith("unknown"):
        texture = truth.attrs.get("texture", "a real print")
        return False, (f"the skin texture is {texture}, a real print whose features are not known; displacement, "
                       "trajectories and strain are scored against the exact truth field")
    return True, ""


class TruthMotion:
    """The simulator's exact motion as a :class:`skinstretch.experiments.analysis.density.SkinPointMotion`: skin
    points move by the truth field, and are in view where feature recall is scored (in contact, at least
    ``border_mm`` from the image edge and the true contact edge: :mod:`skinstretch.experiments.evaluation.features`).
    """

    def __init__(self, truth: SessionTruth, *, image_shape: tuple[int, int], px_per_mm: float,
                 border_mm: float = BORDER_MM, field: TruthField | None = None) -> None:
        self.truth = truth
        self.field = field if field is not None else TruthField(truth)
        self.image_shape = tuple(int(v) for v in image_shape)
        self.border_px = float(border_mm) * float(px_per_mm)

    def move(self, points, frame_from, frame_to):
        d, ok = self.field.between(points, int(frame_from), int(frame_to))
        return points + np.nan_to_num(d), ok

    def in_view(self, points, frame):
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        h, w = self.image_shape
        x, y = pts[:, 0], pts[:, 1]
        ok = np.all(np.isfinite(pts), axis=1)
        ok &= np.minimum(np.minimum(x, w - 1 - x), np.minimum(y, h - 1 - y)) >= self.border_px
        if ok.any():
            dist, inside = contact_edge_distance(self.truth, int(frame), x[ok], y[ok], image_shape=self.image_shape)
            ok[ok] = inside & (dist >= self.border_px)
        return ok


def truth_fraction_kept(r: Results, truth: SessionTruth, *, field: TruthField | None = None) -> FractionKept | None:
    """:func:`skinstretch.experiments.analysis.density.fraction_kept` of the results' features, their skin points
    followed through the exact field (None without features and trajectories, e.g. the flow method)."""
    if r.features is None or r.trajectories is None or r.coordinates != "image":
        return None
    feats = r.features
    frame = np.asarray(feats["frame"], dtype=np.int64)
    offsets = np.searchsorted(frame, np.arange(r.n_frames + 1), side="left")
    kept = np.zeros(feats.shape[0], bool)
    fi = np.asarray(r.trajectories.rows["feature_index"], dtype=np.int64)
    kept[fi[(fi >= 0) & (fi < kept.size)]] = True
    xy = np.column_stack([feats["x"], feats["y"]]).astype(np.float64)
    window = int(r.params.get("tracking", {}).get("min_length_frames") or r.n_frames)
    motion = TruthMotion(truth, image_shape=r.image_shape, px_per_mm=r.px_per_mm, field=field)
    return fraction_kept(r.n_frames, window, lambda k: (xy[offsets[k]:offsets[k + 1]], kept[offsets[k]:offsets[k + 1]]),
                         motion)


def evaluate_trajectories(r: Results, truth: SessionTruth) -> dict[str, Any] | None:
    """The ``"trajectories"`` part of ``skinstretch evaluate`` (None without trajectories, e.g. the flow method).

    ``drift_rmse_px`` / ``drift_median_px`` / ``drift_p95_px``: error of every tracked position (after the first)
    against the true motion from the trajectory's start; ``drift_rmse_px_at_end``: the same at each trajectory's
    last frame only; ``jumped_fraction``: trajectories that are more than 1 px off at some frame (a wrong link
    to a neighbouring landmark); ``points_per_frame``: tracked points in a frame (mean); ``features_per_frame``:
    features extracted per frame (mean); ``n_trajectories``, ``median_frames``; ``fraction_kept``: of the features
    whose skin point stays in view for the minimum trajectory length (``window_frames``), the fraction in a kept
    trajectory (:func:`truth_fraction_kept`: the analysis' own definition, its skin points followed through the
    exact field), ``features_in_view``: how many stay in view.
    """
    tr = r.trajectories
    if tr is None or r.coordinates != "image":
        return None
    tf = TruthField(truth)
    rows = tr.rows[np.isfinite(tr.rows["x"]) & np.isfinite(tr.rows["y"])]
    n_tracks = int(tr.n_tracks)
    track = rows["track"].astype(np.int64)
    frame = rows["frame"].astype(np.int64)
    first = np.full(n_tracks, np.iinfo(np.int64).max)
    last = np.full(n_tracks, -1)
    np.minimum.at(first, track, frame)
    np.maximum.at(last, track, frame)
    start = frame == first[track]
    x0 = np.full(n_tracks, np.nan)
    y0 = np.full(n_tracks, np.nan)
    x0[track[start]], y0[track[start]] = rows["x"][start], rows["y"][start]
    later = ~start & (frame < tf.n_frames)
    k0, k, tk = first[track[later]], frame[later], track[later]
    meas = np.column_stack([rows["x"][later], rows["y"][later]])
    err = np.full(k.size, np.nan)
    key = k0 * (tf.n_frames + 1) + k
    for g in np.unique(key):  # one truth lookup per (start frame, frame)
        sel = np.nonzero(key == g)[0]
        p0 = np.column_stack([x0[tk[sel]], y0[tk[sel]]])
        d, ok = tf.between(p0, int(k0[sel[0]]), int(k[sel[0]]))
        e = np.hypot(*(meas[sel] - p0 - d).T)
        err[sel] = np.where(ok, e, np.nan)
    scored = np.isfinite(err)
    e = err[scored]
    end = err[scored & (k == last[tk])]
    jumped = np.zeros(n_tracks, bool)
    jumped[tk[scored & (err > 1.0)]] = True
    lengths = tr.lengths
    long_enough = lengths >= 2
    per_frame = math.nan
    if r.features is not None and len(r.features):
        per_frame = float(np.bincount(np.asarray(r.features["frame"], dtype=np.int64), minlength=r.n_frames).mean())
    fk = truth_fraction_kept(r, truth, field=tf)
    return {
        "fraction_kept": fk.fraction if fk is not None else math.nan,
        "features_in_view": fk.n_in_view if fk is not None else 0,
        "window_frames": fk.window_frames if fk is not None else 0,
        "n_trajectories": n_tracks,
        "median_frames": float(np.median(lengths)) if n_tracks else math.nan,
        "points_per_frame": float(np.bincount(frame, minlength=r.n_frames).mean()) if r.n_frames else math.nan,
        "features_per_frame": per_frame,
        "drift_rmse_px": float(np.sqrt(np.mean(e**2))) if e.size else math.nan,
        "drift_median_px": float(np.median(e)) if e.size else math.nan,
        "drift_p95_px": float(np.percentile(e, 95)) if e.size else math.nan,
        "drift_rmse_px_at_end": float(np.sqrt(np.mean(end**2))) if end.size else math.nan,
        "n_positions_scored": int(e.size),
        "jumped_fraction": float(jumped[long_enough].mean()) if long_enough.any() else math.nan,
    }

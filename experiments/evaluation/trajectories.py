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


def evaluate_trajectories(r: Results, truth: SessionTruth) -> dict[str, Any] | None:
    """The ``"trajectories"`` part of ``skinstretch evaluate`` (None without trajectories, e.g. the flow method).

    ``drift_rmse_px`` / ``drift_median_px`` / ``drift_p95_px``: error of every tracked position (after the first)
    against the true motion from the trajectory's start; ``drift_rmse_px_at_end``: the same at each trajectory's
    last frame only; ``jumped_fraction``: trajectories that are more than 1 px off at some frame (a wrong link
    to a neighbouring landmark);
    ``points_per_frame``: tracked points in a frame (mean); ``features_per_frame``: features extracted per frame
    (mean); ``n_trajectories``, ``median_frames``.
    """
    if r.trajectories is None or r.coordinates != "image":
        return None
    tf = TruthField(truth)
    x = np.asarray(r.trajectories["x"], dtype=np.float64)
    y = np.asarray(r.trajectories["y"], dtype=np.float64)
    present = np.asarray(r.trajectories["present"], dtype=bool) & np.isfinite(x) & np.isfinite(y)
    n_frames, n_traj = present.shape
    lengths = present.sum(axis=0)
    first = np.argmax(present, axis=0)
    errors, at_end, jumped = [], [], np.zeros(n_traj, bool)
    last = n_frames - 1 - np.argmax(present[::-1], axis=0)
    for k0 in np.unique(first[lengths >= 2]):
        cols = np.nonzero((first == k0) & (lengths >= 2))[0]
        p0 = np.column_stack([x[k0, cols], y[k0, cols]])
        for k in range(k0 + 1, min(n_frames, tf.n_frames)):
            here = present[k, cols]
            if not here.any():
                continue
            d, ok = tf.between(p0[here], int(k0), int(k))
            meas = np.column_stack([x[k, cols[here]], y[k, cols[here]]])
            err = np.hypot(*(meas - p0[here] - d).T)[ok]
            jumped[cols[here][ok][err > 1.0]] = True
            errors.append(err)
            at_end.append(err[(last[cols[here]] == k)[ok]])
    err = np.concatenate(errors) if errors else np.zeros(0)
    end = np.concatenate(at_end) if at_end else np.zeros(0)
    per_frame = math.nan
    if r.features is not None and len(r.features):
        per_frame = float(np.bincount(np.asarray(r.features["frame"], dtype=np.int64), minlength=r.n_frames).mean())
    return {
        "n_trajectories": int(n_traj),
        "median_frames": float(np.median(lengths)) if n_traj else math.nan,
        "points_per_frame": float(present.sum(axis=1).mean()) if n_frames else math.nan,
        "features_per_frame": per_frame,
        "drift_rmse_px": float(np.sqrt(np.mean(err**2))) if err.size else math.nan,
        "drift_median_px": float(np.median(err)) if err.size else math.nan,
        "drift_p95_px": float(np.percentile(err, 95)) if err.size else math.nan,
        "drift_rmse_px_at_end": float(np.sqrt(np.mean(end**2))) if end.size else math.nan,
        "n_positions_scored": int(err.size),
        "jumped_fraction": float(jumped[lengths >= 2].mean()) if np.any(lengths >= 2) else math.nan,
    }

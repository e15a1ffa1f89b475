"""Feature extraction against a simulated session's ground truth: recall, precision, localisation, repeatability.

Matching rules (documented here because every number depends on them)
--------------------------------------------------------------------
- Per frame, detections are matched **one-to-one** to truth features with the Hungarian algorithm on the
  Euclidean distance, gated at ``match_radius_px`` (default: 0.1 mm in pixels, i.e. ~6 px at 62 px/mm, about a
  quarter of the ridge period, so a detection cannot be credited to the neighbouring ridge's feature).
- Per kind (``valley_ending``, ``valley_bifurcation``, ``pore``) only features of that kind are matched; for
  ``minutiae`` endings and bifurcations are pooled and matched regardless of which of the two kinds was reported
  (a ridge ending seen as a valley bifurcation is still the right landmark for tracking).
- Only truth features **visible** in that frame (``truth.feature_visible``: in view and in contact) and outside
  the exclusion mask of that frame count. The exclusion mask is the extractor's fingerprint-border deletion mask
  when given (seed 4.8.6: features there are deleted on purpose), else an image-edge margin.
- Truth features that are out of contact (background) or under the mask are "don't care": a detection within
  the radius of one of them is neither a true nor a false positive. Every other unmatched detection is a false
  positive (precision), every unmatched eligible truth feature a miss (recall).
- ``loc_rmse_px``: RMS distance of matched pairs. ``repeatability_px``: RMS over consecutive frames of the change
  of a truth feature's localisation error, ``|e_{k+1} - e_k|`` with ``e = detected - true``, i.e. the
  frame-to-frame jitter of a matched feature relative to its true motion (a constant offset does not count).
- ``loc_bias_px``: RMS over matched pairs of their truth feature's *mean* error vector (over the frames it was
  matched in), i.e. the constant offset of a landmark from the truth point (a valley ending's grey-level tip lies
  ~3 px beyond the phase singularity the simulator calls the minutia). ``loc_rmse_debiased_px``: RMS of the error
  minus that mean. ``loc_rmse_px**2 == loc_bias_px**2 + loc_rmse_debiased_px**2``; ``loc_rmse_px`` stays the raw,
  uncorrected figure.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
from scipy.optimize import linear_sum_assignment

from skinstretch.drivers.session_file import SessionTruth
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind, validate_features

__all__ = ["evaluate_features", "GROUPS"]

#: Groups reported, with the feature kinds they pool.
GROUPS: dict[str, tuple[int, ...]] = {
    "valley_ending": (int(FeatureKind.VALLEY_ENDING),),
    "valley_bifurcation": (int(FeatureKind.VALLEY_BIFURCATION),),
    "pore": (int(FeatureKind.PORE),),
    "minutiae": (int(FeatureKind.VALLEY_ENDING), int(FeatureKind.VALLEY_BIFURCATION)),
}


def _match(tx, ty, dx, dy, radius):
    """One-to-one matches (truth index, detection index) within ``radius`` minimising the total distance."""
    if tx.size == 0 or dx.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    d = np.hypot(tx[:, None] - dx[None, :], ty[:, None] - dy[None, :])
    cost = np.where(d <= radius, d, 1e6)
    ri, ci = linear_sum_assignment(cost)
    ok = cost[ri, ci] <= radius
    return ri[ok], ci[ok], d[ri[ok], ci[ok]]


def evaluate_features(
    features: np.ndarray,
    truth: SessionTruth,
    *,
    match_radius_px: float | None = None,
    px_per_mm: float | None = None,
    exclusion_masks: Mapping[int, np.ndarray] | None = None,
    image_shape: tuple[int, int] | None = None,
    edge_margin_px: float = 10.0,
    frames: list[int] | None = None,
) -> dict:
    """Score a feature table against the truth of a simulated session.

    Parameters
    ----------
    features : FEATURE_DTYPE array
        Detections of any number of frames (the ``frame`` column says which).
    truth : SessionTruth
        The simulated session's truth.
    match_radius_px : float, optional
        Gate of the one-to-one matching. Default 0.1 mm converted with ``px_per_mm`` (which is then required).
    px_per_mm : float, optional
        Pixel scale, for the default radius.
    exclusion_masks : mapping frame -> (H, W) bool, optional
        Per-frame "don't care" masks (the extractor's border deletion mask). Without them, truth closer than
        ``edge_margin_px`` to the image edge (``image_shape`` required) is excluded.
    image_shape : (H, W), optional
    edge_margin_px : float
    frames : list of int, optional
        Frames to score (default: every frame that appears in the truth up to the last frame in ``features``).

    Returns
    -------
    dict
        ``{"match_radius_px", "n_frames", group: {"n_truth", "n_detected", "n_matched", "recall", "precision",
        "loc_rmse_px", "loc_bias_px", "loc_rmse_debiased_px", "repeatability_px"}}`` for each of :data:`GROUPS`. Ratios are ``None`` when undefined
        (nothing to count), never NaN.
    """
    validate_features(features)
    if match_radius_px is None:
        if px_per_mm is None:
            raise InvalidInputError("give match_radius_px, or px_per_mm for the default 0.1 mm radius")
        match_radius_px = 0.1 * float(px_per_mm)
    if not match_radius_px > 0:
        raise InvalidInputError(f"match_radius_px must be positive, got {match_radius_px!r}")
    n_frames = truth.feature_x.shape[0]
    if frames is None:
        last = int(features["frame"].max()) if features.size else n_frames - 1
        frames = list(range(min(last + 1, n_frames)))
    bad = [k for k in frames if not 0 <= k < n_frames]
    if bad:
        raise InvalidInputError(f"frames {bad[:5]} are outside the truth's {n_frames} frames")
    if exclusion_masks is None and image_shape is None:
        raise InvalidInputError("give exclusion_masks or image_shape (for the edge margin)")
    by_frame = {k: features[features["frame"] == k] for k in frames}
    out: dict = {"match_radius_px": float(match_radius_px), "n_frames": len(frames)}
    for group, kinds in GROUPS.items():
        n_truth = n_det = n_match = 0
        sq = []
        err_by_truth: dict[int, list] = {}
        err_prev: dict[int, np.ndarray] = {}
        jitter = []
        tkind = np.isin(truth.feature_kind, kinds)
        for k in frames:
            tx, ty = truth.feature_x[k], truth.feature_y[k]
            vis = truth.feature_visible[k] & tkind
            if exclusion_masks is not None:
                mask = exclusion_masks[k]
                h, w = mask.shape
                xi = np.clip(np.rint(tx).astype(np.int64), 0, w - 1)
                yi = np.clip(np.rint(ty).astype(np.int64), 0, h - 1)
                inside = (tx >= 0) & (tx <= w - 1) & (ty >= 0) & (ty <= h - 1)
                eligible = vis & inside & ~mask[yi, xi]
            else:
                h, w = image_shape
                m = edge_margin_px
                eligible = vis & (tx >= m) & (tx <= w - 1 - m) & (ty >= m) & (ty <= h - 1 - m)
            dont_care = tkind & ~eligible & np.isfinite(tx) & np.isfinite(ty)
            det = by_frame[k]
            det = det[np.isin(det["kind"], kinds)]
            te = np.flatnonzero(eligible)
            ri, ci, dist = _match(tx[te], ty[te], det["x"], det["y"], match_radius_px)
            unmatched = np.setdiff1d(np.arange(det.size), ci)
            # Unmatched detections next to a don't-care truth feature are ignored, not counted as false.
            tdc = np.flatnonzero(dont_care)
            ignored = 0
            if unmatched.size and tdc.size:
                d = np.hypot(
                    det["x"][unmatched][:, None] - tx[tdc][None, :], det["y"][unmatched][:, None] - ty[tdc][None, :]
                )
                ignored = int(np.count_nonzero(d.min(axis=1) <= match_radius_px))
            n_truth += te.size
            n_det += det.size - ignored
            n_match += ri.size
            sq.extend((dist**2).tolist())
            errs = {}
            for t_i, d_i in zip(te[ri].tolist(), ci.tolist()):
                e = np.array([det["x"][d_i] - tx[t_i], det["y"][d_i] - ty[t_i]])
                errs[t_i] = e
                err_by_truth.setdefault(t_i, []).append(e)
                if t_i in err_prev:
                    jitter.append(float(np.sum((e - err_prev[t_i]) ** 2)))
            err_prev = errs
        bias_sq, resid_sq = [], []
        for es in err_by_truth.values():
            es = np.asarray(es)
            mean = es.mean(axis=0)
            bias_sq.extend([float(mean @ mean)] * len(es))
            resid_sq.extend(np.sum((es - mean) ** 2, axis=1).tolist())
        out[group] = {
            "n_truth": n_truth,
            "n_detected": n_det,
            "n_matched": n_match,
            "recall": n_match / n_truth if n_truth else None,
            "precision": n_match / n_det if n_det else None,
            "loc_rmse_px": float(np.sqrt(np.mean(sq))) if sq else None,
            "loc_bias_px": float(np.sqrt(np.mean(bias_sq))) if bias_sq else None,
            "loc_rmse_debiased_px": float(np.sqrt(np.mean(resid_sq))) if resid_sq else None,
            "repeatability_px": float(np.sqrt(np.mean(jitter))) if jitter else None,
            "n_jitter_pairs": len(jitter),
        }
    return out

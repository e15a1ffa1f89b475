"""Feature extraction against a simulated session's ground truth: recall, precision, localisation, repeatability.

Every feature score of the project comes from here: ``skinstretch evaluate`` (:func:`evaluate_features`, its JSON
form) and the ``features`` and ``accuracy`` bench sections (:func:`score_features`, typed).

Matching rules (documented here because every number depends on them)
--------------------------------------------------------------------
- Per frame, detections are matched **one-to-one** to truth features with the Hungarian algorithm on the
  Euclidean distance, gated at ``match_radius_px`` (default: 0.1 mm in pixels, i.e. ~6 px at 62 px/mm, about a
  quarter of the ridge period, so a detection cannot be credited to the neighbouring ridge's feature).
- Per kind (``valley_ending``, ``valley_bifurcation``, ``pore``) only features of that kind are matched; for
  ``minutiae`` endings and bifurcations are pooled and matched regardless of which of the two kinds was reported
  (a ridge ending seen as a valley bifurcation is still the right landmark for tracking).
- **Eligible** truth features (the ones recall counts) are those visible in that frame (``truth.feature_visible``:
  in view and in contact, contact >= 0.5 in the simulator) and at least ``border_mm`` (default 0.3 mm) from the
  image edge and from the true contact edge. The band exists because seed 4.8.6 deletes, on purpose, every feature
  within 0.2 mm of the background it detects (itself dilated by 0.1 mm, :class:`ExtractionParams`): that is
  0.3 mm, about one ridge, along the fingertip's outline and the image edge, where a ridge fades out and false
  endings appear. The band is taken from the *truth* (where the true contact crosses 0.5), never from the
  extractor's own background mask, so an extractor cannot excuse a miss by calling the skin background.
- The true contact edge is found from the truth's own samples of contact in that frame: the displacement grid
  points (``displacement_valid``: in view and in contact) and the truth features (``feature_visible``), both at
  their frame-k positions. A point's distance to the edge is its distance to the nearest sample of the other
  status (in or out of contact), so it is good to about half the grid spacing (4 px).
- Truth features that are not eligible are "don't care": a detection within the radius of one of them is neither
  a true nor a false positive; so is a detection in the border band. Every other unmatched detection is a false
  positive (precision): in particular **any feature found where the skin is out of contact** (beyond the band).
  Every unmatched eligible truth feature is a miss (recall). ``n_out_of_contact`` counts the detections (all kinds)
  where the skin is out of contact at any distance from the edge, the band included (a point takes the status of
  the nearest contact sample of the truth; within half the grid spacing of the edge it may take the wrong one).
- ``loc_rmse_px``: RMS distance of matched pairs. ``repeatability_px``: RMS over consecutive frames of the change
  of a truth feature's localisation error, ``|e_{k+1} - e_k|`` with ``e = detected - true``, i.e. the
  frame-to-frame jitter of a matched feature relative to its true motion (a constant offset does not count).
- ``loc_bias_px``: RMS over matched pairs of their truth feature's *mean* error vector (over the frames it was
  matched in), i.e. the constant offset of a landmark from the truth point. ``loc_rmse_debiased_px``: RMS of the
  error minus that mean. ``loc_rmse_px**2 == loc_bias_px**2 + loc_rmse_debiased_px**2``; ``loc_rmse_px`` stays
  the raw, uncorrected figure.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from skinstretch.drivers.session_file import SessionTruth
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind, validate_features

__all__ = ["evaluate_features", "score_features", "contact_edge_distance", "FeatureScores", "KindScore", "GROUPS",
           "BORDER_MM"]

#: Groups reported, with the feature kinds they pool.
GROUPS: dict[str, tuple[int, ...]] = {
    "valley_ending": (int(FeatureKind.VALLEY_ENDING),),
    "valley_bifurcation": (int(FeatureKind.VALLEY_BIFURCATION),),
    "pore": (int(FeatureKind.PORE),),
    "minutiae": (int(FeatureKind.VALLEY_ENDING), int(FeatureKind.VALLEY_BIFURCATION)),
}

#: Width of the "don't care" band along the image edge and the true contact edge (seed 4.8.6: 0.2 mm of border
#: deletion beyond a background dilated by 0.1 mm).
BORDER_MM = 0.3


@dataclass(frozen=True)
class KindScore:
    """Scores of one group of feature kinds over the frames scored. Ratios are None when undefined, never NaN."""

    n_truth: int
    n_detected: int
    n_matched: int
    recall: float | None
    precision: float | None
    loc_rmse_px: float | None
    loc_bias_px: float | None
    loc_rmse_debiased_px: float | None
    repeatability_px: float | None
    n_jitter_pairs: int


@dataclass(frozen=True)
class FeatureScores:
    """What :func:`score_features` returns: the rules' parameters and one :class:`KindScore` per group of
    :data:`GROUPS` (``kinds["valley_ending"]``, ...)."""

    match_radius_px: float
    border_px: float
    n_frames: int
    kinds: dict[str, KindScore]
    #: Detections (all kinds) where the truth says the skin is out of contact, band included (module doc).
    n_out_of_contact: int = 0

    def to_dict(self) -> dict:
        """``{"match_radius_px", "border_px", "n_frames", "n_out_of_contact", group: {...KindScore fields}}`` (the
        JSON form)."""
        out: dict = {"match_radius_px": self.match_radius_px, "border_px": self.border_px, "n_frames": self.n_frames,
                     "n_out_of_contact": self.n_out_of_contact}
        out.update({name: asdict(score) for name, score in self.kinds.items()})
        return out


def _match(tx, ty, dx, dy, radius):
    """One-to-one matches (truth index, detection index) within ``radius`` minimising the total distance."""
    if tx.size == 0 or dx.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    d = np.hypot(tx[:, None] - dx[None, :], ty[:, None] - dy[None, :])
    cost = np.where(d <= radius, d, 1e6)
    ri, ci = linear_sum_assignment(cost)
    ok = cost[ri, ci] <= radius
    return ri[ok], ci[ok], d[ri[ok], ci[ok]]


def _contact_samples(truth: SessionTruth, k: int, image_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Frame-k positions (S, 2) of the truth's contact samples inside the image, and whether each is in contact."""
    h, w = image_shape
    gx = truth.grid_x[None, :] + truth.displacement[k, ..., 0]
    gy = truth.grid_y[:, None] + truth.displacement[k, ..., 1]
    xs = np.concatenate([gx.ravel(), truth.feature_x[k]])
    ys = np.concatenate([gy.ravel(), truth.feature_y[k]])
    contact = np.concatenate([truth.displacement_valid[k].ravel(), truth.feature_visible[k]])
    inside = np.isfinite(xs) & np.isfinite(ys) & (xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1)
    return np.column_stack([xs[inside], ys[inside]]), contact[inside]


def contact_edge_distance(
    truth: SessionTruth, k: int, x: np.ndarray, y: np.ndarray, *, image_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Distance (px) of points of frame ``k`` to the true contact edge, and whether each point is in contact.

    The edge is where the truth's contact samples (displacement grid points and truth features at their frame-k
    positions, see the module doc) change status: a point takes the status of its nearest sample and its distance
    to the edge is the distance to the nearest sample of the other status (``inf`` when the frame has only one).
    """
    pts = np.column_stack([np.asarray(x, float), np.asarray(y, float)])
    dist = np.full(pts.shape[0], np.inf)
    inside = np.zeros(pts.shape[0], bool)
    if pts.shape[0] == 0:
        return dist, inside
    samples, contact = _contact_samples(truth, k, image_shape)
    near = {}
    for status in (True, False):
        s = samples[contact == status]
        near[status] = cKDTree(s).query(pts)[0] if s.shape[0] else np.full(pts.shape[0], np.inf)
    inside = near[True] <= near[False]
    dist = np.where(inside, near[False], near[True])
    return dist, inside


def _edge_distance(x, y, image_shape):
    h, w = image_shape
    return np.minimum(np.minimum(x, w - 1 - x), np.minimum(y, h - 1 - y))


def score_features(
    features: np.ndarray,
    truth: SessionTruth,
    *,
    image_shape: tuple[int, int],
    px_per_mm: float | None = None,
    match_radius_px: float | None = None,
    border_mm: float = BORDER_MM,
    frames: list[int] | None = None,
) -> FeatureScores:
    """Score a feature table against the truth of a simulated session (rules in the module doc).

    Parameters
    ----------
    features : FEATURE_DTYPE array
        Detections of any number of frames (the ``frame`` column says which).
    truth : SessionTruth
        The simulated session's truth.
    image_shape : (H, W)
        Size of the frames (the image edge of the border band).
    px_per_mm : float, optional
        Pixel scale: converts ``border_mm`` and the default 0.1 mm radius. Required unless ``match_radius_px`` is
        given and ``border_mm`` is 0.
    match_radius_px : float, optional
        Gate of the one-to-one matching (default 0.1 mm).
    border_mm : float
        Width of the "don't care" band along the image edge and the true contact edge (0 = none).
    frames : list of int, optional
        Frames to score (default: every frame of the truth up to the last frame in ``features``).

    Returns
    -------
    FeatureScores
    """
    validate_features(features)
    if not (np.isfinite(border_mm) and border_mm >= 0):
        raise InvalidInputError(f"border_mm must be a non-negative number, got {border_mm!r}")
    if px_per_mm is None and (match_radius_px is None or border_mm > 0):
        raise InvalidInputError("give px_per_mm (for the 0.1 mm radius and the border band), or match_radius_px "
                                "with border_mm=0")
    if px_per_mm is not None and not (np.isfinite(px_per_mm) and px_per_mm > 0):
        raise InvalidInputError(f"px_per_mm must be positive, got {px_per_mm!r}")
    if match_radius_px is None:
        match_radius_px = 0.1 * float(px_per_mm)
    if not match_radius_px > 0:
        raise InvalidInputError(f"match_radius_px must be positive, got {match_radius_px!r}")
    if len(image_shape) != 2 or min(image_shape) < 1:
        raise InvalidInputError(f"image_shape must be (H, W), got {image_shape!r}")
    border_px = float(border_mm) * float(px_per_mm) if border_mm > 0 else 0.0
    n_frames = truth.feature_x.shape[0]
    if frames is None:
        last = int(features["frame"].max()) if features.size else n_frames - 1
        frames = list(range(min(last + 1, n_frames)))
    bad = [k for k in frames if not 0 <= k < n_frames]
    if bad:
        raise InvalidInputError(f"frames {bad[:5]} are outside the truth's {n_frames} frames")
    # Per frame: which truth features are eligible, which detections fall in the border band.
    per_frame = {}
    n_out = 0
    for k in frames:
        tx, ty = truth.feature_x[k], truth.feature_y[k]
        finite = np.isfinite(tx) & np.isfinite(ty)
        det = features[features["frame"] == k]
        t_ok = np.zeros(tx.size, bool)
        d_band = np.zeros(det.size, bool)
        vis = truth.feature_visible[k] & finite
        if border_px > 0:
            t_edge, _ = contact_edge_distance(truth, k, tx[vis], ty[vis], image_shape=image_shape)
            t_ok[vis] = (t_edge >= border_px) & (_edge_distance(tx[vis], ty[vis], image_shape) >= border_px)
            if det.size:
                d_edge, in_contact = contact_edge_distance(truth, k, det["x"], det["y"], image_shape=image_shape)
                d_band = (d_edge < border_px) | (_edge_distance(det["x"], det["y"], image_shape) < border_px)
                n_out += int(np.count_nonzero(~in_contact))
        else:
            h, w = image_shape
            t_ok = vis & (tx >= 0) & (tx <= w - 1) & (ty >= 0) & (ty <= h - 1)
            if det.size:
                n_out += int(np.count_nonzero(~contact_edge_distance(truth, k, det["x"], det["y"],
                                                                     image_shape=image_shape)[1]))
        per_frame[k] = (det, t_ok, d_band, finite)
    kinds = {group: _score_group(kinds, truth, per_frame, frames, match_radius_px) for group, kinds in GROUPS.items()}
    return FeatureScores(match_radius_px=float(match_radius_px), border_px=border_px, n_frames=len(frames), kinds=kinds,
                         n_out_of_contact=n_out)


def _score_group(kinds, truth, per_frame, frames, radius) -> KindScore:
    n_truth = n_det = n_match = 0
    sq = []
    err_by_truth: dict[int, list] = {}
    err_prev: dict[int, np.ndarray] = {}
    jitter = []
    tkind = np.isin(truth.feature_kind, kinds)
    for k in frames:
        det, t_ok, d_band, finite = per_frame[k]
        tx, ty = truth.feature_x[k], truth.feature_y[k]
        eligible = t_ok & tkind
        dont_care = tkind & ~eligible & finite
        of_kind = np.isin(det["kind"], kinds)
        det, band = det[of_kind], d_band[of_kind]
        te = np.flatnonzero(eligible)
        ri, ci, dist = _match(tx[te], ty[te], det["x"], det["y"], radius)
        unmatched = np.setdiff1d(np.arange(det.size), ci)
        # Unmatched detections in the border band or next to a don't-care truth feature are ignored, not false.
        ignored = band[unmatched]
        tdc = np.flatnonzero(dont_care)
        if unmatched.size and tdc.size:
            d = np.hypot(det["x"][unmatched][:, None] - tx[tdc][None, :], det["y"][unmatched][:, None] - ty[tdc][None, :])
            ignored = ignored | (d.min(axis=1) <= radius)
        n_truth += te.size
        n_det += det.size - int(np.count_nonzero(ignored))
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
    rms = lambda v: float(np.sqrt(np.mean(v))) if v else None  # noqa: E731
    return KindScore(
        n_truth=n_truth,
        n_detected=n_det,
        n_matched=n_match,
        recall=n_match / n_truth if n_truth else None,
        precision=n_match / n_det if n_det else None,
        loc_rmse_px=rms(sq),
        loc_bias_px=rms(bias_sq),
        loc_rmse_debiased_px=rms(resid_sq),
        repeatability_px=rms(jitter),
        n_jitter_pairs=len(jitter),
    )


def evaluate_features(features: np.ndarray, truth: SessionTruth, **options) -> dict:
    """:func:`score_features` (same arguments) as a JSON-ready dictionary (``FeatureScores.to_dict()``): what
    ``skinstretch evaluate`` prints."""
    return score_features(features, truth, **options).to_dict()

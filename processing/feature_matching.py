"""Matching features between consecutive frames (seed 5.1.1) and keeping one track per skin point.

* :func:`match_features` / :func:`match_columns`: each feature of frame k-1 is looked for near its expected
  position in frame k; candidates of the same kind inside a circular search window are rated by eq. 5.1,
  ``C = (180 - theta) / 180 + (d_max - d) / d_max``, and finalised in decreasing confidence, each feature used once.
* With sub-pixel registration (:class:`skinstretch.processing.tracking.FeatureTracker`), points followed by
  registration alone meet the features again: :func:`merge_bridged` lets a free feature continue the point it
  sits on, :func:`duplicate_starts` keeps a second detection of a tracked point from starting a track, and
  :func:`crowded_points` drops one of two tracks that came to follow one skin point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import validate_features
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.jit import njit

__all__ = ["Matches", "FeatureColumns", "feature_columns", "match_features", "match_columns",
           "duplicate_starts", "merge_bridged", "crowded_points"]


@dataclass(frozen=True)
class Matches:
    """Matched pairs between two feature tables: row indices into each, and the eq. 5.1 confidence."""

    prev_index: np.ndarray  # (m,) int64
    curr_index: np.ndarray  # (m,) int64
    confidence: np.ndarray  # (m,) float64

    def __len__(self) -> int:
        return int(self.prev_index.size)



def match_features(
    prev: np.ndarray,
    curr: np.ndarray,
    *,
    calibration: Calibration,
    predicted_displacement: np.ndarray | None = None,
    search_radius_mm: float = 0.3,
) -> Matches:
    """Match the features of two consecutive frames (seed 5.1.1).

    Parameters
    ----------
    prev, curr : FEATURE_DTYPE arrays
        Features of frame k-1 and frame k.
    calibration : Calibration
        Converts the search radius to pixels.
    predicted_displacement : array of shape (2,) or (len(prev), 2), optional
        Expected displacement (dx, dy) px of every feature of ``prev`` (default: none).
    search_radius_mm : float
        Radius of the circular search window around each expected position.

    Returns :class:`Matches`: one-to-one pairs, finalised in decreasing eq. 5.1 confidence.

    Examples
    --------
    >>> from skinstretch.processing.feature_table import make_features
    >>> a = make_features([10.0, 50.0], [10.0, 10.0], [2, 2])
    >>> b = make_features([52.0, 12.0], [10.0, 11.0], [2, 2])
    >>> m = match_features(a, b, calibration=Calibration(px_per_mm=62.0))
    >>> m.prev_index.tolist(), m.curr_index.tolist()
    ([0, 1], [1, 0])
    """
    validate_features(prev)
    validate_features(curr)
    if not (np.isfinite(search_radius_mm) and search_radius_mm > 0):
        raise InvalidInputError(f"search_radius_mm must be positive, got {search_radius_mm!r}")
    radius = calibration.px(search_radius_mm)
    pred = _broadcast_prediction(predicted_displacement, prev.shape[0])
    return match_columns(feature_columns(prev), feature_columns(curr), pred, radius)


def _broadcast_prediction(pred, n: int) -> np.ndarray:
    if pred is None:
        return np.zeros((n, 2))
    pred = np.asarray(pred, dtype=np.float64)
    if pred.shape == (2,):
        return np.tile(pred, (n, 1))
    if pred.shape != (n, 2):
        raise InvalidInputError(f"predicted_displacement must have shape (2,) or ({n}, 2), got {pred.shape}")
    if not np.all(np.isfinite(pred)):
        raise InvalidInputError("predicted_displacement holds non-finite values")
    return pred


@dataclass(frozen=True)
class FeatureColumns:
    xy: np.ndarray
    kind: np.ndarray
    orientation: np.ndarray
    known: np.ndarray


def feature_columns(table: np.ndarray) -> FeatureColumns:
    return FeatureColumns(
        np.column_stack([table["x"], table["y"]]).astype(np.float64),
        table["kind"].astype(np.int8),
        table["orientation"].astype(np.float64),
        table["orientation_known"].astype(bool),
    )


def match_columns(prev: FeatureColumns, curr: FeatureColumns, pred: np.ndarray, radius: float) -> Matches:
    if prev.xy.shape[0] == 0 or curr.xy.shape[0] == 0:
        return Matches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    expected = np.ascontiguousarray(prev.xy + pred, dtype=np.float64)
    order = np.argsort(curr.xy[:, 0], kind="stable")
    i, j, conf = _match_kernel(
        expected,
        prev.kind,
        prev.orientation,
        prev.known,
        np.ascontiguousarray(curr.xy[order], dtype=np.float64),
        order.astype(np.int64),
        curr.kind,
        curr.orientation,
        curr.known,
        float(radius),
    )
    return Matches(i, j, conf)


@njit(nogil=True)
def _match_kernel(expected, pkind, porient, pknown, cxy_sorted, corder, ckind, corient, cknown, radius):
    """Candidates (same kind, distance <= radius from the expected position; ``cxy_sorted`` is the current
    frame's positions sorted by x, ``corder`` their rows), rated by eq. 5.1, then finalised greedily in decreasing
    confidence (ties: shorter distance first), each feature used once. Returns the pairs sorted by prev row."""
    n = expected.shape[0]
    m = cxy_sorted.shape[0]
    r2 = radius * radius
    cap = 16
    ci = np.empty(cap, np.int64)
    cj = np.empty(cap, np.int64)
    cd = np.empty(cap, np.float64)
    cc = np.empty(cap, np.float64)
    k = 0
    for a in range(n):
        ex = expected[a, 0]
        ey = expected[a, 1]
        lo = np.searchsorted(cxy_sorted[:, 0], ex - radius, side="left")
        for t in range(lo, m):
            dx = cxy_sorted[t, 0] - ex
            if dx > radius:
                break
            dy = cxy_sorted[t, 1] - ey
            d2 = dx * dx + dy * dy
            if d2 > r2:
                continue
            b = corder[t]
            if pkind[a] != ckind[b]:
                continue
            d = np.sqrt(d2)
            # Eq. 5.1; the orientation term is null for pores and minutiae of unknown orientation.
            orient = 0.0
            if pknown[a] and cknown[b]:
                dtheta = abs((porient[a] - corient[b] + 180.0) % 360.0 - 180.0)
                orient = (180.0 - dtheta) / 180.0
            if k == cap:
                cap *= 2
                ci2 = np.empty(cap, np.int64)
                cj2 = np.empty(cap, np.int64)
                cd2 = np.empty(cap, np.float64)
                cc2 = np.empty(cap, np.float64)
                ci2[:k] = ci
                cj2[:k] = cj
                cd2[:k] = cd
                cc2[:k] = cc
                ci, cj, cd, cc = ci2, cj2, cd2, cc2
            ci[k] = a
            cj[k] = b
            cd[k] = d
            cc[k] = orient + (radius - d) / radius
            k += 1
    ci, cj, cd, cc = ci[:k], cj[:k], cd[:k], cc[:k]
    by_d = np.argsort(cd, kind="mergesort")
    order = by_d[np.argsort(-cc[by_d], kind="mergesort")]
    used_p = np.zeros(n, np.bool_)
    used_c = np.zeros(ckind.shape[0], np.bool_)
    owner = np.full(n, -1, np.int64)
    for t in order:
        a = ci[t]
        b = cj[t]
        if used_p[a] or used_c[b]:
            continue
        used_p[a] = True
        used_c[b] = True
        owner[a] = t
    count = 0
    for a in range(n):
        if owner[a] >= 0:
            count += 1
    pi = np.empty(count, np.int64)
    pj = np.empty(count, np.int64)
    pc = np.empty(count, np.float64)
    q = 0
    for a in range(n):
        t = owner[a]
        if t >= 0:
            pi[q] = a
            pj[q] = cj[t]
            pc[q] = cc[t]
            q += 1
    return pi, pj, pc


def duplicate_starts(xy: np.ndarray, tracks: np.ndarray, bridged_xy: np.ndarray, *, radius: float) -> np.ndarray:
    """Features (``xy``, their ``tracks``: -1 for none yet) that would start a track within ``radius`` of a tracked
    point of this frame (another feature's or a bridged one, ``bridged_xy``) or of an earlier such feature: one skin
    point detected twice (two kinds at one place), which must not start a second track (an edge a fraction of a
    pixel long)."""
    start = tracks < 0
    if not start.any() or xy.shape[0] + bridged_xy.shape[0] < 2:
        return np.zeros(xy.shape[0], bool)
    everything = np.concatenate([xy, bridged_xy])
    pairs = cKDTree(everything).query_pairs(radius, output_type="ndarray")
    starts = np.concatenate([start, np.zeros(bridged_xy.shape[0], bool)])
    out = np.zeros(everything.shape[0], bool)
    if pairs.size:
        a, b = pairs[:, 0], pairs[:, 1]  # a < b
        out[a[starts[a] & ~starts[b]]] = True  # next to a tracked point
        out[b[starts[b] & ~starts[a]]] = True
        both = starts[a] & starts[b]
        for i, j in sorted(zip(a[both].tolist(), b[both].tolist())):
            if not out[i]:  # two new features: the later one, unless the earlier is a duplicate itself
                out[j] = True
    return out[: xy.shape[0]]


def merge_bridged(prev_xy, prev_tracks, bridged, bridged_disp, xy, tracks, disp, refined, done, *, radius: float):
    """A point of the previous frame (rows ``bridged`` of ``prev_xy``, tracks ``prev_tracks``) followed by
    registration to within ``radius`` of a feature of this frame (``xy``) that started no track of its own is that
    feature (whatever its kind: a valley ending and a bifurcation trade places as a ridge gap opens or closes): the
    feature continues the bridged track, with the displacement the registration measured. Fills ``tracks``,
    ``disp``, ``refined`` and ``done`` (previous points finished with) in place; returns the bridged points left
    and their displacements."""
    q = prev_xy[bridged] + bridged_disp
    dist, j = cKDTree(xy).query(q, distance_upper_bound=radius)
    hit = np.flatnonzero(np.isfinite(dist))
    merged = np.zeros(bridged.size, bool)
    for b in hit[np.argsort(dist[hit], kind="stable")]:  # the nearest first
        f = j[b]
        if tracks[f] < 0:
            tracks[f] = prev_tracks[bridged[b]]
            disp[f] = bridged_disp[b]
            refined[f] = True
            merged[b] = True
    done[bridged[merged]] = True  # neither bridged further nor waiting to be re-linked
    return bridged[~merged], bridged_disp[~merged]


def crowded_points(xy: np.ndarray, tracks: np.ndarray, bridged_xy: np.ndarray, bridged_tracks: np.ndarray, *,
                   radius: float):
    """Tracked points of this frame (features ``xy`` with ``tracks`` >= 0, and the bridged points) closer than
    ``radius`` to another are one skin point followed twice (a skin point detected as two kinds, each matched to a
    track of its kind; a bridged point drifting onto a feature): one of each pair is dropped, a bridged point before
    a feature, then the younger track. Returns (features to untrack, bridged points to drop), boolean masks."""
    on = np.flatnonzero(tracks >= 0)
    drop_f = np.zeros(xy.shape[0], bool)
    drop_b = np.zeros(bridged_xy.shape[0], bool)
    pts = np.concatenate([xy[on], bridged_xy])
    if pts.shape[0] < 2:
        return drop_f, drop_b
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    if not pairs.size:
        return drop_f, drop_b
    m = on.size
    ids = np.concatenate([tracks[on], bridged_tracks])
    rank = np.stack([np.arange(pts.shape[0]) >= m, ids], axis=1)  # (bridged, track id): larger is dropped
    dist = np.hypot(*(pts[pairs[:, 0]] - pts[pairs[:, 1]]).T)
    gone = np.zeros(pts.shape[0], bool)
    for a, b in pairs[np.argsort(dist, kind="stable")]:
        if gone[a] or gone[b]:
            continue
        gone[b if tuple(rank[b]) > tuple(rank[a]) else a] = True
    drop_f[on[gone[:m]]] = True
    drop_b[gone[m:]] = True
    return drop_f, drop_b

"""Evaluate analysis results against a simulated session's ground truth (displacement, matches, strain, profile).

Every comparison uses the truth *displacement field* (Lagrangian, on the frame-0 grid) interpolated at the
measured points, so the feature method and the dense methods are judged the same way:

* displacement: for each measured point p in frame a, the true displacement of the skin point at p to frame b;
* edge/area strain: the same edges and triangles, moved by the true field;
* profile: the seed Figure 94 profile computed by the same code from the true field on its grid, compared by
  correlation (not on a flat surface, where the truth has no pattern: there the amplitude is what counts);
* wrong matches (features only): a matched pair whose extracted features lie nearest to different truth features.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial import cKDTree

from skinstretch.drivers.session_file import SessionTruth
from skinstretch.experiments.results_file import PairStatus, Results
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.measurement_uncertainty import RADIUS_95_1D, RADIUS_95_2D
from skinstretch.processing.tracking import MotionSample


class TruthField:
    """Look up the true displacement between any two frames at image points of the first frame."""

    def __init__(self, truth: SessionTruth) -> None:
        self.truth = truth
        self.gx = np.asarray(truth.grid_x, dtype=np.float64)
        self.gy = np.asarray(truth.grid_y, dtype=np.float64)
        self.disp = np.asarray(truth.displacement, dtype=np.float64)
        self.valid = np.asarray(truth.displacement_valid, dtype=bool)
        self.n_frames = self.disp.shape[0]

    def _interp(self, values: np.ndarray, pts: np.ndarray) -> np.ndarray:
        f = RegularGridInterpolator((self.gy, self.gx), values, bounds_error=False, fill_value=np.nan)
        return f(np.column_stack([pts[:, 1], pts[:, 0]]))

    def between(self, points: np.ndarray, frame_a: int, frame_b: int) -> tuple[np.ndarray, np.ndarray]:
        """True displacement (n, 2) from frame a to frame b of the skin points at ``points`` in frame a, and
        whether it is known (skin point in view and in contact in both frames, inside the truth grid)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if not (0 <= frame_a < self.n_frames and 0 <= frame_b < self.n_frames):
            raise InvalidInputError(f"frames ({frame_a}, {frame_b}) out of range for {self.n_frames} truth frames")
        da, db = self.disp[frame_a], self.disp[frame_b]
        # Frame-0 grid point X seen at p in frame a: p = X + da(X); fixed-point inversion (|grad u| << 1).
        X = pts.copy()
        for _ in range(5):
            u = np.column_stack([self._interp(da[..., 0], X), self._interp(da[..., 1], X)])
            X = pts - np.nan_to_num(u)
        ua = np.column_stack([self._interp(da[..., 0], X), self._interp(da[..., 1], X)])
        ub = np.column_stack([self._interp(db[..., 0], X), self._interp(db[..., 1], X)])
        both = (self.valid[frame_a] & self.valid[frame_b]).astype(np.float64)
        ok_grid = self._interp(both, X) > 0.999
        d = ub - ua
        ok = ok_grid & np.all(np.isfinite(d), axis=1)
        d[~ok] = np.nan
        return d, ok

    def grid_motion(self, frame_a: int, frame_b: int, *, stride: int = 1) -> MotionSample:
        """True motion of the grid's skin points (every ``stride``-th) from frame a to b, at frame-a positions."""
        X, Y = np.meshgrid(self.gx[::stride], self.gy[::stride])
        da = self.disp[frame_a, ::stride, ::stride]
        db = self.disp[frame_b, ::stride, ::stride]
        ok = self.valid[frame_a, ::stride, ::stride] & self.valid[frame_b, ::stride, ::stride]
        pa = np.stack([X + da[..., 0], Y + da[..., 1]], axis=-1)[ok]
        return MotionSample(frame_a, frame_b, pa, (db - da)[ok], np.nonzero(ok.ravel())[0])


def _rms(a: np.ndarray) -> float:
    a = np.asarray(a, dtype=np.float64)
    return float(np.sqrt(np.mean(a**2))) if a.size else math.nan


def displacement_errors(r: Results, tf: TruthField, *, with_sigma: bool = False):
    """Per measured point of every consecutive pair: |measured - true| px (points with known truth only); with
    ``with_sigma`` also each point's reported standard error (NaN where the results have none)."""
    return _motion_errors(r.motion_pairs, r.motion, tf, with_sigma=with_sigma)


def cumulative_errors(r: Results, tf: TruthField, *, with_sigma: bool = False):
    """As :func:`displacement_errors`, for the motion from the reference frame (``cumulative``; none in results
    written before it)."""
    c = r.cumulative
    if c is None:
        return (np.zeros(0), np.zeros(0)) if with_sigma else np.zeros(0)
    return _motion_errors(c.pairs, c.motion, tf, with_sigma=with_sigma)


def _motion_errors(pairs: np.ndarray, motion: np.ndarray, tf: TruthField, *, with_sigma: bool):
    errs, sigmas = [], []
    motion = motion[np.argsort(motion["pair"], kind="stable")]
    bounds = np.searchsorted(motion["pair"], np.arange(len(pairs) + 1))
    for i, pair in enumerate(pairs):
        rows = motion[bounds[i] : bounds[i + 1]]
        if rows.size == 0:
            continue
        pts = np.column_stack([rows["x"], rows["y"]])
        d, ok = tf.between(pts, int(pair["frame_a"]), int(pair["frame_b"]))
        meas = np.column_stack([rows["dx"], rows["dy"]])
        errs.append(np.hypot(*(meas[ok] - d[ok]).T))
        sigmas.append(rows["sigma"][ok] if "sigma" in (rows.dtype.names or ()) else np.full(int(ok.sum()), np.nan))
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)  # noqa: E731
    return (cat(errs), cat(sigmas)) if with_sigma else cat(errs)


def edge_strain_errors(r: Results, tf: TruthField, span: int, *, with_sigma: bool = False):
    """(edge-length change errors, triangle-area change errors) of one span (fractions); with ``with_sigma`` also
    the edges' reported standard errors (NaN where the results have none)."""
    if span not in r.strain:
        return (np.zeros(0),) * (3 if with_sigma else 2)
    s = r.strain[span]
    e_err, a_err, e_sigma = [], [], []
    for i, pair in enumerate(s.pairs):
        if pair["status"] != PairStatus.OK:
            continue
        fa, fb = int(pair["frame_a"]), int(pair["frame_b"])
        e = s.edges[s.edges["pair"] == i]
        if e.size:
            pa = np.column_stack([e["xa"], e["ya"]])
            pb = np.column_stack([e["xb"], e["yb"]])
            da, oka = tf.between(pa, fa, fb)
            db, okb = tf.between(pb, fa, fb)
            ok = oka & okb
            true_change = np.hypot(*((pb + db) - (pa + da)).T) / np.hypot(*(pb - pa).T) - 1.0
            e_err.append(e["change"][ok] - true_change[ok])
            e_sigma.append(e["change_sigma"][ok] if "change_sigma" in (e.dtype.names or ())
                           else np.full(int(ok.sum()), np.nan))
        t = s.triangles[(s.triangles["pair"] == i) & ~s.triangles["flipped"]]
        if t.size:
            p = [np.column_stack([t[f"x{j}"], t[f"y{j}"]]) for j in range(3)]
            dd = [tf.between(pj, fa, fb) for pj in p]
            ok = dd[0][1] & dd[1][1] & dd[2][1]
            q = [p[j] + dd[j][0] for j in range(3)]

            def area(v):
                return 0.5 * np.abs(
                    (v[1][:, 0] - v[0][:, 0]) * (v[2][:, 1] - v[0][:, 1])
                    - (v[2][:, 0] - v[0][:, 0]) * (v[1][:, 1] - v[0][:, 1])
                )

            true_change = area(q) / area(p) - 1.0
            a_err.append(t["change"][ok] - true_change[ok])
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)  # noqa: E731
    return (cat(e_err), cat(a_err), cat(e_sigma)) if with_sigma else (cat(e_err), cat(a_err))


def coverage_95(errors: np.ndarray, sigma: np.ndarray, radius: float) -> float:
    """The fraction of ``errors`` (absolute, or vector lengths) within ``radius`` times their reported standard
    error: the 95 % interval's coverage (an honest uncertainty gives >= 0.95); a point without one counts as
    outside. NaN when there are no errors."""
    errors, sigma = np.abs(np.asarray(errors, np.float64)), np.asarray(sigma, np.float64)
    return float(np.mean(errors <= radius * np.where(np.isnan(sigma), -1.0, sigma))) if errors.size else math.nan


def wrong_match_rate(r: Results, truth: SessionTruth, *, assoc_px: float) -> tuple[float, int]:
    """Fraction of consecutive matches whose two extracted features are nearest to different truth features
    (both within ``assoc_px`` of one); also returns how many matches could be judged."""
    if r.trajectories is None or r.coordinates != "image":
        return math.nan, 0
    rows = r.trajectories.rows
    fx, fy, vis = truth.feature_x, truth.feature_y, truth.feature_visible
    truth_id = np.full(rows.size, -1, np.int64)  # nearest visible truth feature of each row, within assoc_px
    off = r.trajectories.frame_offsets
    for k in range(min(r.n_frames, fx.shape[0])):
        lo, hi = int(off[k]), int(off[k + 1])
        v = np.nonzero(vis[k])[0]
        if hi == lo or v.size == 0:
            continue
        raw = np.column_stack([rows["raw_x"][lo:hi], rows["raw_y"][lo:hi]])
        found = np.all(np.isfinite(raw), axis=1)  # a point bridged by registration has no extracted feature
        dist, j = cKDTree(np.column_stack([fx[k, v], fy[k, v]])).query(np.where(found[:, None], raw, 0.0))
        truth_id[lo:hi] = np.where(found & (dist <= assoc_px), v[j], -1)
    # A linked row follows the same track's row of the previous frame: judge the pair of truth ids.
    order = np.lexsort((rows["frame"], rows["track"]))
    tr, fr, tid, linked = rows["track"][order], rows["frame"][order], truth_id[order], rows["linked"][order]
    follows = (tr[1:] == tr[:-1]) & (fr[1:] == fr[:-1] + 1) & linked[1:]
    judged = follows & (tid[1:] >= 0) & (tid[:-1] >= 0)
    wrong = judged & (tid[1:] != tid[:-1])
    n = int(judged.sum())
    return (float(wrong.sum()) / n if n else math.nan), n


def true_profile(r: Results, tf: TruthField, *, strip_px: float):
    """The seed Figure 94 profile computed by the analysis code from the true motion of the truth grid's skin points
    (every consecutive pair, the results' axis and positions)."""
    from skinstretch.experiments.analysis.derive import stretch_profile

    samples, ft = [], []
    for k in range(r.n_frames - 1):
        s = tf.grid_motion(k, k + 1, stride=2)
        samples.append(s)
        ft.append(s.displacement.mean(axis=0) if len(s) else np.zeros(2))
    return stretch_profile(
        samples, np.asarray(ft), axis=r.profile_axis_index, positions=r.profile.x, strip_px=strip_px
    )


def profile_correlation(r: Results, tf: TruthField, *, strip_px: float) -> tuple[float, np.ndarray]:
    """Pearson correlation of the measured profile with the same profile computed from the true field, over the
    positions valid in both (NaN when fewer than 3 or one of them is constant), and the true profile."""
    true = true_profile(r, tf, strip_px=strip_px)
    ok = true.valid & r.profile_valid
    if ok.sum() < 3 or np.std(true.change[ok]) == 0 or np.std(r.profile_change[ok]) == 0:
        return math.nan, true.change
    return float(np.corrcoef(true.change[ok], r.profile_change[ok])[0, 1]), true.change


def _sliding_direction(r: Results) -> float:
    travel = np.nansum(np.asarray(r.fingertip.displacement, dtype=np.float64)[:, r.profile_axis_index])
    return 1.0 if travel >= 0 else -1.0


def profile_strip_px(r: Results) -> float:
    """The width (px) of the analysis' profile strips: the margin :func:`profile_pattern` leaves at each end."""
    return float(r.params["strain"]["profile_strip_mm"]) * r.px_per_mm


def measured_profile_pattern(r: Results, *, strip_px: float | None = None):
    """The pattern (amplitude, lobes) of the analysis' own stretch profile, None when too few positions are valid:
    the one computation behind ``skinstretch evaluate``'s ``profile.amplitude`` and the RMS the report's stretch
    profile figure shows (a number shown twice must be the same number)."""
    from skinstretch.processing.errors import InsufficientDataError  # noqa: PLC0415
    from skinstretch.processing.stretch import StretchProfile, profile_pattern  # noqa: PLC0415

    margin = profile_strip_px(r) if strip_px is None else strip_px
    try:
        return profile_pattern(StretchProfile(r.profile_position, r.profile_change, r.profile_valid),
                               direction=_sliding_direction(r), margin=margin)
    except InsufficientDataError:
        return None


def evaluate_profile(r: Results, tf: TruthField, *, strip_px: float) -> dict[str, Any]:
    """The ``"profile"`` part of ``skinstretch evaluate``: correlation with the truth and the pattern (seed 6.3.2).

    ``amplitude``/``true_amplitude`` are the RMS of the measured/true profile (fractions per frame pair; one strip
    width from the ends of the valid positions left out, see :func:`skinstretch.processing.stretch.profile_pattern`) and
    ``compression_first``/``true_compression_first`` whether its compression lobe comes before its expansion lobe
    in the sliding direction (the seed: True for a ridge, False for a valley). On a flat surface the true profile
    has no pattern, so ``correlation`` is not computed (null) and a ``note`` says to compare the amplitude with a
    ridge or valley session instead.
    """
    from skinstretch.processing.errors import InsufficientDataError
    from skinstretch.processing.stretch import profile_pattern

    surface = str(tf.truth.attrs.get("surface", "unknown"))
    true = true_profile(r, tf, strip_px=strip_px)
    ok = true.valid & r.profile_valid
    out: dict[str, Any] = {"axis": r.profile_axis, "surface": surface}
    corr = math.nan
    if ok.sum() >= 3 and np.std(true.change[ok]) > 0 and np.std(r.profile_change[ok]) > 0:
        corr = float(np.corrcoef(true.change[ok], r.profile_change[ok])[0, 1])
    direction = _sliding_direction(r)
    try:
        true_pattern = profile_pattern(true, direction=direction, margin=strip_px)
    except InsufficientDataError:
        true_pattern = None
    for prefix, pat in (("", measured_profile_pattern(r, strip_px=strip_px)), ("true_", true_pattern)):
        if pat is None:
            out[f"{prefix}amplitude"], out[f"{prefix}compression_first"] = math.nan, None
            continue
        out[f"{prefix}amplitude"] = pat.amplitude
        out[f"{prefix}compression_first"] = pat.compression_first if surface != "flat" else None
    if surface == "flat":
        out["correlation"] = math.nan
        out["note"] = (
            "flat surface: the true profile has no ridge/valley pattern, so no correlation is computed; "
            "compare 'amplitude' with that of a ridge or valley session (seed 6.3.2, Figure 94)"
        )
    else:
        out["correlation"] = corr
    out["n_positions"] = int(ok.sum())
    return out


def evaluate_tracking(r: Results, truth: SessionTruth) -> dict[str, Any]:
    """The "tracking", "strain", "profile" and "timing" parts of ``skinstretch evaluate``'s JSON."""
    tf = TruthField(truth)
    if tf.n_frames < r.n_frames:
        raise InvalidInputError(f"truth has {tf.n_frames} frames, results {r.n_frames}")
    derr, dsigma = displacement_errors(r, tf, with_sigma=True)
    assoc = 0.1 * r.px_per_mm  # 0.1 mm: well under the spacing of features of one kind
    wrong, judged = wrong_match_rate(r, truth, assoc_px=assoc)
    med_len = math.nan
    if r.tracks is not None and r.tracks.size:
        med_len = float(np.median(r.tracks["n_frames"]))
    out: dict[str, Any] = {
        "tracking": {
            "displacement_rmse_px": _rms(derr),
            "displacement_median_px": float(np.median(derr)) if derr.size else math.nan,
            "displacement_p95_px": float(np.percentile(derr, 95)) if derr.size else math.nan,
            "n_displacements": int(derr.size),
            "wrong_match_rate": wrong,
            "n_matches_judged": judged,
            "median_trajectory_frames": med_len,
        },
        "strain": {},
        "uncertainty": {"displacement_coverage_95": coverage_95(derr, dsigma, RADIUS_95_2D),
                        "displacement_sigma_median_px": float(np.median(dsigma[np.isfinite(dsigma)])) if np.isfinite(dsigma).any()
                        else math.nan},
    }
    cerr, csigma = cumulative_errors(r, tf, with_sigma=True)
    out["tracking"]["cumulative_rmse_px"] = _rms(cerr)
    out["uncertainty"]["cumulative_coverage_95"] = coverage_95(cerr, csigma, RADIUS_95_2D)
    for span in sorted(r.strain):
        e_err, a_err, e_sigma = edge_strain_errors(r, tf, span, with_sigma=True)
        out["strain"][f"edge_rmse_{span}"] = _rms(e_err)
        out["strain"][f"area_rmse_{span}"] = _rms(a_err)
        out["strain"][f"n_edges_{span}"] = int(e_err.size)
        out["uncertainty"][f"edge_coverage_95_{span}"] = coverage_95(e_err, e_sigma, RADIUS_95_1D)
    for key in ("edge_rmse_1", "edge_rmse_11", "area_rmse_1"):
        out["strain"].setdefault(key, math.nan)
    out["profile"] = evaluate_profile(r, tf, strip_px=profile_strip_px(r))
    out["timing"] = {"frames_per_s": float(r.timing.get("frames_per_s", math.nan))}
    return out


@dataclass(frozen=True)
class DenseEvaluation:
    """Error of a dense flow (any method) on one frame pair against the truth field."""

    displacement_errors: np.ndarray
    edge_errors: np.ndarray


def evaluate_dense_pair(
    flow_sampler, tf: TruthField, frame_a: int, frame_b: int, *, edge_points: np.ndarray | None = None,
    stride: int = 2,
) -> DenseEvaluation:
    """Compare a dense flow, given as ``flow_sampler(points) -> (n, 2)`` displacements, with the truth.

    Displacement at the truth grid's skin points (every ``stride``-th) in frame a; edge strain on the Delaunay
    edges of ``edge_points`` (e.g. the true features visible in frame a) when given.
    """
    from scipy.spatial import Delaunay

    g = tf.grid_motion(frame_a, frame_b, stride=stride)
    meas = np.asarray(flow_sampler(g.points), dtype=np.float64)
    ok = np.all(np.isfinite(meas), axis=1)
    derr = np.hypot(*(meas[ok] - g.displacement[ok]).T)
    eerr = np.zeros(0)
    if edge_points is not None and len(edge_points) >= 3:
        p = np.asarray(edge_points, dtype=np.float64)
        dt, okt = tf.between(p, frame_a, frame_b)
        dm = np.asarray(flow_sampler(p), dtype=np.float64)
        okm = okt & np.all(np.isfinite(dm), axis=1)
        p, dt, dm = p[okm], dt[okm], dm[okm]
        if p.shape[0] >= 3:
            tri = Delaunay(p).simplices
            edges = np.unique(np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1), axis=0)
            la = np.hypot(*(p[edges[:, 0]] - p[edges[:, 1]]).T)
            lt = np.hypot(*((p + dt)[edges[:, 0]] - (p + dt)[edges[:, 1]]).T)
            lm = np.hypot(*((p + dm)[edges[:, 0]] - (p + dm)[edges[:, 1]]).T)
            eerr = (lm - lt) / la
    return DenseEvaluation(derr, eerr)

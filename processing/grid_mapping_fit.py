"""Fitting the imaging model to indexed grid dots: the pixel-to-skin mapping and its residuals (seed 3.4, 7.2.1).

:func:`fit_grid_mapping` fits :class:`~skinstretch.processing.imaging_model.ImagingModel` (a pinhole camera with
radial distortion looking at a flat, Gaussian or Gaussian-plus-spline ruled surface) by robust least squares
(:func:`scipy.optimize.least_squares`) to the dots that :mod:`skinstretch.processing.dot_grid_detection` found and
indexed. The grid is laid on the surface without stretching, so dot (i, j) is at unrolled position (i p, j p) in
the grid's frame. Several images of a moving grid can be fitted jointly (one grid placement per image), which
samples a ridge or valley more densely than the 0.5 mm pitch the seed found too sparse (7.2.1).

The result is a :class:`~skinstretch.processing.grid_mapping.GridMapping` and a :class:`CalibrationReport` of
residuals. A fit that cannot be trusted raises :class:`~skinstretch.processing.errors.CalibrationError` saying why.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from skinstretch.processing.argument_checks import positive_number
from skinstretch.processing.dot_grid_detection import INDEX_NONE
from skinstretch.processing.errors import CalibrationError, InvalidInputError
from skinstretch.processing.grid_mapping import SURFACE_KINDS, GridMapping, RigParameters, SurfaceFrame
from skinstretch.processing.imaging_model import ImagingModel, SplineBasis, rotation_2d

__all__ = ["MIN_ROWS_CURVED", "CalibrationReport", "fit_grid_mapping"]

#: A ridge or valley profile needs this many rows of dots (4.5 mm at 0.5 mm pitch) across it to be fitted.
MIN_ROWS_CURVED = 9

# ------------------------------------------------------------------------------------------------ fitting


@dataclass
class CalibrationReport:
    """Residuals of a calibration fit.

    Attributes
    ----------
    n_detected, n_indexed, n_used, n_outliers : int
        Dots found, given lattice indices, used in the final fit, and rejected as outliers (all images together).
    rms_px, max_px : float
        Residual (model - detected centre) over the dots used, px.
    rms_um : float
        The same RMS expressed on the surface, micrometres (via the local scale).
    image, ij, xy, residual_px, used : arrays
        Per dot: image number, lattice index, detected centre, residual vector and whether it was used.
    surface : str
        Surface model fitted ("flat", "ridge", "valley").
    """

    n_detected: int
    n_indexed: int
    n_used: int
    n_outliers: int
    rms_px: float
    max_px: float
    rms_um: float
    surface: str
    image: np.ndarray
    ij: np.ndarray
    xy: np.ndarray
    residual_px: np.ndarray
    used: np.ndarray

    def summary(self) -> dict[str, Any]:
        return {
            "n_detected": self.n_detected,
            "n_indexed": self.n_indexed,
            "n_used": self.n_used,
            "n_outliers": self.n_outliers,
            "rms_px": self.rms_px,
            "max_px": self.max_px,
            "rms_um": self.rms_um,
            "surface": self.surface,
        }


@dataclass
class _GridView:
    ij: np.ndarray  # (K, 2) int
    xy: np.ndarray  # (K, 2) float


_RIG_NAMES = ("r0", "r1", "r2", "t0", "t1", "t2", "focal", "k1", "k2")


def _unpack(p: np.ndarray, n_images: int, curved, principal: np.ndarray, spacing: float):
    """Rig and grid placements from the parameter vector; ``curved`` is False (flat), True (Gaussian profile) or a
    SplineBasis (Gaussian plus spline, whose coefficients close the vector)."""
    knots, coefs = (), ()
    if isinstance(curved, SplineBasis):
        knots, coefs = curved.knots, tuple(p[len(p) - curved.n :])
        p = p[: len(p) - curved.n]
    rig = dict(zip(_RIG_NAMES, p[:9]))
    k = 9
    amplitude = sigma = center = 0.0
    if curved:
        amplitude, log_sigma, center = p[k : k + 3]
        sigma = math.exp(log_sigma)
        k += 3
    poses = [(p[k], 0.0, 0.0)] if curved else [(0.0, 0.0, 0.0)]
    k += 1 if curved else 0
    for _ in range(1, n_images):
        poses.append(tuple(p[k : k + 3]))
        k += 3
    model = ImagingModel(
        rotvec=np.array([rig["r0"], rig["r1"], rig["r2"]]),
        trans=np.array([rig["t0"], rig["t1"], rig["t2"]]),
        focal_px=rig["focal"],
        k1=rig["k1"],
        k2=rig["k2"],
        principal=principal,
        amplitude=amplitude,
        sigma=sigma,
        center=center,
        knots=knots,
        coefs=coefs,
    )
    return model, poses


def _grid_to_surface(ij: np.ndarray, pose: tuple[float, float, float], spacing: float) -> np.ndarray:
    phi, tu, ts = pose
    return (ij * spacing) @ rotation_2d(phi).T + np.array([tu, ts])


def _select(views: list[_GridView], keep: np.ndarray) -> list[_GridView]:
    """The views restricted to the dots flagged in ``keep`` (one flag per dot, all views concatenated)."""
    out, start = [], 0
    for view in views:
        sel = keep[start : start + len(view.ij)]
        out.append(_GridView(ij=view.ij[sel], xy=view.xy[sel]))
        start += len(view.ij)
    return out


def _dot_image_offset(model: ImagingModel, pose, ij: np.ndarray, spacing: float, radius: float,
                      n: int = 48) -> np.ndarray:
    """Area centroid of each dot's image minus the image of its centre, px (K, 2).

    The dot is a disc on the unrolled surface; its image outline is projected through the rig and the centroid of
    that polygon taken (Green's theorem)."""
    centre = _grid_to_surface(ij.astype(np.float64), pose, spacing)
    t = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    ring = centre[:, None, :] + radius * np.stack([np.cos(t), np.sin(t)], axis=-1)[None]
    poly = model.project(ring)
    x, y = poly[..., 0], poly[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum(axis=1)
    cx = ((x + xn) * cross).sum(axis=1) / (6.0 * area)
    cy = ((y + yn) * cross).sum(axis=1) / (6.0 * area)
    return np.stack([cx, cy], axis=-1) - model.project(centre)


def _residuals(p, views, curved, principal, spacing):
    try:
        model, poses = _unpack(p, len(views), curved, principal, spacing)
    except (ValueError, OverflowError):
        return np.full(sum(2 * len(v.ij) for v in views), 1e6)
    out = []
    for view, pose in zip(views, poses):
        pred = model.project(_grid_to_surface(view.ij.astype(np.float64), pose, spacing))
        out.append((pred - view.xy).ravel())
    r = np.concatenate(out)
    return np.where(np.isfinite(r), r, 1e6)


#: Regularisation of a spline profile correction, px-equivalent per mm: its second differences (smoothness where
#: the 0.5 mm grid leaves gaps) and, weakly, its size (the Gaussian stays the prior shape).
SPLINE_SMOOTHNESS = 5.0
SPLINE_SIZE = 0.5
#: Median residual (px) of the Gaussian-profile fit above which the profile gets a spline correction (the noise
#: level of the dot centres is ~0.02 px).
SPLINE_TRIGGER_PX = 0.05


def _objective(p, views, curved, principal, spacing):
    r = _residuals(p, views, curved, principal, spacing)
    if isinstance(curved, SplineBasis):
        c = p[len(p) - curved.n :]
        r = np.concatenate([r, SPLINE_SMOOTHNESS * np.diff(c, 2), SPLINE_SIZE * c])
    return r


def _initial_rig(view: _GridView, principal: np.ndarray, spacing: float, working_distance_mm: float) -> np.ndarray:
    """Nominal 45-degree prism view, scaled from the lattice spacing near the grid origin."""
    ij, xy = view.ij, view.xy
    by = {tuple(k): x for k, x in zip(ij.tolist(), xy)}
    steps = [by[(i + 1, j)] - by[(i, j)] for (i, j) in by if (i + 1, j) in by and abs(i) + abs(j) < 6]
    a = np.median(np.array(steps), axis=0) if steps else np.array([1.0, 0.0])
    scale = float(np.linalg.norm(a)) / spacing  # px per mm along i
    focal = scale * working_distance_mm
    tilt = math.radians(45.0)
    roll = math.atan2(a[1], a[0])
    # Rows of R: camera x (along U), camera y, camera axis, with the 45-degree tilt about U, then the roll.
    ex, ey, d = np.array([1.0, 0, 0]), np.array([0, math.cos(tilt), -math.sin(tilt)]), np.array(
        [0, math.sin(tilt), math.cos(tilt)]
    )
    cr, sr = math.cos(roll), math.sin(roll)
    rotvec = Rotation.from_matrix(np.stack([cr * ex - sr * ey, sr * ex + cr * ey, d])).as_rotvec()
    p0 = by.get((0, 0), xy[0])
    # Put the grid origin on the ray of its observed pixel, at the working distance.
    ray = np.array([(p0[0] - principal[0]) / focal, (p0[1] - principal[1]) / focal, 1.0])
    trans = ray * working_distance_mm
    return np.concatenate([rotvec, trans, [focal, 0.0, 0.0]])


def _shape_guess(view: _GridView, spacing: float) -> tuple[str, float]:
    """Ridge, valley or flat from how the row spacing changes along j, and the shape's centre in grid mm."""
    by = {tuple(k): x for k, x in zip(view.ij.tolist(), view.xy)}
    rows: dict[int, list[float]] = {}
    for (i, j), x in by.items():
        nxt = by.get((i, j + 1))
        if nxt is not None:
            rows.setdefault(j, []).append(float(np.linalg.norm(nxt - x)))
    js = sorted(j for j in rows if len(rows[j]) >= 3)
    if len(js) < 3:
        return "flat", 0.0
    med = np.array([np.median(rows[j]) for j in js])
    rel = (med.max() - med.min()) / np.median(med)
    if rel < 0.1:
        return "flat", 0.0
    jmin, jmax = js[int(np.argmin(med))], js[int(np.argmax(med))]
    center = 0.5 * (jmin + jmax + 1) * spacing
    # Over a ridge, rows bunch up before the crest (surface rising towards the finger, away from the camera).
    return ("ridge" if jmin < jmax else "valley"), center


def _fit(views, *, curved, principal, spacing, p0, loss, f_scale, max_nfev=400):
    lb, ub = np.full(len(p0), -np.inf), np.full(len(p0), np.inf)
    lb[6] = 1.0  # focal length, px
    if curved:
        # Keep the profile physical while the fit wanders: |amplitude| <= 3 mm, 0.1 mm <= sigma <= 10 mm.
        lb[9:12] = (-3.0, math.log(0.1), -25.0)
        ub[9:12] = (3.0, math.log(10.0), 25.0)
    p0 = np.minimum(np.maximum(p0, np.where(np.isfinite(lb), lb + 1e-6, lb)), np.where(np.isfinite(ub), ub - 1e-6, ub))
    return least_squares(
        _objective, p0, args=(views, curved, principal, spacing), loss=loss, f_scale=f_scale, x_scale="jac",
        method="trf", bounds=(lb, ub), max_nfev=max_nfev if not isinstance(curved, SplineBasis) else min(max_nfev, 80),
        xtol=1e-10, ftol=1e-10, gtol=1e-10,
    )


def fit_grid_mapping(
    views: Sequence[tuple[np.ndarray, np.ndarray]],
    *,
    image_shape: tuple[int, int],
    surface: str = "auto",
    spacing_mm: float = 0.5,
    working_distance_mm: float = 150.0,
    shape_height_mm: float = 0.5,
    shape_width_mm: float = 3.0,
    max_rms_px: float = 0.5,
    min_dots: int = 40,
    outlier_px: float = 1.0,
    dot_diameter_mm: float | None = 0.2,
    spline_profile: bool = True,
    n_detected: int | None = None,
) -> tuple[GridMapping, CalibrationReport]:
    """Fit the rig model to indexed dots of one or more grid images (the grid may move between images).

    Parameters
    ----------
    views : sequence of (ij (K, 2) int, xy (K, 2) float)
        Lattice indices and detected centres (px) of each image's dots; unindexed dots must be left out.
    image_shape, surface : (H, W), {"auto", "flat", "ridge", "valley"}
        Image size; surface model ("auto" guesses it from the spacing of the rows and keeps the best fit).
    spacing_mm, working_distance_mm : float
        Dot pitch of the grid; nominal camera distance (starting point only).
    shape_height_mm, shape_width_mm : float
        Nominal size of a ridge or valley (starting point only; width = 4 sigma).
    max_rms_px, min_dots : float, int
        A fit whose RMS residual exceeds this, or fewer indexed dots (all images), raise CalibrationError.
    outlier_px : float
        Dots whose residual exceeds max(outlier_px, 5 x robust sigma) after the robust fit are dropped.
    dot_diameter_mm : float or None
        Dot diameter: the offset of a dot's image centroid from its centre's image is predicted and removed.
    spline_profile : bool
        A cubic-spline correction of the ridge or valley profile when the Gaussian leaves systematic residuals.
    n_detected : int, optional
        Number of dots detected (for the report only).

    Returns ``mapping`` (GridMapping) and ``report`` (CalibrationReport).
    """
    if surface not in ("auto",) + SURFACE_KINDS:
        raise InvalidInputError(f"surface must be 'auto' or one of {SURFACE_KINDS}, got {surface!r}")
    for name, value in (("spacing_mm", spacing_mm), ("working_distance_mm", working_distance_mm),
                        ("max_rms_px", max_rms_px), ("shape_width_mm", shape_width_mm),
                        ("outlier_px", outlier_px)):
        positive_number(value, name)
    if not views:
        raise InvalidInputError("views must hold at least one (ij, xy) pair")
    gviews = []
    for k, (ij, xy) in enumerate(views):
        ij = np.asarray(ij, dtype=np.int64)
        xy = np.asarray(xy, dtype=np.float64)
        if ij.shape != xy.shape or ij.ndim != 2 or ij.shape[1] != 2:
            raise InvalidInputError(f"view {k}: ij and xy must both be (K, 2), got {ij.shape} and {xy.shape}")
        if np.any(ij == INDEX_NONE):
            raise InvalidInputError(f"view {k}: leave unindexed dots out of the fit")
        gviews.append(_GridView(ij=ij, xy=xy))
    n_indexed = sum(len(v.ij) for v in gviews)
    if n_indexed < min_dots:
        raise CalibrationError(f"too few grid dots indexed: {n_indexed} (need at least {min_dots})")
    if len(gviews[0].ij) < max(10, min_dots // max(1, len(gviews))):
        raise CalibrationError(f"the first image has too few indexed dots ({len(gviews[0].ij)})")
    h, w = image_shape
    principal = np.array([(w - 1) / 2.0, (h - 1) / 2.0])

    guess_kind, guess_center = _shape_guess(gviews[0], spacing_mm)
    kinds = [surface] if surface != "auto" else (["flat"] if guess_kind == "flat" else [guess_kind, "flat"])
    rows = len(np.unique(np.concatenate([v.ij[:, 1] for v in gviews])))
    if surface in ("ridge", "valley") and rows < MIN_ROWS_CURVED:
        raise CalibrationError(
            f"the grid spans only {rows} rows of dots: too few to fit a {surface}'s profile (need "
            f"{MIN_ROWS_CURVED}); calibrate on a full frame and use GridMapping.for_window for smaller modes"
        )
    if rows < MIN_ROWS_CURVED:
        kinds = ["flat"]
    if rows < 3:
        raise CalibrationError(f"the grid spans only {rows} rows of dots (need at least 3)")
    rig0 = _initial_rig(gviews[0], principal, spacing_mm, working_distance_mm)

    best = None
    for kind in kinds:
        curved = kind != "flat"
        # Fit the first image alone, then add the other images' grid placements, initialised from it.
        starts = []
        if curved:
            amp = shape_height_mm if kind == "ridge" else -shape_height_mm
            sig = math.log(shape_width_mm / 4.0)
            for dc in (0.0, -0.75, 0.75):
                starts.append(np.concatenate([rig0, [amp, sig, guess_center + dc, 0.0]]))
        else:
            starts.append(rig0.copy())
        # Plain least squares first (the indexing is robust, and a robust loss far from the solution only slows
        # the descent), from each start for a few iterations; the best start is then fitted robustly.
        fit0 = None
        for p0 in starts:
            res = _fit(gviews[:1], curved=curved, principal=principal, spacing=spacing_mm, p0=p0,
                       loss="linear", f_scale=1.0, max_nfev=60)
            if fit0 is None or res.cost < fit0.cost:
                fit0 = res
            if np.sqrt(2 * fit0.cost / len(fit0.fun)) < 0.5:  # converged near the noise: no other start needed
                break
        fit0 = _fit(gviews[:1], curved=curved, principal=principal, spacing=spacing_mm, p0=fit0.x,
                    loss="soft_l1", f_scale=0.3)
        p = fit0.x
        if len(gviews) > 1:
            model, poses = _unpack(p, 1, curved, principal, spacing_mm)
            extra = []
            for view in gviews[1:]:
                us, ok = model.back_project(view.xy)
                # Grid placement of this image: rigid fit of its lattice onto its dots seen through image 0's model.
                g = view.ij * spacing_mm
                ok &= np.all(np.isfinite(us), axis=1)
                if ok.sum() < 3:
                    raise CalibrationError("a moving-grid image could not be placed on the surface")
                gc, uc = g[ok].mean(0), us[ok].mean(0)
                hmat = (g[ok] - gc).T @ (us[ok] - uc)
                phi = math.atan2(hmat[0, 1] - hmat[1, 0], hmat[0, 0] + hmat[1, 1])
                t = uc - rotation_2d(phi) @ gc
                extra.extend([phi, t[0], t[1]])
            p = np.concatenate([p, extra])
            p = _fit(gviews, curved=curved, principal=principal, spacing=spacing_mm, p0=p, loss="soft_l1",
                     f_scale=0.3).x
        if curved and spline_profile:
            r = _residuals(p, gviews, curved, principal, spacing_mm).reshape(-1, 2)
            if np.median(np.linalg.norm(r, axis=1)) > SPLINE_TRIGGER_PX:
                # The shape is not quite Gaussian (a machined surface never is): let a smooth spline correct the
                # profile, knots every 0.3 mm over the shape (seed 7.2.1's "model of the surface").
                model, _ = _unpack(p, len(gviews), curved, principal, spacing_mm)
                curved = SplineBasis.around(model.center, model.sigma)
                p = _fit(gviews, curved=curved, principal=principal, spacing=spacing_mm,
                         p0=np.concatenate([p, np.zeros(curved.n)]), loss="soft_l1", f_scale=0.3).x
        # Drop outliers (wrong indices, spurious dots), then a plain least-squares fit.
        r = _residuals(p, gviews, curved, principal, spacing_mm).reshape(-1, 2)
        rn = np.linalg.norm(r, axis=1)
        sigma = 1.4826 * np.median(rn) / 1.1774  # Rayleigh median -> per-axis sigma
        keep = rn <= max(outlier_px, 5.0 * sigma)
        kept_views = _select(gviews, keep)
        if sum(len(v.ij) for v in kept_views) < min_dots:
            continue
        res = _fit(kept_views, curved=curved, principal=principal, spacing=spacing_mm, p0=p, loss="linear",
                   f_scale=1.0)
        cost = float(np.sqrt(np.mean(res.fun**2)))
        if kind == "flat" and best is not None and cost <= 1.2 * best[0]:
            best = (cost, kind, res.x, keep, curved)  # a curved model that does not fit clearly better is dropped
        elif best is None or cost < best[0]:
            best = (cost, kind, res.x, keep, curved)
        if best[0] < 0.1 and (kind == "flat" or abs(res.x[9]) >= 0.05):
            # The guessed model fits to noise level with a real shape: no need to try a flat one.
            break
    if best is None:
        raise CalibrationError("grid not found: too many dots disagree with any rig model")
    _, kind, p, keep, curved = best
    detected_views = gviews
    if dot_diameter_mm is not None and not isinstance(curved, SplineBasis):
        # (Not with a spline profile: there the refit is stiff and the ~0.04 px offsets are below what the spline
        # already absorbs.)
        # The image of a round dot is not centred on the image of its centre (perspective, and the surface's
        # curvature across the dot: ~0.04 px on a ridge's slopes, ~1 um). Predict that offset with the fitted rig,
        # remove it from the detected centres and fit again (once: the offset hardly depends on the fit).
        model, poses = _unpack(p, len(gviews), curved, principal, spacing_mm)
        corrected = [
            _GridView(ij=v.ij, xy=v.xy - _dot_image_offset(model, pose, v.ij, spacing_mm, 0.5 * dot_diameter_mm))
            for v, pose in zip(detected_views, poses)
        ]
        before = np.sqrt(np.mean(_residuals(p, _select(detected_views, keep), curved, principal, spacing_mm) ** 2))
        refit = _fit(_select(corrected, keep), curved=curved, principal=principal, spacing=spacing_mm, p0=p,
                     loss="linear", f_scale=1.0)
        after = np.sqrt(np.mean(_residuals(refit.x, _select(corrected, keep), curved, principal, spacing_mm) ** 2))
        # The offsets are ~0.04 px: the refit must not end worse than the fit it refines (a stiff spline fit
        # cut short could); then the uncorrected fit stands.
        if np.isfinite(after) and after <= 1.05 * before:
            gviews, p = corrected, refit.x
    model, poses = _unpack(p, len(gviews), curved, principal, spacing_mm)

    # Residuals over every indexed dot (outliers included, flagged).
    r_all = _residuals(p, gviews, curved, principal, spacing_mm).reshape(-1, 2)
    used_r = r_all[keep]
    rms = float(np.sqrt(np.mean(np.sum(used_r**2, axis=1))))
    mx = float(np.max(np.linalg.norm(used_r, axis=1)))

    # Output frame: origin at the image centre's surface point; u along the rulings (curved) or along image x.
    centre_us, ok = model.back_project(principal[None, :])
    if not ok[0]:
        raise CalibrationError("the fitted camera does not see the surface at the image centre")
    if curved:
        angle = 0.0
    else:
        d, _ = model.back_project(np.array([principal + [1.0, 0.0]]))
        vec = d[0] - centre_us[0]
        angle = math.atan2(vec[1], vec[0])
    # With u along the rulings, make s grow with the image row.
    rot = rotation_2d(angle)
    down, _ = model.back_project(np.array([principal + [0.0, 1.0]]))
    if ((down[0] - centre_us[0]) @ rot)[1] < 0:
        raise CalibrationError("fitted surface frame is mirrored (s decreases down the image); grid misindexed")
    rig = RigParameters(
        rotvec=tuple(model.rotvec.tolist()),
        trans=tuple(model.trans.tolist()),
        focal_px=float(model.focal_px),
        k1=float(model.k1),
        k2=float(model.k2),
        principal=tuple(principal.tolist()),
        amplitude_mm=float(model.amplitude),
        sigma_mm=float(model.sigma) if curved else 1.0,
        center_mm=float(model.center),
        spline_knots=tuple(float(k) for k in model.knots),
        spline_coefs=tuple(float(c) for c in model.coefs),
    )
    frame = SurfaceFrame(angle_rad=angle, origin_mm=tuple(centre_us[0].tolist()))
    mapping = GridMapping(width=int(w), height=int(h), surface=kind, rig=rig, frame=frame)
    # Residuals on the surface: each used dot's residual vector mapped through the local scale of the fit.
    xy_fit = np.concatenate([v.xy for v in gviews])[keep]
    d_mm = mapping.image_to_surface(xy_fit + used_r) - mapping.image_to_surface(xy_fit)
    rms_um = float(np.sqrt(np.mean(np.sum(d_mm**2, axis=1))) * 1000.0)
    image_no = np.concatenate([np.full(len(v.ij), k) for k, v in enumerate(gviews)])
    report = CalibrationReport(
        n_detected=int(n_detected if n_detected is not None else n_indexed),
        n_indexed=int(n_indexed),
        n_used=int(keep.sum()),
        n_outliers=int((~keep).sum()),
        rms_px=rms,
        max_px=mx,
        rms_um=rms_um,
        surface=kind,
        image=image_no,
        ij=np.concatenate([v.ij for v in gviews]),
        xy=np.concatenate([v.xy for v in detected_views]),
        residual_px=r_all,
        used=keep,
    )
    mapping = dataclasses.replace(mapping, report=report.summary())
    if rms > max_rms_px:
        hint = (
            f"; {rows} rows of dots cannot resolve a ridge or valley: calibrate on a full frame and use "
            "GridMapping.for_window" if rows < MIN_ROWS_CURVED else ""
        )
        raise CalibrationError(
            f"calibration residuals too large: RMS {rms:.3f} px > {max_rms_px} px over {keep.sum()} dots "
            f"({kind} surface model){hint}"
        )
    return mapping, report


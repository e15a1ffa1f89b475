"""Geometric calibration from images of a dot grid pressed on the contact surface (seed 3.4, improved per 7.2.1).

The seed corrects the prism's perspective and "unrolls" curved contact surfaces with a grid of dots 0.5 mm apart
printed on transparency film and pressed on the surface. Measurements are then made in mm *on the skin* (arc
length along the surface), not on a flat projection. This module does that in three steps:

1. :func:`detect_dots`: dark dots on the bright surface, with sub-pixel centres (background-normalised darkness,
   connected components, darkness-weighted centroids).
2. :func:`index_grid`: integer lattice indices (i, j) for the dots, robust to missing and spurious dots: the grid is
   grown from a regular seed dot using *local* lattice vectors extrapolated from the neighbours already indexed, so
   it follows the strong spacing changes over a ridge or valley.
3. :func:`fit_grid_mapping`: a physical model of the rig fitted by robust least squares (scipy): a pinhole camera
   (pose, focal length, radial distortion k1, k2) looking at a parallel-ruled surface whose height profile is flat or
   Gaussian (ridge / valley: amplitude, width, position), with the grid laid on the surface without stretching, so
   dot (i, j) is at unrolled position (i p, j p) in the grid's frame. This is the seed's 7.2.1 proposal ("a model of
   the surface and of the image acquisition system ... in a minimization strategy"); several images of a moving grid
   can be fitted jointly (one grid placement per image), which samples a ridge or valley more densely than the
   0.5 mm pitch the seed found too sparse.

The result is a :class:`GridMapping` (``image_to_surface``, ``surface_to_image``, ``px_per_mm``, ``to_dict`` /
``from_dict``) and a :class:`CalibrationReport` of residuals. A fit that cannot be trusted raises
:class:`skinstretch.processing.errors.CalibrationError` saying why.

Coordinates
-----------
Image pixels ``(x, y)``: x the column, y the row, origin at the centre of the top-left pixel. Surface ``(u, s)`` in
mm, unrolled: ``s`` is the arc length across the rulings of a ridge or valley, ``u`` along them. A grid only fixes
the surface frame up to a rigid motion of the unrolled plane, so the mapping's frame is defined as: origin at the
surface point seen at the image centre; ``u`` along the rulings (curved surfaces) or along the image x axis at the
centre (flat surfaces); ``s`` increasing with the image row.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import cv2
import numpy as np
from scipy.interpolate import BSpline
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from skinstretch.processing.errors import CalibrationError, InvalidInputError

MAPPING_KIND = "skinstretch-grid-mapping"
MAPPING_VERSION = 1
SURFACE_KINDS = ("flat", "ridge", "valley")
#: A ridge or valley profile needs this many rows of dots (4.5 mm at 0.5 mm pitch) across it to be fitted.
MIN_ROWS_CURVED = 9
#: Index given by :func:`index_grid` to dots that are not on the lattice.
INDEX_NONE = np.iinfo(np.int64).min


# ------------------------------------------------------------------------------------------------ dot detection


@dataclass
class DotDetections:
    """Dots found in one image: sub-pixel centres ``xy`` (K, 2) px, ``area`` (K,) px^2, ``darkness`` (K,) in 0..1."""

    xy: np.ndarray
    area: np.ndarray
    darkness: np.ndarray

    def __len__(self) -> int:
        return int(self.xy.shape[0])


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2 or image.shape[0] < 16 or image.shape[1] < 16:
        raise InvalidInputError(f"image must be a 2-D greyscale array of at least 16x16, got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.number) or not np.all(np.isfinite(image)):
        raise InvalidInputError("image must be numeric and finite")
    return image.astype(np.float32)


def detect_dots(
    image: np.ndarray,
    *,
    px_per_mm: float,
    dot_diameter_mm: float = 0.2,
    threshold: float = 0.4,
    min_area_factor: float = 0.15,
    max_area_factor: float = 3.0,
) -> DotDetections:
    """Find the dark dots of a calibration grid and their sub-pixel centres.

    Parameters
    ----------
    image : (H, W) array
        Greyscale image, dots dark on a bright surface.
    px_per_mm : float
        Nominal scale along the image x axis (sets the expected dot size and the background window).
    dot_diameter_mm : float
        Dot diameter on the sheet.
    threshold : float
        Relative darkness ``1 - I / background`` above which a pixel belongs to a dot.
    min_area_factor, max_area_factor : float
        Components smaller or larger than these multiples of the expected (sqrt(2)-compressed) dot area are
        rejected (noise, merged dots, large specks).

    Returns
    -------
    DotDetections
        Components touching the image border are left out (their centroid would be biased).
    """
    img = _check_image(image)
    if not (math.isfinite(px_per_mm) and px_per_mm > 0):
        raise InvalidInputError(f"px_per_mm must be positive, got {px_per_mm!r}")
    if not (math.isfinite(dot_diameter_mm) and dot_diameter_mm > 0):
        raise InvalidInputError(f"dot_diameter_mm must be positive, got {dot_diameter_mm!r}")
    if not 0 < threshold < 1:
        raise InvalidInputError(f"threshold must be in (0, 1), got {threshold!r}")
    dot_px = dot_diameter_mm * px_per_mm
    # Bright background envelope: a grey closing wider than a dot removes the dots, keeping the illumination
    # (slopes of a ridge are darker, seed 6.3.2), so the darkness is relative to the local surface brightness.
    k = int(2 * math.ceil(1.5 * dot_px) + 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    background = cv2.morphologyEx(cv2.GaussianBlur(img, (0, 0), 0.8), cv2.MORPH_CLOSE, kernel)
    background = cv2.GaussianBlur(background, (0, 0), 0.25 * k)
    background = np.maximum(background, max(1.0, float(np.percentile(img, 99)) * 0.05))
    dark = np.clip(1.0 - img / background, 0.0, 1.0)
    mask = (dark > threshold).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    expected_area = math.pi / 4 * dot_px * dot_px * math.cos(math.radians(45.0))
    h, w = img.shape
    xs, areas, darks = [], [], []
    pad = 5
    for lab in range(1, n):
        x0, y0, bw, bh, area = stats[lab]
        if not (min_area_factor * expected_area <= area <= max_area_factor * expected_area):
            continue
        if x0 == 0 or y0 == 0 or x0 + bw >= w or y0 + bh >= h:
            continue
        xa, xb = max(x0 - pad, 0), min(x0 + bw + pad, w)
        ya, yb = max(y0 - pad, 0), min(y0 + bh + pad, h)
        lab_win = labels[ya:yb, xa:xb]
        comp = (lab_win == lab).astype(np.uint8)
        grown = cv2.dilate(comp, np.ones((5, 5), np.uint8)).astype(bool)
        others = cv2.dilate(((lab_win != lab) & (lab_win != 0)).astype(np.uint8), np.ones((5, 5), np.uint8))
        ring = cv2.dilate(comp, np.ones((9, 9), np.uint8)).astype(bool) & ~grown & ~others.astype(bool)
        gy, gx = np.mgrid[ya:yb, xa:xb]
        win = img[ya:yb, xa:xb]
        # Local background: a plane fitted to a ring around the dot. The slopes of a ridge or valley darken the
        # light (seed 6.3.2) with a gradient across a dot; relative darkness 1 - I / plane is then the dot's
        # coverage whatever the illumination, so its centroid is the dot's area centroid (blur preserves it).
        if ring.sum() >= 8:
            design = np.column_stack([np.ones(ring.sum()), gx[ring] - x0, gy[ring] - y0])
            coef, *_ = np.linalg.lstsq(design, win[ring].astype(np.float64), rcond=None)
            plane = coef[0] + coef[1] * (gx - x0) + coef[2] * (gy - y0)
        else:
            plane = background[ya:yb, xa:xb]
        rel = 1.0 - win / np.maximum(plane, 1.0)
        wgt = np.clip(rel, 0.0, None) * (grown & ~others.astype(bool))
        total = float(wgt.sum())
        if total <= 0:
            continue
        xs.append((float((wgt * gx).sum() / total), float((wgt * gy).sum() / total)))
        areas.append(float(area))
        darks.append(float(dark[ya:yb, xa:xb][comp.astype(bool)].mean()))
    xy = np.array(xs, dtype=np.float64).reshape(-1, 2)
    return DotDetections(xy=xy, area=np.array(areas), darkness=np.array(darks))


# ------------------------------------------------------------------------------------------------ grid topology


def _seed_lattice(xy: np.ndarray, tree: cKDTree, center: np.ndarray) -> tuple[int, np.ndarray, np.ndarray] | None:
    """A dot near the centre whose four lattice neighbours are where a regular lattice puts them (strictly first;
    a ridge's slopes can leave no strictly regular dot in a narrow strip, so then more loosely)."""
    for tol in (0.15, 0.3):
        found = _seed_lattice_within(xy, tree, center, tol)
        if found is not None:
            return found
    return None


def _seed_lattice_within(xy, tree, center, tol) -> tuple[int, np.ndarray, np.ndarray] | None:
    k = min(7, len(xy))
    order = np.argsort(np.linalg.norm(xy - center, axis=1))
    for idx in order[: min(len(order), 60)]:
        dist, nb = tree.query(xy[idx], k=k)
        vecs = xy[nb[1:]] - xy[idx]
        dist = dist[1:]
        if len(vecs) < 4 or not np.all(np.isfinite(dist)):
            continue
        a1 = vecs[0]
        cos = np.abs(vecs @ a1) / (np.linalg.norm(vecs, axis=1) * np.linalg.norm(a1))
        cand = np.flatnonzero(cos < 0.5)
        if cand.size == 0:
            continue
        a2 = vecs[cand[0]]
        ok = True
        for vec in (a1, -a1, a2, -a2):
            d, _ = tree.query(xy[idx] + vec)
            if d > tol * np.linalg.norm(vec):
                ok = False
                break
        if not ok or np.linalg.norm(a2) > 2.5 * np.linalg.norm(a1):
            continue
        # i runs along the vector closer to the image x axis, j along the other; both point to +x / +y.
        a, b = (a1, a2) if abs(a1[0]) / np.linalg.norm(a1) >= abs(a2[0]) / np.linalg.norm(a2) else (a2, a1)
        a = a if a[0] > 0 else -a
        b = b if b[1] > 0 else -b
        return int(idx), a, b
    return None


def index_grid(xy: np.ndarray, *, image_shape: tuple[int, int] | None = None, tolerance: float = 0.3) -> np.ndarray:
    """Lattice indices (i, j) of grid dots, robust to missing and spurious dots and to a ridge or valley.

    Rows of constant ``j`` run along the surface's rulings (image x), where the dot pitch is regular; across them
    the pitch changes by up to ~2x over a ridge's slopes, so no fixed lattice vector predicts the next row. The
    grid is therefore indexed row by row from a regular seed dot near the image centre: a row is walked along
    its local lattice vector (jumping over single missing dots), then the next row is found by *consensus*: every
    dot of the current row proposes its nearest dot ahead, and only proposals whose step agrees with the row's
    median step are kept (a missing dot would propose the row after next, a speck something in between).

    Parameters
    ----------
    xy : (K, 2) array
        Dot centres, px.
    image_shape : (H, W), optional
        Used to pick the seed near the image centre (default: the centre of the dots).
    tolerance : float
        A predicted position accepts the nearest dot within this fraction of the local lattice step.

    Returns
    -------
    (K, 2) int64
        (i, j) of each dot; unindexed dots (spurious, or off the lattice) get ``INDEX_NONE`` in both columns.
        Dot (0, 0) is the seed; i increases along +x, j along +y.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or not np.all(np.isfinite(xy)):
        raise InvalidInputError(f"xy must be a finite (K, 2) array, got shape {xy.shape}")
    if not 0 < tolerance < 0.5:
        raise InvalidInputError(f"tolerance must be in (0, 0.5), got {tolerance!r}")
    out = np.full((len(xy), 2), INDEX_NONE, dtype=np.int64)
    if len(xy) < 5:
        return out
    tree = cKDTree(xy)
    center = (
        np.array([(image_shape[1] - 1) / 2, (image_shape[0] - 1) / 2]) if image_shape is not None else xy.mean(0)
    )
    seed = _seed_lattice(xy, tree, center)
    if seed is None:
        return out
    idx0, a0, b0 = seed
    where: dict[tuple[int, int], int] = {}
    taken = np.zeros(len(xy), dtype=bool)

    def assign(key: tuple[int, int], k: int) -> None:
        where[key] = k
        taken[k] = True

    def walk_row(j: int, row_step: float) -> None:
        """Extend row j both ways along its local lattice vector from the dots it already has."""
        for direction in (1, -1):
            frontier = sorted((i for (i, jj) in where if jj == j), reverse=direction == 1)
            todo = list(frontier)
            while todo:
                i = todo.pop()
                p = xy[where[(i, j)]]
                back = where.get((i - direction, j))
                vec = p - xy[back] if back is not None else direction * a0
                for hop in (1, 2):
                    key = (i + hop * direction, j)
                    if key in where:
                        break
                    tol = tolerance * min(np.linalg.norm(vec), row_step)
                    dist, nb = tree.query(p + hop * vec)
                    if dist <= tol and not taken[nb]:
                        assign(key, int(nb))
                        todo.append(key[0])
                        break

    def next_row(j: int, direction: int, step: np.ndarray) -> tuple[int, np.ndarray] | None:
        """Index row j + direction by consensus of row j's dots; returns the count found and the mean step."""
        row = [(i, where[(i, j)]) for (i, jj) in list(where) if jj == j]
        along = np.array([0.0, 0.0])
        cols = sorted(i for i, _ in row)
        if len(cols) >= 2:
            along = (xy[where[(cols[-1], j)]] - xy[where[(cols[0], j)]]) / (cols[-1] - cols[0])
        a_hat = along / np.linalg.norm(along) if np.linalg.norm(along) > 0 else a0 / np.linalg.norm(a0)
        a_len = np.linalg.norm(along) if np.linalg.norm(along) > 0 else np.linalg.norm(a0)
        n_hat = np.array([-a_hat[1], a_hat[0]])
        if n_hat @ (direction * b0) < 0:
            n_hat = -n_hat
        proposals = []
        for i, k in row:
            p = xy[k]
            cand = tree.query_ball_point(p + 0.9 * step, r=1.6 * max(np.linalg.norm(step), 1.0))
            best = None
            for c in cand:
                if taken[c]:
                    continue
                o = xy[c] - p
                f, al = o @ n_hat, o @ a_hat
                if f <= 0.25 * np.linalg.norm(step) or abs(al - step @ a_hat) > 0.45 * a_len:
                    continue
                if best is None or f < best[0]:
                    best = (f, al, c)
            if best is not None:
                proposals.append((i, *best))
        if len(proposals) < 3:
            return None
        f_med = float(np.median([q[1] for q in proposals]))
        al_med = float(np.median([q[2] for q in proposals]))
        steps = []
        for i, f, al, c in proposals:
            if abs(f - f_med) <= tolerance * f_med and abs(al - al_med) <= tolerance * min(a_len, f_med):
                key = (i, j + direction)
                if key not in where and not taken[c]:
                    assign(key, int(c))
                    steps.append(xy[c] - xy[where[(i, j)]])
        if len(steps) < 3:
            return None
        return len(steps), np.mean(steps, axis=0)

    assign((0, 0), idx0)
    walk_row(0, float(np.linalg.norm(b0)))
    for direction in (1, -1):
        j, step = 0, direction * b0
        while True:
            found = next_row(j, direction, step)
            if found is None:
                break
            _, step = found
            j += direction
            walk_row(j, float(np.linalg.norm(step)))
    for (i, j), k in where.items():
        out[k] = (i, j)
    return out



# ------------------------------------------------------------------------------------------------ the rig model


def _rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(rotvec))
    if theta < 1e-15:
        return np.eye(3)
    k = rotvec / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * (kx @ kx)


@dataclass(frozen=True)
class _SplineBasis:
    """Cubic B-spline correction to a Gaussian profile: uniform knots, zero (with its first two derivatives)
    outside them, so the surface stays flat away from the shape."""

    knots: tuple[float, ...]

    @property
    def n(self) -> int:
        return len(self.knots) - 4

    @classmethod
    def around(cls, center: float, sigma: float, *, step: float = 0.3, extent_sigmas: float = 5.0) -> "_SplineBasis":
        n_int = max(4, int(math.ceil(2 * extent_sigmas * sigma / step)))
        lo = center - 0.5 * n_int * step
        return cls(knots=tuple(float(lo + k * step) for k in range(n_int + 1)))


class _Profile:
    """Height profile (Gaussian, optionally plus a B-spline correction) and its tabulated arc length from v = 0."""

    def __init__(self, amplitude: float, sigma: float, center: float, knots: tuple = (), coefs: tuple = (), *,
                 step: float = 0.01) -> None:
        self.amplitude, self.sigma, self.center = float(amplitude), float(sigma), float(center)
        self.spline = BSpline(np.asarray(knots), np.asarray(coefs), 3, extrapolate=False) if len(coefs) else None
        self.dspline = self.spline.derivative() if self.spline is not None else None
        self.flat = self.amplitude == 0.0 and self.spline is None
        if self.flat:
            return
        # Tabulate where the surface is not flat (Gaussian beyond 8 sigma < 1e-13 mm; the spline has compact
        # support) and through v = 0, the arc length's origin; outside, s - v is constant.
        lo, hi = min(center - 8 * sigma, -0.5), max(center + 8 * sigma, 0.5)
        if len(knots):
            lo, hi = min(lo, knots[0]), max(hi, knots[-1])
        v = np.linspace(lo, hi, int(math.ceil((hi - lo) / step)) + 1)
        g = np.sqrt(1.0 + self.slope(v) ** 2)
        gm = np.sqrt(1.0 + self.slope(0.5 * (v[1:] + v[:-1])) ** 2)
        s = np.concatenate([[0.0], np.cumsum((v[1] - v[0]) / 6.0 * (g[:-1] + 4.0 * gm + g[1:]))])
        self.v, self.s = v, s - np.interp(0.0, v, s)

    def height(self, v: np.ndarray) -> np.ndarray:
        if self.flat:
            return np.zeros_like(v)
        z = (v - self.center) / self.sigma
        h = self.amplitude * np.exp(-0.5 * z * z)
        if self.spline is not None:
            h = h + np.nan_to_num(self.spline(v), nan=0.0)
        return h

    def slope(self, v: np.ndarray) -> np.ndarray:
        if self.flat:
            return np.zeros_like(v)
        z = (v - self.center) / self.sigma
        d = -self.amplitude * z / self.sigma * np.exp(-0.5 * z * z)
        if self.dspline is not None:
            d = d + np.nan_to_num(self.dspline(v), nan=0.0)
        return d

    def v_of_s(self, s: np.ndarray) -> np.ndarray:
        if self.flat:
            return s
        out = np.interp(s, self.s, self.v)
        out = np.where(s < self.s[0], self.v[0] + (s - self.s[0]), out)
        return np.where(s > self.s[-1], self.v[-1] + (s - self.s[-1]), out)

    def s_of_v(self, v: np.ndarray) -> np.ndarray:
        if self.flat:
            return v
        out = np.interp(v, self.v, self.s)
        out = np.where(v < self.v[0], self.s[0] + (v - self.v[0]), out)
        return np.where(v > self.v[-1], self.s[-1] + (v - self.v[-1]), out)


@functools.lru_cache(maxsize=32)
def _cached_profile(amplitude: float, sigma: float, center: float, knots: tuple, coefs: tuple) -> _Profile:
    # A finite-difference Jacobian perturbs one parameter at a time: most evaluations reuse the same profile.
    return _Profile(amplitude, sigma, center, knots, coefs)


@dataclass
class _Rig:
    """Camera + ruled surface: surface frame (u, s) mm <-> image px."""

    rotvec: np.ndarray
    trans: np.ndarray
    focal_px: float
    k1: float
    k2: float
    principal: np.ndarray
    amplitude: float
    sigma: float
    center: float
    knots: tuple = ()
    coefs: tuple = ()

    def __post_init__(self) -> None:
        self.R = _rotation_matrix(np.asarray(self.rotvec, dtype=np.float64))
        self.profile = _cached_profile(
            float(self.amplitude), float(self.sigma), float(self.center),
            tuple(float(k) for k in self.knots), tuple(float(c) for c in self.coefs),
        )

    def project(self, us: np.ndarray) -> np.ndarray:
        v = self.profile.v_of_s(us[..., 1])
        p = np.stack([us[..., 0], v, self.profile.height(v)], axis=-1)
        cam = p @ self.R.T + self.trans
        a, b = cam[..., 0] / cam[..., 2], cam[..., 1] / cam[..., 2]
        r2 = a * a + b * b
        rad = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        return np.stack([self.principal[0] + self.focal_px * a * rad, self.principal[1] + self.focal_px * b * rad], -1)

    def back_project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Surface (u, s) seen at pixels, and whether the ray met the surface in front of the camera."""
        ad = (xy[..., 0] - self.principal[0]) / self.focal_px
        bd = (xy[..., 1] - self.principal[1]) / self.focal_px
        a, b = ad.copy(), bd.copy()
        for _ in range(20):  # fixed point, then it is exact to ~1e-16 for percent-level distortion
            r2 = a * a + b * b
            rad = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
            a_new, b_new = ad / rad, bd / rad
            done = max(np.max(np.abs(a_new - a), initial=0.0), np.max(np.abs(b_new - b), initial=0.0)) < 1e-16
            a, b = a_new, b_new
            if done:
                break
        ray_c = np.stack([a, b, np.ones_like(a)], axis=-1)
        ray = ray_c @ self.R  # R^T applied to each ray: surface-frame direction
        c = -self.R.T @ self.trans  # camera centre in the surface frame
        ok = np.abs(ray[..., 1]) > 1e-9
        rv = np.where(ok, ray[..., 1], 1.0)
        k = ray[..., 2] / rv
        with np.errstate(divide="ignore", invalid="ignore"):
            v = c[1] - c[2] / np.where(np.abs(k) > 1e-12, k, np.nan)
            if not self.profile.flat:
                for _ in range(40):
                    g = c[2] + (v - c[1]) * k - self.profile.height(v)
                    step = g / (k - self.profile.slope(v))
                    v = v - step
                    if np.nanmax(np.abs(step), initial=0.0) < 1e-12:
                        break
        t = (v - c[1]) / rv
        ok &= np.isfinite(v) & (t > 0)
        u = c[0] + t * ray[..., 0]
        return np.stack([u, self.profile.s_of_v(v)], axis=-1), ok


def _rot2(phi: float) -> np.ndarray:
    return np.array([[math.cos(phi), -math.sin(phi)], [math.sin(phi), math.cos(phi)]])


# ------------------------------------------------------------------------------------------------ the mapping


@dataclass
class GridMapping:
    """A fitted pixel <-> unrolled-surface mapping (JSON-serialisable through ``to_dict`` / ``from_dict``).

    Build it with :func:`calibrate_grid_image`, :func:`calibrate_grid_images` or :func:`fit_grid_mapping`.
    ``surface_to_image(image_to_surface(xy)) == xy`` to ~1e-9 px.
    """

    width: int
    height: int
    surface: str
    rig: dict[str, Any]
    frame: dict[str, Any]
    report: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.surface not in SURFACE_KINDS:
            raise InvalidInputError(f"surface must be one of {SURFACE_KINDS}, got {self.surface!r}")
        r = self.rig
        try:
            self._rig = _Rig(
                rotvec=np.asarray(r["rotvec"], dtype=np.float64),
                trans=np.asarray(r["trans"], dtype=np.float64),
                focal_px=float(r["focal_px"]),
                k1=float(r["k1"]),
                k2=float(r["k2"]),
                principal=np.asarray(r["principal"], dtype=np.float64),
                amplitude=float(r["amplitude_mm"]),
                sigma=float(r["sigma_mm"]),
                center=float(r["center_mm"]),
                knots=tuple(float(k) for k in r.get("spline_knots", ())),
                coefs=tuple(float(c) for c in r.get("spline_coefs", ())),
            )
            if len(self._rig.coefs) and len(self._rig.knots) != len(self._rig.coefs) + 4:
                raise ValueError("spline_knots must have 4 more entries than spline_coefs")
            self._frame_rot = _rot2(float(self.frame["angle_rad"]))
            self._frame_origin = np.asarray(self.frame["origin_mm"], dtype=np.float64).reshape(2)
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidInputError(f"mapping parameters incomplete or malformed: {exc}") from None

    # Output frame: out = R_frame^T (us - origin), i.e. ``frame`` holds where the output frame sits in the rig frame.
    def image_to_surface(self, xy_px: np.ndarray) -> np.ndarray:
        """Unrolled surface position (u, s) in mm of image pixels (x, y); (..., 2) -> (..., 2).

        Pixels whose ray misses the surface (far outside any plausible field) raise CalibrationError.
        """
        xy = np.asarray(xy_px, dtype=np.float64)
        if xy.shape[-1:] != (2,):
            raise InvalidInputError(f"xy_px must have a trailing axis of 2, got shape {xy.shape}")
        us, ok = self._rig.back_project(xy)
        if not np.all(ok):
            raise CalibrationError(f"{int(np.size(ok) - np.count_nonzero(ok))} pixel(s) do not see the surface")
        return (us - self._frame_origin) @ self._frame_rot

    def surface_to_image(self, us_mm: np.ndarray) -> np.ndarray:
        """Image pixels (x, y) of unrolled surface positions (u, s) in mm; (..., 2) -> (..., 2)."""
        us = np.asarray(us_mm, dtype=np.float64)
        if us.shape[-1:] != (2,):
            raise InvalidInputError(f"us_mm must have a trailing axis of 2, got shape {us.shape}")
        return self._rig.project(us @ self._frame_rot.T + self._frame_origin)

    @property
    def px_per_mm(self) -> float:
        """Pixels per mm along the image x axis at the image centre (the axis without the sqrt(2) compression)."""
        c = np.array([[(self.width - 1) / 2.0, (self.height - 1) / 2.0]])
        d = self.image_to_surface(c + [[0.5, 0.0]]) - self.image_to_surface(c - [[0.5, 0.0]])
        return float(1.0 / np.linalg.norm(d))

    def for_window(self, *, x0: int, y0: int, width: int, height: int) -> "GridMapping":
        """The same mapping for a sub-window of the sensor (the camera's half and strip modes, seed 3.3).

        A strip 100 rows high holds too few grid rows to fit a ridge's profile: calibrate on a full frame, then
        take the window whose top-left pixel is (``x0``, ``y0``) of the full frame. The surface frame is kept.
        """
        for name, value in (("x0", x0), ("y0", y0)):
            if int(value) < 0:
                raise InvalidInputError(f"{name} must be >= 0, got {value!r}")
        if int(width) <= 0 or int(height) <= 0 or x0 + width > self.width or y0 + height > self.height:
            raise InvalidInputError(
                f"window {width}x{height} at ({x0}, {y0}) does not fit in the {self.width}x{self.height} calibration"
            )
        rig = dict(self.rig)
        rig["principal"] = (np.asarray(self.rig["principal"], dtype=np.float64) - [x0, y0]).tolist()
        return GridMapping(width=int(width), height=int(height), surface=self.surface, rig=rig,
                           frame=dict(self.frame), report=dict(self.report, window=[int(x0), int(y0)]))

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable description (plain floats, lists, strings)."""
        def plain(value: Any) -> Any:
            if isinstance(value, dict):
                return {k: plain(v) for k, v in value.items()}
            if isinstance(value, (list, tuple, np.ndarray)):
                return [plain(v) for v in np.asarray(value).tolist()] if isinstance(value, np.ndarray) else [
                    plain(v) for v in value
                ]
            if isinstance(value, (np.floating, np.integer)):
                return value.item()
            return value

        return {
            "kind": MAPPING_KIND,
            "version": MAPPING_VERSION,
            "width": int(self.width),
            "height": int(self.height),
            "surface": self.surface,
            "rig": plain(self.rig),
            "frame": plain(self.frame),
            "report": plain(self.report),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "GridMapping":
        return mapping_from_dict(data)


def mapping_from_dict(data: dict[str, Any]) -> GridMapping:
    """Rebuild a mapping from :meth:`GridMapping.to_dict` output; CalibrationError if it is not one."""
    if not isinstance(data, dict) or data.get("kind") != MAPPING_KIND:
        raise CalibrationError(f"not a skinstretch grid mapping (kind {data.get('kind') if isinstance(data, dict) else type(data).__name__!r})")
    if data.get("version") != MAPPING_VERSION:
        raise CalibrationError(f"grid mapping version {data.get('version')!r} is not supported (reads {MAPPING_VERSION})")
    try:
        return GridMapping(
            width=int(data["width"]),
            height=int(data["height"]),
            surface=str(data["surface"]),
            rig=dict(data["rig"]),
            frame=dict(data["frame"]),
            report=dict(data.get("report", {})),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"grid mapping is incomplete: {exc}") from None


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
    _SplineBasis (Gaussian plus spline, whose coefficients close the vector)."""
    knots, coefs = (), ()
    if isinstance(curved, _SplineBasis):
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
    model = _Rig(
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
    return (ij * spacing) @ _rot2(phi).T + np.array([tu, ts])


def _select(views: list[_GridView], keep: np.ndarray) -> list[_GridView]:
    """The views restricted to the dots flagged in ``keep`` (one flag per dot, all views concatenated)."""
    out, start = [], 0
    for view in views:
        sel = keep[start : start + len(view.ij)]
        out.append(_GridView(ij=view.ij[sel], xy=view.xy[sel]))
        start += len(view.ij)
    return out


def _dot_image_offset(model: _Rig, pose, ij: np.ndarray, spacing: float, radius: float, n: int = 48) -> np.ndarray:
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
    if isinstance(curved, _SplineBasis):
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
    R = np.stack([cr * ex - sr * ey, sr * ex + cr * ey, d])
    # Rotation vector of R (Rodrigues inverse).
    angle = math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2)))
    if angle < 1e-12:
        rotvec = np.zeros(3)
    else:
        rotvec = angle / (2 * math.sin(angle)) * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
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
        method="trf", bounds=(lb, ub), max_nfev=max_nfev if not isinstance(curved, _SplineBasis) else min(max_nfev, 80),
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
    image_shape : (H, W)
        Image size.
    surface : {"auto", "flat", "ridge", "valley"}
        Surface model; "auto" guesses it from the spacing of the rows and keeps the best fit.
    spacing_mm : float
        Dot pitch of the grid.
    working_distance_mm : float
        Nominal camera distance (starting point only).
    shape_height_mm, shape_width_mm : float
        Nominal size of a ridge or valley (starting point only; width = 4 sigma).
    max_rms_px : float
        A fit whose RMS residual exceeds this raises CalibrationError.
    min_dots : int
        Fewer indexed dots (all images together) raise CalibrationError.
    outlier_px : float
        Dots whose residual exceeds max(outlier_px, 5 x robust sigma) after the robust fit are dropped.
    dot_diameter_mm : float or None
        Dot diameter; the offset between a dot's image centroid and the image of its centre is then predicted with
        the fitted rig and removed (None: detected centroids are taken as the dot centres).
    spline_profile : bool
        When the Gaussian profile leaves systematic residuals (median above ``SPLINE_TRIGGER_PX``), add a smooth
        cubic-spline correction to the ridge or valley profile.
    n_detected : int, optional
        Number of dots detected (for the report only).

    Returns
    -------
    mapping : GridMapping
    report : CalibrationReport
    """
    if surface not in ("auto",) + SURFACE_KINDS:
        raise InvalidInputError(f"surface must be 'auto' or one of {SURFACE_KINDS}, got {surface!r}")
    for name, value in (("spacing_mm", spacing_mm), ("working_distance_mm", working_distance_mm),
                        ("max_rms_px", max_rms_px), ("shape_width_mm", shape_width_mm),
                        ("outlier_px", outlier_px)):
        if not (math.isfinite(value) and value > 0):
            raise InvalidInputError(f"{name} must be positive, got {value!r}")
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
                t = uc - _rot2(phi) @ gc
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
                curved = _SplineBasis.around(model.center, model.sigma)
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
    if dot_diameter_mm is not None and not isinstance(curved, _SplineBasis):
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
    rot = _rot2(angle)
    down, _ = model.back_project(np.array([principal + [0.0, 1.0]]))
    if ((down[0] - centre_us[0]) @ rot)[1] < 0:
        raise CalibrationError("fitted surface frame is mirrored (s decreases down the image); grid misindexed")
    rig = {
        "rotvec": model.rotvec.tolist(),
        "trans": model.trans.tolist(),
        "focal_px": float(model.focal_px),
        "k1": float(model.k1),
        "k2": float(model.k2),
        "principal": principal.tolist(),
        "amplitude_mm": float(model.amplitude),
        "sigma_mm": float(model.sigma) if curved else 1.0,
        "center_mm": float(model.center),
        # Spline correction of the profile (empty when the Gaussian fits): cubic B-spline knots and coefficients.
        "spline_knots": [float(k) for k in model.knots],
        "spline_coefs": [float(c) for c in model.coefs],
    }
    frame = {"angle_rad": angle, "origin_mm": centre_us[0].tolist()}
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
    mapping.report = report.summary()
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


def calibrate_grid_images(
    images: Sequence[np.ndarray],
    *,
    px_per_mm: float,
    surface: str = "auto",
    spacing_mm: float = 0.5,
    dot_diameter_mm: float = 0.2,
    working_distance_mm: float = 150.0,
    max_rms_px: float = 0.5,
    min_dots: int = 40,
    min_indexed_fraction: float = 0.5,
) -> tuple[GridMapping, CalibrationReport]:
    """Calibrate from one or more images of a dot grid (moved between images, seed 7.2.1), all of one rig.

    Parameters
    ----------
    images : sequence of (H, W) arrays
        Grid images (dark dots on a bright surface), all the same size.
    px_per_mm : float
        Nominal scale along the image x axis (e.g. 640 px / 10.3 mm), for dot sizes and the starting point.
    surface, spacing_mm, working_distance_mm, max_rms_px, min_dots
        See :func:`fit_grid_mapping`.
    dot_diameter_mm : float
        Dot diameter on the sheet.
    min_indexed_fraction : float
        If fewer than this fraction of the detected dots of an image fit one lattice, there is no grid in it.

    Returns
    -------
    mapping : GridMapping
    report : CalibrationReport

    Raises
    ------
    CalibrationError
        No dots, too few dots, no lattice among the dots, or residuals too large.
    """
    if len(images) == 0:
        raise InvalidInputError("images must hold at least one image")
    if not (math.isfinite(px_per_mm) and px_per_mm > 0):
        raise InvalidInputError(f"px_per_mm must be positive, got {px_per_mm!r}")
    shape = np.asarray(images[0]).shape
    views, n_detected = [], 0
    for k, image in enumerate(images):
        if np.asarray(image).shape != shape:
            raise InvalidInputError(f"image {k} has shape {np.asarray(image).shape}, expected {shape}")
        dots = detect_dots(image, px_per_mm=px_per_mm, dot_diameter_mm=dot_diameter_mm)
        n_detected += len(dots)
        if len(dots) < 5:
            raise CalibrationError(f"image {k}: grid not found ({len(dots)} dots detected)")
        ij = index_grid(dots.xy, image_shape=shape)
        ok = ij[:, 0] != INDEX_NONE
        if ok.sum() < min_indexed_fraction * len(dots) or ok.sum() < 10:
            hint = (
                "; in a narrow strip over a ridge or valley no row spacing is regular: calibrate on a full frame "
                "and use GridMapping.for_window" if shape[0] < 0.5 * shape[1] else ""
            )
            raise CalibrationError(
                f"image {k}: grid not found ({ok.sum()} of {len(dots)} detected dots form a lattice){hint}"
            )
        views.append((ij[ok], dots.xy[ok]))
    return fit_grid_mapping(
        views,
        image_shape=shape,
        surface=surface,
        spacing_mm=spacing_mm,
        working_distance_mm=working_distance_mm,
        max_rms_px=max_rms_px,
        min_dots=min_dots,
        dot_diameter_mm=dot_diameter_mm,
        n_detected=n_detected,
    )


def calibrate_grid_image(image: np.ndarray, *, px_per_mm: float, **options: Any) -> tuple[GridMapping, CalibrationReport]:
    """Calibrate from a single grid image; options as for :func:`calibrate_grid_images`."""
    return calibrate_grid_images([image], px_per_mm=px_per_mm, **options)

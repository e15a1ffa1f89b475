"""Images of the seed's calibration grid seen through the prism, with exact ground truth (seed 3.4).

The seed prints dots 0.5 mm apart on transparency film and presses it on the contact surface with a film of oil:
the dots touch the glass and stop the reflection, so they are DARK on the bright surface. The sheet follows the
ruled surface without stretching (it is developable), so the dots form a square lattice in the *unrolled* surface
coordinates (u, s) of :mod:`skinstretch.simulators.ideal_optics`. This module renders that picture through any :class:`Optics`
(typically :class:`skinstretch.simulators.prism_optics.PrismOptics` with a flat, ridge or valley surface) with the defects the
seed reports (seed 7.2.1): missing dots (bubbles in the oil), spurious dark specks (dust), darker illumination on
the slopes, blur and noise. The ground truth is every dot's lattice index, surface position and projected centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from skinstretch.processing.argument_checks import non_negative_number, positive_number
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.ideal_optics import Optics


@dataclass
class CalibrationGridImage:
    """A rendered calibration-grid image and its ground truth.

    Attributes
    ----------
    image : (H, W) uint8
        The picture.
    ij : (K, 2) int
        Lattice index (i along u, j along s) of every dot of the sheet that falls in the field of view.
    us_mm : (K, 2) float
        Surface position (u, s) of each dot centre, mm.
    xy_px : (K, 2) float
        Image position of each dot centre (its projection through the optics), px.
    drawn : (K,) bool
        False for the dots removed to simulate missing dots.
    inside : (K,) bool
        True when the whole dot lies inside the image (at least a dot radius from the border).
    spurious_xy_px : (M, 2) float
        Centres of the spurious dark specks added.
    spacing_mm, dot_diameter_mm : float
        The sheet's dot pitch and dot size.
    optics : Optics
        The optics that produced the image (its ``image_to_surface`` is the true mapping).
    """

    image: np.ndarray
    ij: np.ndarray
    us_mm: np.ndarray
    xy_px: np.ndarray
    drawn: np.ndarray
    inside: np.ndarray
    spurious_xy_px: np.ndarray
    spacing_mm: float
    dot_diameter_mm: float
    optics: Optics

    @property
    def visible(self) -> np.ndarray:
        """Dots that are drawn and wholly inside the image (the ones a detector should find)."""
        return self.drawn & self.inside


def _pixel_jacobian(us: np.ndarray) -> np.ndarray:
    """d(x, y)/d(u, s) per pixel from the per-pixel surface coordinates (central differences), shape (H, W, 2, 2)."""
    dus_dx = np.gradient(us, axis=1)  # (H, W, 2): d(u, s)/dx
    dus_dy = np.gradient(us, axis=0)
    inv = np.stack([dus_dx, dus_dy], axis=-1)  # rows u, s; columns x, y
    return np.linalg.inv(inv)  # rows x, y; columns u, s


def render_calibration_grid(
    optics: Optics,
    *,
    spacing_mm: float = 0.5,
    dot_diameter_mm: float = 0.2,
    offset_mm: tuple[float, float] = (0.0, 0.0),
    rotation_deg: float = 0.0,
    missing_fraction: float = 0.0,
    n_spurious: int = 0,
    bright_level: float = 210.0,
    dark_level: float = 25.0,
    slope_darkening: float = 0.8,
    vignetting: float = 0.15,
    blur_sigma_px: float = 0.6,
    noise_sigma: float = 2.0,
    seed: int = 0,
) -> CalibrationGridImage:
    """Render a dot-grid calibration image through ``optics`` with its ground truth.

    Parameters
    ----------
    optics : Optics
        Maps surface (u, s) mm to image px; a ``surface`` attribute (``slope(v)``), when present, darkens the slopes.
    spacing_mm : float
        Dot pitch on the sheet (seed 3.4: 0.5 mm).
    dot_diameter_mm : float
        Dot diameter on the sheet.
    offset_mm : (float, float)
        Surface position (u, s) of dot (0, 0); moving it simulates the seed's 7.2.1 "moving grid".
    rotation_deg : float
        Rotation of the lattice in the unrolled surface plane (counter-clockwise from the u axis).
    missing_fraction : float
        Fraction of dots removed at random (bubbles in the oil, seed 7.2.1).
    n_spurious : int
        Number of dark specks (dust) added at random places, 0.5 to 1.5 dot diameters across.
    bright_level, dark_level : float
        Grey levels of the reflecting surface and of a dot.
    slope_darkening : float
        The surface's brightness is multiplied by ``1 - slope_darkening * |slope|`` (seed 6.3.2: the slopes of a
        ridge or valley show up darker).
    vignetting : float
        Relative brightness loss at the image corners (smooth, quadratic).
    blur_sigma_px : float
        Gaussian optical blur.
    noise_sigma : float
        Additive Gaussian noise, grey levels.
    seed : int
        Seed of the random defects and noise.

    Returns
    -------
    CalibrationGridImage
    """
    for name, value in (("spacing_mm", spacing_mm), ("dot_diameter_mm", dot_diameter_mm)):
        positive_number(value, name)
    if dot_diameter_mm >= spacing_mm:
        raise InvalidInputError(f"dot_diameter_mm ({dot_diameter_mm}) must be smaller than spacing_mm ({spacing_mm})")
    if not 0.0 <= missing_fraction < 1.0:
        raise InvalidInputError(f"missing_fraction must be in [0, 1), got {missing_fraction!r}")
    if int(n_spurious) < 0:
        raise InvalidInputError(f"n_spurious must be >= 0, got {n_spurious!r}")
    for name, value in (("blur_sigma_px", blur_sigma_px), ("noise_sigma", noise_sigma),
                        ("slope_darkening", slope_darkening), ("vignetting", vignetting)):
        non_negative_number(value, name)
    rng = np.random.default_rng(seed)
    h, w = int(optics.height), int(optics.width)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    us = optics.image_to_surface(np.stack([xx, yy], axis=-1))

    # Lattice coordinates of every pixel's surface point, and the offset to the nearest lattice node.
    phi = math.radians(rotation_deg)
    rot = np.array([[math.cos(phi), -math.sin(phi)], [math.sin(phi), math.cos(phi)]])
    off = np.asarray(offset_mm, dtype=np.float64)
    lat = ((us - off) @ rot) / spacing_mm  # R^T (us - off): lattice frame, in pitches
    node = np.rint(lat)
    delta_us = ((lat - node) * spacing_mm) @ rot.T  # nearest node -> point, surface mm

    # Lattice nodes in view, and which are missing.
    i_lo, j_lo = node[..., 0].min() - 1, node[..., 1].min() - 1
    i_hi, j_hi = node[..., 0].max() + 1, node[..., 1].max() + 1
    ii, jj = np.meshgrid(np.arange(i_lo, i_hi + 1), np.arange(j_lo, j_hi + 1), indexing="ij")
    ij_all = np.stack([ii.ravel(), jj.ravel()], axis=-1).astype(np.int64)
    us_all = (ij_all * spacing_mm) @ rot.T + off
    xy_all = optics.surface_to_image(us_all)
    margin = 1.0
    keep = (xy_all[:, 0] > -margin) & (xy_all[:, 0] < w - 1 + margin) & (xy_all[:, 1] > -margin) & (
        xy_all[:, 1] < h - 1 + margin
    )
    ij_all, us_all, xy_all = ij_all[keep], us_all[keep], xy_all[keep]
    drawn = rng.random(len(ij_all)) >= missing_fraction
    missing_keys = {(int(a), int(b)) for a, b in ij_all[~drawn]}

    # Anti-aliased disc coverage: signed distance to the disc edge, in pixels along the direction to the node.
    jac = _pixel_jacobian(us)
    dpx = np.einsum("...ab,...b->...a", jac, delta_us)
    dist_px = np.linalg.norm(dpx, axis=-1)
    dist_mm = np.linalg.norm(delta_us, axis=-1)
    radius = 0.5 * dot_diameter_mm
    signed = dist_px * (1.0 - radius / np.maximum(dist_mm, 1e-12))
    coverage = np.clip(0.5 - signed, 0.0, 1.0)
    if missing_keys:
        # Pixels whose nearest node is a missing dot show the bare surface.
        big = 1 << 20
        pixel_key = node[..., 0].astype(np.int64) * big + node[..., 1].astype(np.int64)
        missing = np.array([a * big + b for a, b in missing_keys], dtype=np.int64)
        coverage[np.isin(pixel_key, missing)] = 0.0

    # Spurious specks (dust), drawn in the image plane.
    n_spurious = int(n_spurious)
    spurious = np.column_stack([rng.uniform(10, w - 11, n_spurious), rng.uniform(10, h - 11, n_spurious)])
    dot_px = dot_diameter_mm * optics.px_per_mm
    for (sx, sy), scale in zip(spurious, rng.uniform(0.5, 1.5, n_spurious)):
        r = 0.5 * dot_px * scale
        d = np.hypot(xx - sx, (yy - sy) * rng.uniform(0.8, 1.25)) - r
        coverage = np.maximum(coverage, np.clip(0.5 - d, 0.0, 1.0))

    # Illumination: slopes darker (seed 6.3.2), smooth vignetting.
    illum = np.ones((h, w))
    surface = getattr(optics, "surface", None)
    if surface is not None and hasattr(surface, "slope") and hasattr(optics, "surface_points_3d"):
        v = optics.surface_points_3d(us)[..., 1]
        illum *= np.clip(1.0 - slope_darkening * np.abs(surface.slope(v)), 0.05, 1.0)
    rr = ((xx - (w - 1) / 2) / (w / 2)) ** 2 + ((yy - (h - 1) / 2) / (h / 2)) ** 2
    illum *= 1.0 - vignetting * rr / 2.0
    img = illum * (bright_level * (1.0 - coverage) + dark_level * coverage)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    image = np.clip(np.rint(img), 0, 255).astype(np.uint8)

    # A dot is wholly inside when its centre is a radius (along each image axis) away from the border.
    scale = np.abs(optics.local_scale(us_all)) if hasattr(optics, "local_scale") else None
    if scale is not None:
        rx = radius * np.hypot(scale[:, 0, 0], scale[:, 0, 1]) + 1.5
        ry = radius * np.hypot(scale[:, 1, 0], scale[:, 1, 1]) + 1.5
    else:
        rx = ry = np.full(len(xy_all), radius * optics.px_per_mm + 1.5)
    inside = (xy_all[:, 0] >= rx) & (xy_all[:, 0] <= w - 1 - rx) & (xy_all[:, 1] >= ry) & (xy_all[:, 1] <= h - 1 - ry)
    return CalibrationGridImage(
        image=image,
        ij=ij_all,
        us_mm=us_all,
        xy_px=xy_all,
        drawn=drawn,
        inside=inside,
        spurious_xy_px=spurious,
        spacing_mm=float(spacing_mm),
        dot_diameter_mm=float(dot_diameter_mm),
        optics=optics,
    )

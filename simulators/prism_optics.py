"""The seed's imaging rig as a forward model: contact surface -> 45-degree prism view -> lens -> sensor (seed 3.2-3.4).

Geometry
--------
The contact surface is the prism's hypotenuse face, or a glass plate joined to it with index-matching oil (seed 3.3),
so the camera sees every surface point through glass of one index. A right-handed surface frame has ``U`` along the
rulings (the surface height does not vary along ``U``), ``V`` across them, in the flat contact plane, and ``N`` the
plane's normal pointing out of the glass, into the finger. The surface is *parallel-ruled* (seed appendix A: only a
height profile across the rulings keeps FTIR working): the point at ``v`` across the rulings sits at height
``h(v)`` along ``N`` (ridge: ``h > 0``, towards the finger; valley: ``h < 0``, into the plate).

Surface coordinates (``skinstretch.simulators.ideal_optics``) are the *unrolled* ones of seed 3.4: ``u`` along ``U`` and ``s`` the arc
length of the profile curve ``(v, h(v))`` from ``v = 0`` (the centre of the field of view), both in mm.

The camera looks through the prism's exit face at the contact plane at ``view_angle_deg`` (45 degrees) from its
normal, tilted about ``U``: lengths along ``V`` are foreshortened by ``cos(45 deg)``, the sqrt(2) compression of
seed 3.2. The compressed axis is the image ``y`` axis (rows): with square pixels this is what reproduces the seed's
~10.3 x 10.8 mm full field on 640 x 484 pixels, and it keeps ``s`` along ``y`` as :class:`skinstretch.simulators.ideal_optics.
IdealOptics` does. The camera is a pinhole at ``working_distance_mm`` from the field centre (an air-equivalent
distance: the glass path is counted as its length divided by the index, which is exact for the paraxial rays of this
narrow, ~2 degree, field), followed by Brown-Conrady lens distortion (radial ``k1``, ``k2``, tangential ``p1``,
``p2``) about the principal point, and a sensor of square pixels. The focal length in pixels is set so that
``field_width_mm`` of the flat surface spans the image width along ``u`` at the centre.

What is not modelled: refraction away from the paraxial limit, depth of field blur, chromatic effects, the finite
thickness of the oil film (seed 7.2.1 notes it can fill valleys).
"""

from __future__ import annotations

import math
from dataclasses import field

import numpy as np
from pydantic import Field, model_validator

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.ruled_surface_rays import ArcLengthTable, cast_rays, surface_points
from skinstretch.processing.validated_dataclass import FiniteFloat, Float, PositiveFloat, PositiveInt, validated_dataclass
from skinstretch.simulators.ideal_optics import Optics
from skinstretch.simulators.surfaces import RuledSurface


@validated_dataclass
class SkewedRidgeSurface(RuledSurface):
    """A ruled ridge or valley whose profile is *not* Gaussian: a Gaussian with a different sigma on each side of
    the crest, as a machined surface might come out. It tests calibrations that assume the Gaussian shape.

    ``width_mm`` still sets the nominal sigma (width / 4); the rising side uses ``sigma * skew_before`` and the
    falling side ``sigma * skew_after``.
    """

    skew_before: PositiveFloat = 0.8
    skew_after: PositiveFloat = 1.2

    def _sigmas(self, z: np.ndarray) -> np.ndarray:
        return np.where(z < 0, self.sigma_mm * self.skew_before, self.sigma_mm * self.skew_after)

    def height(self, z_mm):
        z = np.asarray(z_mm, dtype=np.float64) - self.center_mm
        return self.sign * self.height_mm * np.exp(-0.5 * (z / self._sigmas(z)) ** 2)

    def slope(self, z_mm):
        z = np.asarray(z_mm, dtype=np.float64) - self.center_mm
        sig = self._sigmas(z)
        return -z / sig**2 * self.sign * self.height_mm * np.exp(-0.5 * (z / sig) ** 2)

    @property
    def max_slope(self) -> float:
        return abs(self.sign) * self.height_mm / (self.sigma_mm * min(self.skew_before, self.skew_after)) * math.exp(
            -0.5
        )


@validated_dataclass
class PrismOptics(Optics):
    """Forward and inverse model of the seed's prism rig: surface (u, s) mm <-> image (x, y) px.

    Parameters
    ----------
    width, height : int
        Image size in pixels (default: the full camera mode, 640 x 484).
    surface : RuledSurface
        The contact surface (:mod:`skinstretch.simulators.surfaces`: flat, or the seed's Gaussian ridge or valley, whose 3 mm
        width is read as 4 sigma there). Default flat.
    field_width_mm : float
        Width of flat surface seen across the image width at the field centre (seed 6.3.2: ~10.3 mm).
    working_distance_mm : float
        Air-equivalent distance from the camera's pinhole to the field centre (~15 cm).
    view_angle_deg : float
        Angle between the camera's axis and the contact plane's normal (45 degrees for a right-angle prism).
    k1, k2 : float
        Radial distortion coefficients on normalised image coordinates (``x_d = x (1 + k1 r^2 + k2 r^4)``).
    p1, p2 : float
        Tangential (decentring) distortion coefficients.
    principal_offset_px : (float, float)
        Offset of the principal point (and distortion centre) from the image centre.
    roll_deg : float
        Rotation of the sensor about the camera axis.

    Examples
    --------
    >>> optics = PrismOptics(surface=RuledSurface(kind="ridge"))
    >>> xy = optics.surface_to_image(np.array([[1.0, -0.5]]))
    >>> bool(np.allclose(optics.image_to_surface(xy), [[1.0, -0.5]], atol=1e-9))
    True
    """

    width: PositiveInt = 640
    height: PositiveInt = 484
    surface: RuledSurface = field(default_factory=RuledSurface)
    field_width_mm: PositiveFloat = 10.3
    working_distance_mm: FiniteFloat = 150.0
    view_angle_deg: Float = Field(default=45.0, ge=0, lt=80)
    k1: FiniteFloat = -4.0
    k2: FiniteFloat = 0.0
    p1: FiniteFloat = 0.0
    p2: FiniteFloat = 0.0
    principal_offset_px: tuple[FiniteFloat, FiniteFloat] = (0.0, 0.0)
    roll_deg: FiniteFloat = 0.0

    @model_validator(mode="after")
    def _camera_sees_the_surface(self) -> "PrismOptics":
        if not self.working_distance_mm > 10 * self.field_width_mm:
            raise InvalidInputError(
                f"working_distance_mm must exceed 10x the field width, got {self.working_distance_mm!r}"
            )
        # The view must never graze the surface (|h'| tan(angle) < 1), or a ray would meet it twice.
        if self.surface.max_slope * math.tan(math.radians(self.view_angle_deg)) >= 0.95:
            raise InvalidInputError(
                f"the camera at {self.view_angle_deg} deg cannot see slopes of {self.surface.max_slope:.2f}"
            )
        return self

    def __post_init__(self) -> None:
        # Derived state (the fields are validated): the arc-length table and the camera's frame.
        # Flat beyond 12 sigma; the table reaches +/-40 mm at 2 um steps (interpolation error below 1e-6 mm).
        sigma, centre = self.surface.sigma_mm, self.surface.center_mm
        arc = ArcLengthTable(None) if self.surface.max_slope == 0.0 else ArcLengthTable(
            self.surface.slope, lo=min(-40.0, centre - 12 * sigma), hi=max(40.0, centre + 12 * sigma), step=0.002)
        object.__setattr__(self, "_arc", arc)
        t = math.radians(self.view_angle_deg)
        # Camera frame in surface-frame components (U, V, N): axis d, image axes ex (along U) and ey.
        d = np.array([0.0, math.sin(t), math.cos(t)])
        ex = np.array([1.0, 0.0, 0.0])
        ey = np.array([0.0, math.cos(t), -math.sin(t)])
        r = math.radians(self.roll_deg)
        ex, ey = math.cos(r) * ex + math.sin(r) * ey, -math.sin(r) * ex + math.cos(r) * ey
        object.__setattr__(self, "_axes", np.stack([ex, ey, d]))  # rows: camera x, y, z axes
        object.__setattr__(self, "_pinhole", -self.working_distance_mm * d)
        focal_px = self.width * self.working_distance_mm / self.field_width_mm
        object.__setattr__(self, "focal_px", focal_px)

    # ---------------------------------------------------------------- geometry helpers
    @property
    def px_per_mm(self) -> float:
        """Pixels per mm along ``u`` (image x) at the field centre; ``y`` carries ~1/sqrt(2) of it (seed 3.2)."""
        return self.width / self.field_width_mm

    @property
    def principal_point(self) -> np.ndarray:
        return self.center_px + np.asarray(self.principal_offset_px, dtype=np.float64)

    def surface_points_3d(self, us_mm: np.ndarray) -> np.ndarray:
        """3-D positions (U, V, N components, mm) of unrolled surface points (u, s)."""
        return surface_points(np.asarray(us_mm, dtype=np.float64), self.surface, self._arc)

    def _distort(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r2 = a * a + b * b
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        ad = a * radial + 2.0 * self.p1 * a * b + self.p2 * (r2 + 2.0 * a * a)
        bd = b * radial + self.p1 * (r2 + 2.0 * b * b) + 2.0 * self.p2 * a * b
        return ad, bd

    def _undistort(self, ad: np.ndarray, bd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Newton on the 2x2 distortion map, from the fixed-point start; distortion is ~1 % here so 4-5 steps reach
        # machine precision.
        a, b = ad.copy(), bd.copy()
        for _ in range(8):
            fa, fb = self._distort(a, b)
            ea, eb = fa - ad, fb - bd
            if max(np.max(np.abs(ea), initial=0.0), np.max(np.abs(eb), initial=0.0)) < 1e-15:
                break
            r2 = a * a + b * b
            radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
            drad = 2.0 * self.k1 + 4.0 * self.k2 * r2  # d(radial)/d(r2)
            j11 = radial + a * drad * 2 * a + 2 * self.p1 * b + 6 * self.p2 * a
            j12 = a * drad * 2 * b + 2 * self.p1 * a + 2 * self.p2 * b
            j21 = b * drad * 2 * a + 2 * self.p1 * a + 2 * self.p2 * b
            j22 = radial + b * drad * 2 * b + 6 * self.p1 * b + 2 * self.p2 * a
            det = j11 * j22 - j12 * j21
            a = a - (j22 * ea - j12 * eb) / det
            b = b - (-j21 * ea + j11 * eb) / det
        return a, b

    # ---------------------------------------------------------------- Optics interface
    def surface_to_image(self, us_mm: np.ndarray) -> np.ndarray:
        """Image pixels (x, y) of unrolled surface points (u, s) in mm (any leading shape, trailing axis 2)."""
        us = np.asarray(us_mm, dtype=np.float64)
        if us.shape[-1:] != (2,):
            raise InvalidInputError(f"us_mm must have a trailing axis of 2, got shape {us.shape}")
        q = self.surface_points_3d(us) - self._pinhole
        cam = q @ self._axes.T
        a, b = cam[..., 0] / cam[..., 2], cam[..., 1] / cam[..., 2]
        ad, bd = self._distort(a, b)
        pp = self.principal_point
        return np.stack([pp[0] + self.focal_px * ad, pp[1] + self.focal_px * bd], axis=-1)

    def image_to_surface(self, xy_px: np.ndarray) -> np.ndarray:
        """Unrolled surface points (u, s) in mm seen at image pixels (x, y): the inverse of ``surface_to_image``.

        Undistorts, casts the pixel's ray from the pinhole and intersects it with the ruled surface by Newton's
        method on ``v`` (the ray meets the surface exactly once because the view is never grazing, |h'| tan < 1).
        """
        xy = np.asarray(xy_px, dtype=np.float64)
        if xy.shape[-1:] != (2,):
            raise InvalidInputError(f"xy_px must have a trailing axis of 2, got shape {xy.shape}")
        pp = self.principal_point
        a, b = self._undistort((xy[..., 0] - pp[0]) / self.focal_px, (xy[..., 1] - pp[1]) / self.focal_px)
        ray = a[..., None] * self._axes[0] + b[..., None] * self._axes[1] + self._axes[2]
        us, _ = cast_rays(self._pinhole, ray, self.surface, self._arc)
        return us

    def local_scale(self, us_mm: np.ndarray, *, step_mm: float = 1e-4) -> np.ndarray:
        """Jacobian d(x, y)/d(u, s) in px/mm at surface points, shape (..., 2, 2) (rows x, y; columns u, s)."""
        us = np.asarray(us_mm, dtype=np.float64)
        cols = []
        for k in range(2):
            e = np.zeros(2)
            e[k] = step_mm
            cols.append((self.surface_to_image(us + e) - self.surface_to_image(us - e)) / (2 * step_mm))
        return np.stack(cols, axis=-1)


def prism_optics_for_scene(scene, **overrides) -> PrismOptics:
    """PrismOptics seeing a scene's contact surface with its camera mode and field of view.

    ``scene`` is a :class:`skinstretch.simulators.scene.Scene`; ``overrides`` set any other PrismOptics parameter (distortion,
    working distance...). Pass the result as ``optics=`` to ``SceneRenderer`` / ``render_session`` to render the
    fingertip through the prism rather than the ideal flat view.
    """
    from skinstretch.drivers.camera_modes import camera_mode

    mode = camera_mode(scene.camera.mode)
    surface = RuledSurface(
        kind=scene.surface.kind,
        width_mm=scene.surface.width_mm,
        height_mm=scene.surface.height_mm,
        center_mm=scene.surface.center_mm,
    )
    params = {"width": mode.width, "height": mode.height, "surface": surface,
              "field_width_mm": scene.camera.field_of_view_mm}
    params.update(overrides)
    return PrismOptics(**params)

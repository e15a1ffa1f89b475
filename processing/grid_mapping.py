"""The pixel <-> skin mapping a geometric calibration produces (seed 3.4): :class:`GridMapping`.

Measurements are made in mm *on the skin*, i.e. on the unrolled contact surface, not on a flat projection.
Image pixels are ``(x, y)``: x the column, y the row, origin at the centre of the top-left pixel. Surface ``(u, s)``
is in mm, unrolled: ``s`` is the arc length across the rulings of a ridge or valley, ``u`` along them. A grid only
fixes the surface frame up to a rigid motion of the unrolled plane, so the mapping's frame is defined as: origin at
the surface point seen at the image centre; ``u`` along the rulings (curved surfaces) or along the image x axis at
the centre (flat surfaces); ``s`` increasing with the image row.

A mapping is JSON-serialisable (``to_dict`` / :func:`mapping_from_dict`): session files store it that way.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from skinstretch.processing.errors import CalibrationError, InvalidInputError
from skinstretch.processing.imaging_model import ImagingModel, rotation_2d
from skinstretch.processing.validated_dataclass import FiniteFloat, PositiveFloat, PositiveInt, validated_dataclass

__all__ = ["MAPPING_KIND", "MAPPING_VERSION", "SURFACE_KINDS", "GridMapping", "RigParameters", "SurfaceFrame",
           "mapping_from_dict"]

MAPPING_KIND = "skinstretch-grid-mapping"
MAPPING_VERSION = 1
SURFACE_KINDS = ("flat", "ridge", "valley")
SurfaceKind = Literal["flat", "ridge", "valley"]
Vector3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]


@validated_dataclass
class RigParameters:
    """The fitted camera and surface (:class:`~skinstretch.processing.imaging_model.ImagingModel`'s parameters).

    ``rotvec``, ``trans``: camera pose (surface frame -> camera frame); ``focal_px``; radial distortion ``k1``, ``k2``
    about ``principal`` (px); the Gaussian profile ``amplitude_mm`` (0: flat), ``sigma_mm``, ``center_mm``; the
    cubic-spline correction of the profile, ``spline_knots`` and ``spline_coefs`` (empty when the Gaussian fits).
    """

    rotvec: Vector3
    trans: Vector3
    focal_px: PositiveFloat
    k1: FiniteFloat
    k2: FiniteFloat
    principal: tuple[FiniteFloat, FiniteFloat]
    amplitude_mm: FiniteFloat
    sigma_mm: PositiveFloat
    center_mm: FiniteFloat
    spline_knots: tuple[FiniteFloat, ...] = ()
    spline_coefs: tuple[FiniteFloat, ...] = ()

    @model_validator(mode="after")
    def _spline_sizes_agree(self) -> "RigParameters":
        if self.spline_coefs and len(self.spline_knots) != len(self.spline_coefs) + 4:
            raise InvalidInputError(
                f"spline_knots must have 4 more entries than spline_coefs, got {len(self.spline_knots)} and "
                f"{len(self.spline_coefs)}"
            )
        return self

    def model(self) -> ImagingModel:
        """The imaging model these parameters describe."""
        return ImagingModel(
            rotvec=np.asarray(self.rotvec, dtype=np.float64),
            trans=np.asarray(self.trans, dtype=np.float64),
            focal_px=self.focal_px,
            k1=self.k1,
            k2=self.k2,
            principal=np.asarray(self.principal, dtype=np.float64),
            amplitude=self.amplitude_mm,
            sigma=self.sigma_mm,
            center=self.center_mm,
            knots=self.spline_knots,
            coefs=self.spline_coefs,
        )


@validated_dataclass
class SurfaceFrame:
    """Where the mapping's output frame sits in the model's surface frame: rotation (rad) and origin (mm)."""

    angle_rad: FiniteFloat
    origin_mm: tuple[FiniteFloat, FiniteFloat]


@validated_dataclass
class GridMapping:
    """A fitted pixel <-> unrolled-surface mapping (JSON-serialisable through ``to_dict`` / ``from_dict``).

    Build it with :func:`~skinstretch.processing.geometric_calibration.calibrate_grid_images` or
    :func:`~skinstretch.processing.grid_mapping_fit.fit_grid_mapping`.
    ``surface_to_image(image_to_surface(xy)) == xy`` to ~1e-9 px. ``report`` is the fit's summary
    (:meth:`~skinstretch.processing.grid_mapping_fit.CalibrationReport.summary`).
    """

    width: PositiveInt
    height: PositiveInt
    surface: SurfaceKind
    rig: RigParameters
    frame: SurfaceFrame
    report: dict[str, Any] = Field(default_factory=dict)

    def __post_init__(self) -> None:
        # Derived state only (the fields are validated): the model, and the output frame as a matrix and a vector.
        object.__setattr__(self, "_model", self.rig.model())
        object.__setattr__(self, "_frame_rot", rotation_2d(self.frame.angle_rad))
        object.__setattr__(self, "_frame_origin", np.asarray(self.frame.origin_mm, dtype=np.float64))

    # Output frame: out = R_frame^T (us - origin), i.e. ``frame`` holds where the output frame sits in the rig frame.
    def image_to_surface(self, xy_px: np.ndarray) -> np.ndarray:
        """Unrolled surface position (u, s) in mm of image pixels (x, y); (..., 2) -> (..., 2).

        Pixels whose ray misses the surface (far outside any plausible field) raise CalibrationError.
        """
        xy = np.asarray(xy_px, dtype=np.float64)
        if xy.shape[-1:] != (2,):
            raise InvalidInputError(f"xy_px must have a trailing axis of 2, got shape {xy.shape}")
        us, ok = self._model.back_project(xy)
        if not np.all(ok):
            raise CalibrationError(f"{int(np.size(ok) - np.count_nonzero(ok))} pixel(s) do not see the surface")
        return (us - self._frame_origin) @ self._frame_rot

    def surface_to_image(self, us_mm: np.ndarray) -> np.ndarray:
        """Image pixels (x, y) of unrolled surface positions (u, s) in mm; (..., 2) -> (..., 2)."""
        us = np.asarray(us_mm, dtype=np.float64)
        if us.shape[-1:] != (2,):
            raise InvalidInputError(f"us_mm must have a trailing axis of 2, got shape {us.shape}")
        return self._model.project(us @ self._frame_rot.T + self._frame_origin)

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
        px, py = self.rig.principal
        rig = dataclasses.replace(self.rig, principal=(px - x0, py - y0))
        return dataclasses.replace(self, width=int(width), height=int(height), rig=rig,
                                   report=dict(self.report, window=[int(x0), int(y0)]))

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable description (plain floats, lists, strings)."""
        return {
            "kind": MAPPING_KIND,
            "version": MAPPING_VERSION,
            "width": int(self.width),
            "height": int(self.height),
            "surface": self.surface,
            "rig": _plain(dataclasses.asdict(self.rig)),
            "frame": _plain(dataclasses.asdict(self.frame)),
            "report": _plain(self.report),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "GridMapping":
        return mapping_from_dict(data)


def _plain(value: Any) -> Any:
    """``value`` with tuples and arrays as lists and numpy scalars as Python numbers (for JSON)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def mapping_from_dict(data: dict[str, Any]) -> GridMapping:
    """Rebuild a mapping from :meth:`GridMapping.to_dict` output; CalibrationError if it is not one."""
    if not isinstance(data, dict) or data.get("kind") != MAPPING_KIND:
        found = data.get("kind") if isinstance(data, dict) else type(data).__name__
        raise CalibrationError(f"not a skinstretch grid mapping (kind {found!r})")
    if data.get("version") != MAPPING_VERSION:
        raise CalibrationError(
            f"grid mapping version {data.get('version')!r} is not supported (reads {MAPPING_VERSION})")
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

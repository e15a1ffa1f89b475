"""The geometric-calibration step (seed 3.4, 7.2.1) shared by ``skinstretch calibrate`` and protocols.

A calibration *source* is a grid image (PNG, TIFF, anything OpenCV reads), a session file whose frames show the
grid (several frames are fitted together as a moving grid, which beats a single image: see the calibration bench),
or a calibration JSON written earlier by ``skinstretch calibrate``. The result is a
:class:`skinstretch.processing.geometric_calibration.GridMapping`; :func:`store_calibration` puts it into a session file
(the central window of a full-frame calibration for a half or strip-mode session) so the analysis measures on
the skin.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from skinstretch.drivers.camera_modes import FIELD_OF_VIEW_MM
from skinstretch.drivers.session_file import open_session, write_calibration
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.drivers.errors import SessionFileError
from skinstretch.processing.errors import CalibrationError, InvalidInputError
from skinstretch.processing.geometric_calibration import GridMapping, calibrate_grid_images, mapping_from_dict

__all__ = ["calibrate_source", "mapping_for_frames", "read_grid_images", "store_calibration"]

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def read_grid_images(source: Path, max_frames: int) -> tuple[list[np.ndarray], float | None]:
    """Grid images from an image file or a session, and the session's px/mm when there is one."""
    source = Path(source)
    if not source.exists():
        raise InvalidInputError(f"calibration source {source} does not exist")
    with open(source, "rb") as fh:
        head = fh.read(8)
    if head == _HDF5_MAGIC:
        with open_session(source) as session:
            n = session.n_frames
            if n == 0:
                raise SessionFileError(f"{source}: session has no frames")
            picks = np.unique(np.linspace(0, n - 1, min(n, max(1, max_frames))).round().astype(int))
            return [session.frame(int(k)) for k in picks], session.calibration.px_per_mm
    image = cv2.imread(str(source), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InvalidInputError(f"{source}: not an image OpenCV can read, nor a session file")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return [image], None


def calibrate_source(
    source: str | Path,
    *,
    surface: str = "auto",
    field_width_mm: float = FIELD_OF_VIEW_MM["full"],
    spacing_mm: float = 0.5,
    dot_diameter_mm: float = 0.2,
    max_frames: int = 10,
    max_rms_px: float = 0.5,
) -> tuple[GridMapping, str]:
    """The mapping of a calibration source (see the module doc) and a one-line summary of how it was obtained.

    Raises :class:`CalibrationError` when the grid cannot be trusted (too few dots, grid not found, residuals
    above ``max_rms_px``), :class:`InvalidInputError` for a source that is neither an image, a session nor a
    calibration JSON.
    """
    source = Path(source)
    if max_frames < 1:
        raise InvalidInputError(f"max_frames must be >= 1, got {max_frames}")
    if not field_width_mm > 0:
        raise InvalidInputError(f"field_width_mm must be positive, got {field_width_mm}")
    if source.suffix.lower() == ".json":
        try:
            mapping = mapping_from_dict(json.loads(source.read_text()))
        except FileNotFoundError:
            raise InvalidInputError(f"calibration source {source} does not exist") from None
        except (CalibrationError, ValueError, KeyError, TypeError) as exc:
            raise CalibrationError(f"{source}: not a calibration written by skinstretch calibrate ({exc})") from None
        return mapping, f"loaded {source} ({mapping.width}x{mapping.height}, {mapping.px_per_mm:.2f} px/mm)"
    images, session_px_per_mm = read_grid_images(source, max_frames)
    px_per_mm = session_px_per_mm or images[0].shape[1] / field_width_mm
    mapping, report = calibrate_grid_images(
        images,
        px_per_mm=px_per_mm,
        surface=surface,
        spacing_mm=spacing_mm,
        dot_diameter_mm=dot_diameter_mm,
        max_rms_px=max_rms_px,
    )
    summary = (
        f"calibrated {len(images)} image(s): {report.surface} surface, {report.n_used} dots used "
        f"({report.n_outliers} rejected), residual RMS {report.rms_px:.3f} px ({report.rms_um:.2f} um), "
        f"max {report.max_px:.3f} px, {mapping.px_per_mm:.2f} px/mm"
    )
    return mapping, summary


def mapping_for_frames(mapping: GridMapping, width: int, height: int) -> GridMapping:
    """The mapping for frames of ``width`` x ``height``: the calibration itself, or its central window.

    A half or strip mode reads the sensor's central rows (seed 3.3), so it uses that window of a full-frame
    calibration (a strip holds too few grid rows to be calibrated by itself).
    """
    if (width, height) == (mapping.width, mapping.height):
        return mapping
    if width > mapping.width or height > mapping.height:
        raise InvalidInputError(
            f"frames of {width}x{height} are larger than the {mapping.width}x{mapping.height} calibration images"
        )
    x0, y0 = (mapping.width - width) // 2, (mapping.height - height) // 2
    return mapping.for_window(x0=x0, y0=y0, width=width, height=height)


def store_calibration(session_path: str | Path, mapping: GridMapping) -> GridMapping:
    """Store ``mapping`` (or its central window, for a smaller frame) in a closed session; returns what was stored."""
    with open_session(session_path) as session:
        _, height, width = session.shape
    window = mapping_for_frames(mapping, width, height)
    write_calibration(session_path, Calibration(px_per_mm=window.px_per_mm, mapping=window))
    return window

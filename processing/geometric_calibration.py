"""Geometric calibration from images of a dot grid pressed on the contact surface (seed 3.4, improved per 7.2.1).

The seed corrects the prism's perspective and "unrolls" curved contact surfaces with a grid of dots 0.5 mm apart
printed on transparency film and pressed on the surface; measurements are then made in mm *on the skin* (arc
length along the surface), not on a flat projection. :func:`calibrate_grid_images` does it in three steps, each
in a module of its own:

1. :mod:`~skinstretch.processing.dot_grid_detection`: the dots' sub-pixel centres, then their lattice indices.
2. :mod:`~skinstretch.processing.grid_mapping_fit`: the imaging model
   (:mod:`~skinstretch.processing.imaging_model`: pinhole camera, lens distortion, flat or ridge or valley
   surface) fitted to the indexed dots of one image or of a moving grid's images jointly.
3. :mod:`~skinstretch.processing.grid_mapping`: the result, a :class:`GridMapping` (``image_to_surface``,
   ``surface_to_image``, ``px_per_mm``, ``to_dict`` / :func:`mapping_from_dict`), with a
   :class:`CalibrationReport` of residuals.

A calibration that cannot be trusted raises :class:`skinstretch.processing.errors.CalibrationError` saying why.
The names of the three steps' modules that users need are re-exported here.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from skinstretch.processing.argument_checks import positive_number
from skinstretch.processing.dot_grid_detection import INDEX_NONE, DotDetections, detect_dots, index_grid
from skinstretch.processing.errors import CalibrationError, InvalidInputError
from skinstretch.processing.grid_mapping import SURFACE_KINDS, GridMapping, mapping_from_dict
from skinstretch.processing.grid_mapping_fit import MIN_ROWS_CURVED, CalibrationReport, fit_grid_mapping

__all__ = [
    "INDEX_NONE",
    "MIN_ROWS_CURVED",
    "SURFACE_KINDS",
    "CalibrationReport",
    "DotDetections",
    "GridMapping",
    "calibrate_grid_image",
    "calibrate_grid_images",
    "detect_dots",
    "fit_grid_mapping",
    "index_grid",
    "mapping_from_dict",
]


def calibrate_grid_images(
    images: Sequence[np.ndarray],
    *,
    px_per_mm: float,
    dot_diameter_mm: float = 0.2,
    min_indexed_fraction: float = 0.5,
    **fit_options: Any,
) -> tuple[GridMapping, CalibrationReport]:
    """Calibrate from one or more images of a dot grid (moved between images, seed 7.2.1), all of one rig.

    Parameters
    ----------
    images : sequence of (H, W) arrays
        Grid images (dark dots on a bright surface), all the same size.
    px_per_mm : float
        Nominal scale along the image x axis (e.g. 640 px / 10.3 mm), for dot sizes and the starting point.
    dot_diameter_mm : float
        Dot diameter on the sheet.
    min_indexed_fraction : float
        If fewer than this fraction of the detected dots of an image fit one lattice, there is no grid in it.
    **fit_options
        Options of :func:`fit_grid_mapping`: ``surface`` ("auto", "flat", "ridge", "valley"), ``spacing_mm``,
        ``working_distance_mm``, ``max_rms_px``, ``min_dots``...

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
    px_per_mm = positive_number(px_per_mm, "px_per_mm")
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
    return fit_grid_mapping(views, image_shape=shape, dot_diameter_mm=dot_diameter_mm, n_detected=n_detected,
                            **fit_options)


def calibrate_grid_image(image: np.ndarray, *, px_per_mm: float,
                         **options: Any) -> tuple[GridMapping, CalibrationReport]:
    """Calibrate from a single grid image; options as for :func:`calibrate_grid_images`."""
    return calibrate_grid_images([image], px_per_mm=px_per_mm, **options)

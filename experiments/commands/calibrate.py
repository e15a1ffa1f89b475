"""``skinstretch calibrate``: fit the pixel-to-skin mapping from calibration-grid images (seed 3.4, 7.2.1).

Input is a grid image (PNG, TIFF, anything OpenCV reads) or a session file whose frames show the grid; several
frames of a session are fitted together as a moving grid (seed 7.2.1). The fitted mapping is written as JSON and,
with ``--apply-to``, stored in a session's ``/calibration`` group so the analysis measures on the skin.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from drivers.camera_modes import FIELD_OF_VIEW_MM
from drivers.session_file import open_session, write_calibration
from processing.calibration import Calibration
from processing.errors import InvalidInputError, SessionFileError
from processing.geometric_calibration import SURFACE_KINDS, calibrate_grid_images

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="fit the pixel-to-skin mapping from images of the 0.5 mm dot grid (seed 3.4)",
        description=__doc__,
    )
    p.add_argument("source", type=Path, help="grid image (PNG/TIFF...) or session file (.h5) showing the grid")
    p.add_argument("-o", "--output", type=Path, required=True, help="calibration JSON to write")
    p.add_argument("--apply-to", type=Path, default=None,
                   help="also store the calibration in this session file (a half/strip-mode session gets the "
                        "central window of a full-frame calibration)")
    p.add_argument("--surface", choices=("auto",) + SURFACE_KINDS, default="auto", help="surface model")
    p.add_argument("--field-width-mm", type=float, default=FIELD_OF_VIEW_MM["full"],
                   help="nominal field of view across the image width (sets the expected dot size; default 10.3)")
    p.add_argument("--spacing-mm", type=float, default=0.5, help="dot pitch of the grid (default 0.5)")
    p.add_argument("--dot-diameter-mm", type=float, default=0.2, help="dot diameter (default 0.2)")
    p.add_argument("--max-frames", type=int, default=8,
                   help="session input: at most this many frames, evenly spaced, fitted as a moving grid")
    p.add_argument("--max-rms-px", type=float, default=0.5, help="refuse a fit with a larger RMS residual")
    p.set_defaults(func=run)


def _read_images(source: Path, max_frames: int) -> tuple[list[np.ndarray], float | None]:
    """Grid images from an image file or a session, and the session's px/mm when there is one."""
    if not source.exists():
        raise InvalidInputError(f"source {source} does not exist")
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


def run(args: argparse.Namespace) -> int:
    if args.max_frames < 1:
        raise InvalidInputError(f"--max-frames must be >= 1, got {args.max_frames}")
    if not args.field_width_mm > 0:
        raise InvalidInputError(f"--field-width-mm must be positive, got {args.field_width_mm}")
    images, session_px_per_mm = _read_images(args.source, args.max_frames)
    px_per_mm = session_px_per_mm or images[0].shape[1] / args.field_width_mm
    mapping, report = calibrate_grid_images(
        images,
        px_per_mm=px_per_mm,
        surface=args.surface,
        spacing_mm=args.spacing_mm,
        dot_diameter_mm=args.dot_diameter_mm,
        max_rms_px=args.max_rms_px,
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(mapping.to_dict(), indent=2))
    print(
        f"calibrated {len(images)} image(s): {report.surface} surface, {report.n_used} dots used "
        f"({report.n_outliers} rejected), residual RMS {report.rms_px:.3f} px ({report.rms_um:.2f} um), "
        f"max {report.max_px:.3f} px, {mapping.px_per_mm:.2f} px/mm -> {args.output}",
        file=sys.stderr,
    )
    if args.apply_to is not None:
        with open_session(args.apply_to) as session:
            _, height, width = session.shape
        if (width, height) != (mapping.width, mapping.height):
            # A half or strip mode reads the sensor's central rows (seed 3.3): use that window of the full-frame
            # calibration (a strip holds too few grid rows to be calibrated by itself).
            if width > mapping.width or height > mapping.height:
                raise InvalidInputError(
                    f"{args.apply_to} has {width}x{height} frames, larger than the {mapping.width}x{mapping.height} "
                    "calibration images"
                )
            x0, y0 = (mapping.width - width) // 2, (mapping.height - height) // 2
            mapping = mapping.for_window(x0=x0, y0=y0, width=width, height=height)
            print(f"using the central {width}x{height} window (from x {x0}, y {y0}) for {args.apply_to}",
                  file=sys.stderr)
        write_calibration(args.apply_to, Calibration(px_per_mm=mapping.px_per_mm, mapping=mapping))
        print(f"stored the calibration in {args.apply_to}", file=sys.stderr)
    return 0

"""``skinstretch calibrate``: fit the pixel-to-skin mapping from calibration-grid images (seed 3.4, 7.2.1).

Input is a grid image (PNG, TIFF, anything OpenCV reads) or a session file whose frames show the grid; several
frames of a session are fitted together as a moving grid (seed 7.2.1). The fitted mapping is written as JSON and,
with ``--apply-to``, stored in a session's ``/calibration`` group so the analysis measures on the skin.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from skinstretch.drivers.camera_modes import FIELD_OF_VIEW_MM
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.grid_mapping import SURFACE_KINDS

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="fit the pixel-to-skin mapping from images of the 0.5 mm dot grid (seed 3.4)",
        description=__doc__,
    )
    p.add_argument("source", type=Path, help="grid image (PNG/TIFF...), session file (.h5) showing the grid, or a calibration JSON to apply")
    p.add_argument("-o", "--output", type=Path, required=True, help="calibration JSON to write")
    p.add_argument("--overwrite", action="store_true", help="replace an existing -o file (refused without it)")
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


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.output_paths import REPLACE_IT, check_output_file  # noqa: PLC0415
    from skinstretch.experiments.skin_mapping_step import calibrate_source, store_calibration  # noqa: PLC0415

    if args.max_frames < 1:
        raise InvalidInputError(f"--max-frames must be >= 1, got {args.max_frames}")
    for flag, value in (("--field-width-mm", args.field_width_mm), ("--spacing-mm", args.spacing_mm),
                        ("--dot-diameter-mm", args.dot_diameter_mm), ("--max-rms-px", args.max_rms_px)):
        if not value > 0:
            raise InvalidInputError(f"{flag} must be positive, got {value}")
    check_output_file(args.output, overwrite=args.overwrite, remedy=REPLACE_IT)  # before the fit
    mapping, summary = calibrate_source(
        args.source,
        surface=args.surface,
        field_width_mm=args.field_width_mm,
        spacing_mm=args.spacing_mm,
        dot_diameter_mm=args.dot_diameter_mm,
        max_frames=args.max_frames,
        max_rms_px=args.max_rms_px,
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(mapping.to_dict(), indent=2))
    log.info("%s -> %s", summary, args.output)
    if args.apply_to is not None:
        stored = store_calibration(args.apply_to, mapping)
        if stored is not mapping:
            log.info("using the central %dx%d window of the calibration for %s", stored.width, stored.height,
                     args.apply_to)
        log.info("stored the calibration in %s", args.apply_to)
    return 0

"""``skinstretch import SOURCE -o SESSION.h5``: a video, TIFF stack or folder of images into a session file."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from skinstretch.processing.errors import InvalidInputError

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import",
        help="import a video (AVI, MP4, MOV...), TIFF stack or folder of PNG/TIFF/BMP/JPEG frames as a session file",
        description="Write a normal session file (status complete) from frames recorded elsewhere, so analyze, "
        "report and view read it like a recorded one. Colour becomes BT.601 luma; 16-bit and deeper frames are "
        "mapped linearly from the whole file's range onto 8 bits. Times come from the file (video time stamps, "
        "TIFF metadata) unless --fps is given; the pixel scale from --px-per-mm, --calibration or the TIFF's "
        "metadata. See docs/import-and-replay.md.",
    )
    p.add_argument("source", help="video file, TIFF file (multi-page, OME, ImageJ), or a folder or glob pattern of "
                                   "PNG/TIFF/BMP/JPEG frames (natural order: frame2 before frame10)")
    p.add_argument("-o", "--output", type=Path, required=True, help="session file to write (.h5)")
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--px-per-mm", type=float, default=None, dest="px_per_mm", metavar="X",
                       help="pixel scale of the frames (px per mm)")
    scale.add_argument("--calibration", type=Path, default=None, metavar="CAL.json",
                       help="calibration written by skinstretch calibrate (pixel scale and skin mapping)")
    p.add_argument("--fps", type=float, default=None, metavar="F",
                   help="frame rate in Hz (replaces the file's own times; needed for a folder of images)")
    p.add_argument("--crop", default=None, metavar="X,Y,W,H", help="keep this window of the frames (pixels)")
    p.add_argument("--surface", default=None, metavar="KIND",
                   help="what the finger slid on: flat, ridge, valley... (recorded; the analysis removes the glass "
                        "shading of a surface that is not flat)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.frame_import import Crop, import_frames  # noqa: PLC0415

    calibration = None
    if args.calibration is not None:
        from skinstretch.experiments.skin_mapping_step import calibrate_source  # noqa: PLC0415

        if args.calibration.suffix.lower() != ".json":
            raise InvalidInputError(f"--calibration takes the JSON written by skinstretch calibrate, got {args.calibration}")
        calibration, _ = calibrate_source(args.calibration)
    result = import_frames(
        args.source,
        args.output,
        px_per_mm=args.px_per_mm,
        calibration=calibration,
        fps=args.fps,
        crop=Crop.parse(args.crop) if args.crop else None,
        surface=args.surface,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )
    log.info(
        "wrote %s: %d frames of %dx%d at %.4g Hz (%s), %.4g px/mm (%s), %s, in %.1f s",
        result.path, result.n_frames, result.width, result.height, result.fps, result.fps_source,
        result.px_per_mm, result.px_per_mm_source, result.conversion, result.seconds,
    )
    return 0

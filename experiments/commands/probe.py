"""``skinstretch probe OUTDIR --at X,Y [--to X2,Y2] [--radius-mm R] -o FILE.csv``: a virtual strain gauge (or, with
``--to``, an extensometer) on an analysis, one row per frame (:func:`skinstretch.experiments.probe.probe`)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from skinstretch.processing.errors import InvalidInputError

log = logging.getLogger(__name__)


def _xy(text: str) -> tuple[float, float]:
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in pixels (e.g. 120.5,88), got {text!r}") from None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("probe", help="a virtual strain gauge or extensometer on an analysis, as CSV",
                       description="Follow a skin point (X, Y in pixels of the reference frame, normally frame 0) "
                       "through every frame: its position, displacement since the reference frame and the cumulative "
                       "Green-Lagrange strain (exx, eyy, exy, e1, e2) of the points within --radius-mm of it; with "
                       "--to, the length change between two skin points.")
    p.add_argument("outdir", type=Path, metavar="OUTDIR", help="an analysis output directory (or its results.h5)")
    p.add_argument("--at", type=_xy, required=True, metavar="X,Y", help="the gauge (or the extensometer's first end)")
    p.add_argument("--to", type=_xy, default=None, metavar="X2,Y2", help="the extensometer's second end")
    p.add_argument("--radius-mm", type=float, default=None,
                   help="reach of the local affine fit (default 1.0 mm)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="FILE.csv", help="the CSV file to write")
    p.add_argument("--overwrite", action="store_true", help="replace FILE.csv if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.output_paths import REPLACE_IT, check_output_file  # noqa: PLC0415
    from skinstretch.experiments.probe import probe  # noqa: PLC0415

    check_output_file(args.output, overwrite=args.overwrite, remedy=REPLACE_IT)
    series = probe(args.outdir, at=args.at, to=args.to, radius_mm=args.radius_mm)
    series.to_csv(args.output)
    good = sum(1 for r in series.rows if r.ok)
    if good == 0:
        raise InvalidInputError(f"{args.output}: written, but no frame had enough points within "
                                f"{series.radius_px / series.px_per_mm:g} mm of the {series.kind} "
                                f"({series.rows[0].reason if series.rows else 'no frames'})")
    log.info("%s: %s over %d frames (%d measured), written", args.output, series.kind, len(series.rows), good)
    return 0

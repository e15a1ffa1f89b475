"""``skinstretch analyze SESSION.h5 -o OUTDIR [--method features|flow] [--span 1,11]``: measure skin stretch."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from skinstretch.processing.errors import InvalidInputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "analyze",
        help="measure motion, skin stretch and a tactile movie from a session file",
        description="Analyse SESSION.h5 into OUTDIR/results.h5 and OUTDIR/summary.json (docs/results-format.md): "
        "features (seed chapters 4-5, refined to sub-pixel) or the dense flow method.",
    )
    p.add_argument("session", type=Path, nargs="+",
                   help="session file (HDF5) recorded or simulated by skinstretch; several files or a directory "
                   "run a batch on Dask (skinstretch.experiments.batch.analyze_many)")
    p.add_argument("--scheduler", default=None,
                   help="batch: address of an existing Dask scheduler (default: a local cluster)")
    p.add_argument("-o", "--output", dest="outdir", type=Path, required=True, help="output directory")
    p.add_argument("--method", choices=("features", "flow"), default="features", help="measurement method")
    p.add_argument("--span", default="1,11", help="comma-separated frame spans of the strain (default 1,11)")
    p.add_argument("--min-track", type=int, default=None, help="minimum trajectory length in frames (default 30)")
    p.set_defaults(func=run)


def parse_spans(text: str) -> tuple[int, ...]:
    try:
        spans = tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        raise InvalidInputError(f"--span must be comma-separated integers, got {text!r}") from None
    if not spans or any(s < 1 for s in spans):
        raise InvalidInputError(f"--span values must be positive integers, got {text!r}")
    return spans


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from skinstretch.experiments.analysis import AnalysisParams, analyze_session  # noqa: PLC0415 - keeps --help fast

    if len(args.session) > 1 or args.session[0].is_dir():
        from skinstretch.experiments.batch import analyze_many  # noqa: PLC0415

        options = {"spans": parse_spans(args.span)}
        result = analyze_many(args.session, args.outdir, scheduler=args.scheduler, method=args.method, options=options)
        return 0 if not result.failed else 1
    args.session = args.session[0]
    params = AnalysisParams(spans=parse_spans(args.span))
    if args.min_track is not None:
        if args.min_track < 1:
            raise InvalidInputError(f"--min-track must be >= 1, got {args.min_track}")
        params = replace(params, tracking=replace(params.tracking, min_length_frames=args.min_track))
    path = analyze_session(args.session, args.outdir, method=args.method, params=params, progress=not args.quiet)
    summary = json.loads((args.outdir / "summary.json").read_text())
    t = summary["timing"]
    print(
        f"{args.method}: {summary['n_frames']} frames in {t['total_s']:.1f} s ({t['frames_per_s']:.1f} frames/s) "
        f"-> {path}",
        file=sys.stderr,
    )
    return 0

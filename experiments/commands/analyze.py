"""``skinstretch analyze SESSION.h5 -o OUTDIR [--method features|flow] [--span 1,11] [--min-track N]``: measure skin
stretch. Several sessions (or a directory) run as a batch on Dask."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from skinstretch.processing.errors import InvalidInputError

log = logging.getLogger(__name__)


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
    p.add_argument("--overwrite", action="store_true",
                   help="replace the results of an earlier analysis in the output directory (refused without it)")
    p.add_argument("--method", choices=("features", "flow"), default="features", help="measurement method")
    p.add_argument("--span", default="1,11", help="comma-separated frame spans of the strain (default 1,11)")
    p.add_argument("--min-track", type=int, default=None,
                   help="minimum trajectory length in frames (default 30, or half a clip shorter than that)")
    p.add_argument("--flow-scale", type=float, default=None, metavar="MM",
                   help="flow method: side of the registration window in mm (default 0.8): smaller resolves finer "
                   "strain, larger averages more noise")
    p.add_argument("--flow-scale-px", type=int, default=None, metavar="N",
                   help="flow method: the same in pixels (odd, >= 7), instead of --flow-scale")
    p.add_argument("--workers", type=int, default=None, help="parallel workers (default 2)")
    p.add_argument("--parallel", choices=("processes", "threads", "serial"), default=None,
                   help="how the workers run (default processes)")
    p.set_defaults(func=run)


def parse_spans(text: str) -> tuple[int, ...]:
    """The integers of ``--span``; their range is the parameters' to check (StrainParams)."""
    try:
        return tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        raise InvalidInputError(f"--span must be comma-separated integers, got {text!r}") from None


#: Analysis fields this command's flags set: a bad value is reported under the flag's name.
_FIELD_FLAGS = {
    "analysis.flow.window_mm": "--flow-scale",
    "analysis.flow.window_px": "--flow-scale-px",
    "analysis.execution.workers": "--workers",
    "analysis.execution.kind": "--parallel",
    "analysis.tracking.min_length_frames": "--min-track",
    "analysis.strain.spans": "--span",
}


def params_from_args(args: argparse.Namespace):
    """The AnalysisParams the flags ask for; a value the parameters refuse is named by its flag."""
    from skinstretch.experiments.analysis import analysis_params  # noqa: PLC0415 - keeps --help fast

    try:
        return analysis_params(options_from_args(args))
    except InvalidInputError as exc:
        text = str(exc)
        for field, flag in _FIELD_FLAGS.items():
            text = text.replace(f"{field}:", f"{flag}:")
        raise InvalidInputError(text) from None


def options_from_args(args: argparse.Namespace) -> dict:
    """The analysis options (nested by stage, as in a protocol's ``analysis.options``) the flags ask for."""
    if args.flow_scale is not None and args.flow_scale_px is not None:
        raise InvalidInputError("give --flow-scale (mm) or --flow-scale-px (pixels), not both")
    if (args.flow_scale is not None or args.flow_scale_px is not None) and args.method != "flow":
        raise InvalidInputError("--flow-scale and --flow-scale-px set the flow method's window: add --method flow")
    options: dict = {"strain": {"spans": parse_spans(args.span)}}
    if args.min_track is not None:
        options["tracking"] = {"min_length_frames": args.min_track}
    if args.flow_scale is not None:
        options["flow"] = {"window_mm": args.flow_scale}
    if args.flow_scale_px is not None:
        options["flow"] = {"window_px": args.flow_scale_px}
    execution = {k: v for k, v in (("workers", args.workers), ("kind", args.parallel)) if v is not None}
    if execution:
        options["execution"] = execution
    return options


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.analysis import analyze_session  # noqa: PLC0415 - keeps --help fast
    from skinstretch.experiments.process_lifetime import guard_process_tree  # noqa: PLC0415

    guard_process_tree()  # whatever ends this process, no worker (or Dask process) it started outlives it
    params = params_from_args(args)
    if len(args.session) > 1 or args.session[0].is_dir():
        from skinstretch.experiments.batch import analyze_many  # noqa: PLC0415

        result = analyze_many(args.session, args.outdir, scheduler=args.scheduler, method=args.method, params=params,
                              progress=not args.quiet, overwrite=args.overwrite)
        return 0 if not result.failed else 1
    r = analyze_session(args.session[0], args.outdir, method=args.method, params=params, progress=not args.quiet,
                        overwrite=args.overwrite)
    t = r.timing
    log.info("%s: %d frames in %.1f s (%.1f frames/s) -> %s", args.method, r.n_frames, t["total_s"],
             t["frames_per_s"], r.path)
    density = r.density
    if density is not None:  # a mesh too sparse to map strain was already warned about by the analysis
        log.info("density: %s%s", density.describe(), "; TOO SPARSE to map strain" if density.too_sparse else "")
    return 0

"""``skinstretch report TARGET [-o report.html]``: the self-contained HTML report of a recorded session directory,
an analysis output directory, or a session file."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write the HTML report of a data or session directory, an analysis or a "
                                      "session file",
                       description="Figures (seed chapter 6), numbers with their units, parameters and versions of "
                       "every trial of a data directory (DATADIR of skinstretch record: a study overview first), of a "
                       "session directory (DATADIR/<subject>/<session>), of an analysis output (OUTDIR of skinstretch "
                       "analyze) or of a session file; simulated trials also show measured vs true.")
    p.add_argument("target", type=Path, metavar="DATADIR|SESSION_DIR|OUTDIR|SESSION.h5",
                   help="a data or session directory written by skinstretch record, an analysis output directory, "
                        "or a session file")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="HTML file (default: report.html in the directory, or SESSION-report.html beside a file); "
                        "an existing one is overwritten: a report is regenerated from the data")
    p.add_argument("--title", default=None)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.report import build_report, report_trials  # noqa: PLC0415

    trials = report_trials(args.target)
    if args.output is not None:
        out = args.output
    elif args.target.is_dir():
        out = args.target / "report.html"
    else:
        out = args.target.with_name(f"{args.target.stem}-report.html")
    name = args.target.name if args.target.is_dir() else args.target.stem
    session_dir = args.target if args.target.is_dir() else None
    path = build_report(session_dir, out, trials=trials, title=args.title or f"skinstretch report: {name}")
    log.info("report: %s", path.resolve())
    return 0

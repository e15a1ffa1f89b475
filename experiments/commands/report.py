"""``skinstretch report SESSION_DIR [-o report.html]``: the self-contained HTML report of a recorded session."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write the HTML report of a recorded session directory",
                       description="Figures (seed chapter 6), numbers, parameters and versions of every trial of "
                       "DATADIR/<subject>/<session>; simulated trials also show measured vs true.")
    p.add_argument("session_dir", type=Path, help="a session directory written by skinstretch record")
    p.add_argument("-o", "--output", type=Path, default=None, help="HTML file (default SESSION_DIR/report.html)")
    p.add_argument("--title", default=None)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.report import build_report  # noqa: PLC0415
    from skinstretch.drivers.errors import SessionFileError  # noqa: PLC0415

    if not args.session_dir.is_dir():
        raise SessionFileError(f"{args.session_dir}: not a session directory")
    out = args.output or args.session_dir / "report.html"
    path = build_report(args.session_dir, out, title=args.title or f"skinstretch report: {args.session_dir.name}")
    print(f"report: {path.resolve()}")
    return 0

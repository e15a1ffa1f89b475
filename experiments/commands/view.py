"""``skinstretch view SESSION.h5|OUTDIR [--port P] [--no-browser] [--host H]``: the session viewer in a browser."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="look at a session and its results in a browser (frames, features, matches, strain, tactile movie)",
        description="Serve a local web page showing SESSION.h5 (or a results file, an analysis directory, a trial "
        "directory) frame by frame with its analysis overlays. Pointed at a data directory, or at a session still "
        "being recorded, it follows the newest trial with a live analysis. The page is private: it binds "
        "127.0.0.1 unless --host says otherwise, and every request needs the random token of the printed URL.",
    )
    p.add_argument("target", type=Path, help="session file, results file, analysis or trial directory, or a data "
                   "directory to follow while it is recorded")
    p.add_argument("--port", type=int, default=8765, help="TCP port (default 8765; 0 picks a free one)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only)")
    p.add_argument("--no-browser", action="store_true", help="print the URL only, do not open a browser")
    p.add_argument("--no-live", action="store_true", help="no live analysis of a session still being recorded")
    p.add_argument("--exit-with-parent", type=int, default=None, help=argparse.SUPPRESS)  # record --live
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.viewer.server import serve  # noqa: PLC0415 - keeps `skinstretch --help` fast
    from skinstretch.experiments.viewer.session_data import find_view_target  # noqa: PLC0415
    from skinstretch.processing.errors import InvalidInputError  # noqa: PLC0415

    if not 0 <= args.port <= 65535:
        raise InvalidInputError(f"--port must be in 0..65535, got {args.port}")
    target = find_view_target(args.target)
    # The URL goes to standard output, flushed: ``record --live`` starts this command and reads it from there.
    serve(target, host=args.host, port=args.port, open_browser=not args.no_browser, live=not args.no_live,
          announce=lambda line: print(line, flush=True), parent_pid=args.exit_with_parent)
    return 0

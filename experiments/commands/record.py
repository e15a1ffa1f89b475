"""``skinstretch record PROTOCOL.yaml [--rig RIG.yaml] -o DATADIR [--resume]``: run an experiment protocol.

Exit status 0 only when every trial was recorded and every analysis done; otherwise 1, and the last line says how
many of how many trials and analyses failed, and why the run stopped early if it did (a full disk). Problems found
before anything is recorded (bad protocol, unwritable output, a protocol that cannot fit on the disk) are one
line and status 2. SIGTERM, SIGHUP or Ctrl-C close the trial being recorded as aborted and end the command with
128 + the signal (143, 129, 130), its last line saying so (docs/reliability.md, "Stopped by a signal").
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from skinstretch.experiments.protocol import bundled_protocol, load_protocol, load_rig

log = logging.getLogger("skinstretch")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record",
        help="run an experiment protocol: record every trial crash-safely, analyse after each trial",
        description="Record the trials of PROTOCOL.yaml into DATADIR/<subject>/<session>/<trial>/session.h5, "
        "with an append-only event log (events.jsonl). Devices come from --rig (all simulated by default).",
    )
    p.add_argument("protocol", help="protocol YAML file (or the name of a bundled protocol, e.g. demo)")
    p.add_argument("--rig", default=None, help="rig YAML file: which devices are real (default: all simulated)")
    p.add_argument("-o", "--output", "--datadir", dest="datadir", type=Path, required=True, help="data directory")
    p.add_argument("--resume", action="store_true", help="carry on after a crash with the next unfinished trial")
    p.add_argument("--no-analysis", action="store_true", help="record only; analyse later (skinstretch analyze)")
    p.add_argument("--no-movie", action="store_true", help="do not play the protocol's tactile movie")
    p.add_argument("--live", action="store_true",
                   help="show the trial being recorded in the browser viewer, with online features and strain "
                   "(a separate process reading the session file: the recording never waits on it)")
    p.set_defaults(func=run)


def protocol_path(text: str) -> Path:
    """The protocol file ``text`` names: a file, else a bundled protocol of that name (``demo``), also when a
    folder of that name is in the way (``skinstretch demo -o demo`` makes one)."""
    path = Path(text)
    if not path.is_file() and "/" not in text and not text.endswith(".yaml"):
        return bundled_protocol(text)
    return path


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.process_lifetime import guard_process_tree, stop_on_signals  # noqa: PLC0415

    guard_process_tree()  # whatever ends this process, nothing it started outlives it
    with stop_on_signals():  # SIGTERM, SIGHUP, Ctrl-C: the trial is closed as aborted, then the command ends
        return _record(args)


def _record(args: argparse.Namespace) -> int:
    from skinstretch.experiments.runner import run_protocol  # noqa: PLC0415 - keeps `skinstretch --help` fast

    path = protocol_path(args.protocol)
    protocol = load_protocol(path)
    rig = load_rig(args.rig)
    from skinstretch.experiments.runner import session_dir  # noqa: PLC0415
    from skinstretch.experiments.viewer.live_launch import live_view  # noqa: PLC0415 - the viewer's one hook

    with live_view(session_dir(protocol, args.datadir), enabled=args.live):
        result = run_protocol(
            protocol,
            rig,
            args.datadir,
            resume=args.resume,
            analyse=False if args.no_analysis else None,
            play_movie=not args.no_movie,
            protocol_text=path.read_text(),
            rig_text=Path(args.rig).read_text() if args.rig else None,
        )
    print(f"session: {result.directory}")
    for t in result.trials:
        reason = t.reason if t.status != "not run" else ""  # the run's stop reason is on the last line
        analysis = f"; analysis FAILED: {t.analysis_error}" if t.analysis_error else ""
        print(f"  {t.trial}: {t.status}" + (f" ({reason})" if reason else "") + analysis)
    if result.playback_error:
        print(f"  playback: {result.playback_error}")
    line = result.summary_line()
    if result.ok:
        print(f"record: {line}", flush=True)
        return 0
    print(end="", flush=True)
    log.error("skinstretch record: %s", line)
    if result.interrupted is not None:  # 128 + the signal, as a shell reports a command a signal ended
        return getattr(result.interrupted, "exit_status", 130)
    return 1

"""The ``skinstretch`` command line: one subcommand per module of :mod:`skinstretch.experiments.commands`.

Every subcommand takes ``-v/--verbose`` (more log lines; twice for debugging) and ``-q/--quiet`` (warnings and errors
only, no progress bars). Library code logs through :mod:`logging`; this is the one place that configures it. Any
:class:`~skinstretch.processing.errors.SkinstretchError` ends the command with its one-line message and status 2, and
so does a usage error (an unknown flag, a value its type refuses), naming the argument. An OSError nothing caught
before (the system refused a file: a full disk, a permission) ends it with one line and status 1 (its traceback with
``-vv``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from typing import NoReturn

import skinstretch.experiments.commands as _commands
from skinstretch import __version__
from skinstretch.experiments.module_discovery import public_submodules
from skinstretch.processing.errors import SkinstretchError

log = logging.getLogger("skinstretch")


class _OneLineErrorParser(argparse.ArgumentParser):
    """A usage error in one line naming the argument, like every other error of the command line (the usage
    itself is in ``--help``)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _add_verbosity(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("output")
    group.add_argument("-v", "--verbose", action="count", default=0,
                       help="more messages (-vv: debugging detail)")
    group.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors; no progress bars")


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser of every command; with ``argv`` naming a command whose module has its name, of that one alone
    (importing every command's module costs a command seconds of start-up)."""
    parser = _OneLineErrorParser(
        prog="skinstretch",
        description="Measure fingertip skin stretch from FTIR fingerprint video and play it on a STReSS display.",
    )
    parser.add_argument("--version", action="version", version=f"skinstretch {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in _command_modules(argv):
        module.register(sub)
    for command in sub.choices.values():
        _add_verbosity(command)
        # The command's flags by parameter name, so an error's remedy names --overwrite, not overwrite=True.
        flags = {a.dest: max(a.option_strings, key=len) for a in command._actions if a.option_strings}
        command.set_defaults(cli_flags=flags)
    return parser


def _command_modules(argv: list[str] | None) -> list:
    """The module of the command ``argv`` names (its first word, when a public module of that name registers it),
    else every command's module."""
    word = next((a for a in argv or () if not a.startswith("-")), None)
    if word and word.isidentifier() and not word.startswith("_"):
        try:
            module = importlib.import_module(f"{_commands.__name__}.{word}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{_commands.__name__}.{word}":
                raise
        else:
            probe = argparse.ArgumentParser().add_subparsers()
            module.register(probe)
            if word in probe.choices:
                return [module]
    return public_submodules(_commands)


class _CurrentStderrHandler(logging.StreamHandler):
    """Writes each record to ``sys.stderr`` as it is when the record is emitted, like the standard library's
    last-resort handler: a handler bound to the stream of the moment kept writing to it after a caller (a test's
    capture, a notebook) had replaced and closed it ("I/O operation on closed file")."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # noqa: ANN201 - a text stream
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ and setStream assign it: always sys.stderr instead
        pass


def configure_logging(verbose: int = 0, quiet: bool = False) -> None:
    """Log records of skinstretch to standard error: INFO by default, DEBUG with -v -v, WARNING with --quiet."""
    level = logging.WARNING if quiet else logging.DEBUG if verbose >= 2 else logging.INFO
    fmt = "%(levelname)s %(name)s: %(message)s" if verbose else "%(message)s"
    handler = _CurrentStderrHandler()
    handler.setFormatter(logging.Formatter(fmt))
    log.handlers[:] = [handler]
    log.setLevel(level)
    log.propagate = False


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    try:
        rc = int(args.func(args) or 0)
    except SkinstretchError as exc:
        flags = getattr(args, "cli_flags", {})
        log.error("skinstretch %s: error: %s", args.command, exc.message_for(lambda p: flags.get(p, p)))
        rc = 2
    except OSError as exc:  # what the system refused (a full disk, a permission, a vanished file): one line too
        from skinstretch.experiments.output_paths import os_error_line  # noqa: PLC0415

        text = os_error_line(exc) if exc.filename else (exc.strerror or str(exc))
        log.error("skinstretch %s: error: %s", args.command, " ".join(text.split()))
        log.debug("where it happened", exc_info=True)
        rc = 1
    except KeyboardInterrupt as exc:  # Ctrl-C, or a signal a command turned into one (SIGTERM: 143)
        log.error("skinstretch %s: interrupted%s", args.command, f" ({exc.args[0]})" if exc.args else "")
        rc = getattr(exc, "exit_status", 130)
    _exit_now_if_hdf5_cannot_shut_down(rc)
    lifetime = sys.modules.get("skinstretch.experiments.process_lifetime")  # not imported: no signal handled
    if lifetime is not None and lifetime.stopped_by_signal():
        # everything it wrote is closed; the interpreter's teardown of the numerical libraries took 0.5-0.8 s
        # more, and a command asked to stop ends within a second
        _exit_now(rc)
    return rc


def _exit_now(rc: int) -> None:
    """End the process now, output flushed, without the interpreter's shutdown."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(rc)


def _exit_now_if_hdf5_cannot_shut_down(rc: int) -> None:
    """An HDF5 file the disk never let close stays open inside HDF5, which then crashes (SIGSEGV) while
    shutting down at exit: end the process here instead, output flushed (see skinstretch.drivers.disk_space)."""
    disk_space = sys.modules.get("skinstretch.drivers.disk_space")  # not imported: nothing was written
    if disk_space is not None and disk_space.unclosed_files():
        log.error("skinstretch: %d file(s) could not be closed on the full disk; exiting without HDF5's shutdown",
                  len(disk_space.unclosed_files()))
        _exit_now(rc or 1)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

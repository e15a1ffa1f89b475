"""The ``skinstretch`` command line: discovers the subcommands in :mod:`skinstretch.experiments.commands`."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from skinstretch.processing.errors import SkinstretchError

import skinstretch.experiments.commands as _commands
from skinstretch import __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="skinstretch",
        description="Measure fingertip skin stretch from FTIR fingerprint video and play it on a STReSS display.",
    )
    parser.add_argument("--version", action="version", version=f"skinstretch {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(_commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{_commands.__name__}.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except SkinstretchError as exc:
        print(f"skinstretch {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"skinstretch {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

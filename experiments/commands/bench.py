"""``skinstretch bench``: run the benchmark sections and print speed-against-error tables.

The tables are the command's output (standard output); progress and failures are logged. ``--markdown FILE``
also writes the whole run as a Markdown document (``docs/benchmarks.md`` is written this way) with the date, the
machine and the command line; ``--json FILE`` writes the tables as data.
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import skinstretch.experiments.bench as _bench
from skinstretch.experiments.bench import BenchOptions, SectionResult, markdown_document
from skinstretch.experiments.json_encoding import json_default, json_safe
from skinstretch.experiments.module_discovery import public_submodules
from skinstretch.experiments.provenance import machine_description
from skinstretch.processing.errors import InvalidInputError

if TYPE_CHECKING:
    from skinstretch.simulators.star_pattern import StarPair

log = logging.getLogger(__name__)


def available_sections() -> dict[str, object]:
    return {module.SECTION: module for module in public_submodules(_bench)}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmarks: speed against error, as tables")
    p.add_argument("--only", default="", help="comma-separated sections to run (default: all); see --list")
    p.add_argument("--list", action="store_true", help="list the sections and exit")
    p.add_argument("--quick", action="store_true", help="short runs (a few seconds per section)")
    p.add_argument("--scenes", default="", help="comma-separated scene names for the sections that use scenes")
    p.add_argument("--seconds", type=float, default=None, help="duration of streaming benchmarks")
    p.add_argument("--star-images", nargs=2, type=Path, default=None, metavar=("REF", "DEF"),
                   help="the star section scores these two images (e.g. the DIC Challenge 2.0 Star pair, 4000 x 501 "
                        "px, 8 or 16 bit) instead of star pairs of its own")
    p.add_argument("--workdir", type=Path, default=Path("bench-output"), help="scratch directory")
    p.add_argument("--json", type=Path, default=None,
                   help="also write all tables to this JSON file (overwritten if it exists)")
    p.add_argument("--markdown", type=Path, default=None, metavar="FILE",
                   help="also write every table with its notes, the date, the machine and this command line as "
                        "Markdown to FILE ('-': standard output instead of the plain tables), e.g. docs/benchmarks.md; "
                        "overwritten if it exists")
    p.set_defaults(func=run)


def command_line(args: argparse.Namespace) -> str:
    """The ``skinstretch bench`` command line that reproduces this run (options in a fixed order)."""
    words = ["skinstretch", "bench"]
    if args.only:
        words += ["--only", args.only]
    if args.quick:
        words.append("--quick")
    if args.scenes:
        words += ["--scenes", args.scenes]
    if args.seconds is not None:
        words += ["--seconds", f"{args.seconds:g}"]
    if args.star_images is not None:
        words += ["--star-images", *map(str, args.star_images)]
    if args.markdown is not None:
        words += ["--markdown", str(args.markdown)]
    return shlex.join(words)


def star_images(ref: Path, deformed: Path) -> tuple[str, "StarPair"]:
    """The two images of ``--star-images`` as a star pair (8-bit grey; 16-bit data by ``skinstretch flow``'s rule),
    checked against the star layout; with their description for the table."""
    from skinstretch.experiments.commands.flow import read_grey, to_8bit_pair  # noqa: PLC0415
    from skinstretch.experiments.evaluation.star import star_pair_from_images  # noqa: PLC0415

    a, b = to_8bit_pair(read_grey(ref), read_grey(deformed))
    source = f"{ref.name} -> {deformed.name}"
    return source, star_pair_from_images(a, b, source=source)


class _FirstTimeOnly(logging.Filter):
    """Passes a log message the first time only: a section renders and analyses many clips, and each would say the
    same thing again (a print's dpi, a short clip's minimum trajectory length)."""

    def __init__(self) -> None:
        super().__init__()
        self._seen: set[tuple[str, str]] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        key = (record.name, record.getMessage())
        if key in self._seen:
            return False
        self._seen.add(key)
        return True


def run(args: argparse.Namespace) -> int:
    if not getattr(args, "verbose", 0):
        for handler in logging.getLogger("skinstretch").handlers:
            handler.addFilter(_FirstTimeOnly())
    sections = available_sections()
    if args.list:
        for name, module in sections.items():
            print(f"{name:12s} {module.DESCRIPTION}")
        return 0
    wanted = [s for s in args.only.split(",") if s] or list(sections)
    unknown = [s for s in wanted if s not in sections]
    if unknown:
        raise InvalidInputError(f"unknown bench sections {unknown}; known: {sorted(sections)}")
    to_stdout_as_markdown = args.markdown is not None and str(args.markdown) == "-"
    options = BenchOptions(
        quick=args.quick,
        workdir=args.workdir,
        scenes=[s for s in args.scenes.split(",") if s] or None,
        seconds=args.seconds,
    )
    if args.star_images is not None:  # read and checked before any section runs: one line naming the file
        if "star" not in wanted:
            raise InvalidInputError("--star-images is for the star section: add --only star")
        options.extra["star_images"] = star_images(*args.star_images)
    options.workdir.mkdir(parents=True, exist_ok=True)
    date = time.strftime("%Y-%m-%d %H:%M %Z")
    machine = machine_description()
    results: list[SectionResult] = []
    for name in wanted:
        t0 = time.perf_counter()
        description = sections[name].DESCRIPTION
        log.info("running bench section %s", name)
        try:
            tables = sections[name].run(options)
        except Exception as exc:  # a broken section is reported, the others still run
            log.error("section %s failed: %s: %s", name, type(exc).__name__, exc)
            results.append(SectionResult(name, description, [], time.perf_counter() - t0,
                                         error=f"{type(exc).__name__}: {exc}"))
            continue
        seconds = time.perf_counter() - t0
        results.append(SectionResult(name, description, tables, seconds))
        if not to_stdout_as_markdown:
            print(f"== {name}: {description}\n")
            for table in tables:
                print(table.format() + "\n", flush=True)
        log.info("(%s took %.1f s)", name, seconds)
    if args.json:
        everything = {r.name: [t.to_dict() for t in r.tables] for r in results if r.error is None}
        args.json.write_text(json.dumps(json_safe(everything), indent=2, default=json_default))
    if args.markdown is not None:
        text = markdown_document(results, command=command_line(args), date=date, machine=machine, quick=args.quick)
        if to_stdout_as_markdown:
            sys.stdout.write(text)
        else:
            args.markdown.parent.mkdir(parents=True, exist_ok=True)
            args.markdown.write_text(text)
            log.info("wrote %s", args.markdown)
    return 1 if any(r.error is not None for r in results) else 0

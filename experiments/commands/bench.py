"""``skinstretch bench``: run the benchmark sections and print speed-against-error tables."""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import sys
import time
from pathlib import Path

import skinstretch.experiments.bench as _bench
from skinstretch.experiments.bench import BenchOptions
from skinstretch.experiments.module_discovery import public_submodules


def available_sections() -> dict[str, object]:
    return {module.SECTION: module for module in public_submodules(_bench)}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmarks: speed against error, as tables")
    p.add_argument("--only", default="", help="comma-separated sections to run (default: all); see --list")
    p.add_argument("--list", action="store_true", help="list the sections and exit")
    p.add_argument("--quick", action="store_true", help="short runs (a few seconds per section)")
    p.add_argument("--scenes", default="", help="comma-separated scene names for the sections that use scenes")
    p.add_argument("--seconds", type=float, default=None, help="duration of streaming benchmarks")
    p.add_argument("--workdir", type=Path, default=Path("bench-output"), help="scratch directory")
    p.add_argument("--json", type=Path, default=None, help="also write all tables to this JSON file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    sections = available_sections()
    if args.list:
        for name, module in sections.items():
            print(f"{name:12s} {module.DESCRIPTION}")
        return 0
    wanted = [s for s in args.only.split(",") if s] or list(sections)
    unknown = [s for s in wanted if s not in sections]
    if unknown:
        print(f"unknown bench sections {unknown}; known: {sorted(sections)}", file=sys.stderr)
        return 2
    options = BenchOptions(
        quick=args.quick,
        workdir=args.workdir,
        scenes=[s for s in args.scenes.split(",") if s] or None,
        seconds=args.seconds,
    )
    options.workdir.mkdir(parents=True, exist_ok=True)
    everything = {}
    failed = False
    for name in wanted:
        t0 = time.perf_counter()
        print(f"== {name}: {sections[name].DESCRIPTION}", flush=True)
        try:
            tables = sections[name].run(options)
        except Exception as exc:  # a broken section is reported, the others still run
            failed = True
            print(f"  section {name} failed: {type(exc).__name__}: {exc}\n", flush=True)
            continue
        for table in tables:
            print(table.format() + "\n", flush=True)
        everything[name] = [t.to_dict() for t in tables]
        print(f"  ({name} took {time.perf_counter() - t0:.1f} s)\n", flush=True)
    if args.json:
        args.json.write_text(json.dumps(everything, indent=2))
    return 1 if failed else 0

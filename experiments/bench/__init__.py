"""Benchmarks: one module per section, each defining ``SECTION`` (a short name), ``DESCRIPTION`` and
``run(options: BenchOptions) -> list[BenchTable]``. ``skinstretch bench`` discovers them and prints the tables;
``--markdown`` also writes them as one Markdown document (:func:`markdown_document`, ``docs/benchmarks.md``).

Benchmarks always report speed *and* error against ground truth side by side.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from skinstretch.experiments.number_format import format_number


@dataclass
class BenchOptions:
    """What every section is given: a quick flag (CI-sized runs), a scratch directory, scenes to use."""

    quick: bool = False
    workdir: Path = Path("bench-output")
    scenes: Sequence[str] | None = None
    seconds: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class BenchTable:
    """A table of results: ``rows`` are sequences aligned with ``columns``; ``notes`` print under it."""

    title: str
    columns: Sequence[str]
    rows: list[Sequence[Any]]
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """Title, columns, rows and notes (write it with :func:`skinstretch.experiments.json_encoding.json_default`
        and ``json_safe``: rows hold numpy numbers and NaN)."""
        return {"title": self.title, "columns": list(self.columns), "rows": [list(r) for r in self.rows],
                "notes": list(self.notes)}

    def format(self) -> str:
        cells = [[str(c) for c in self.columns]] + [[format_number(v) for v in row] for row in self.rows]
        widths = [max(len(r[i]) for r in cells) for i in range(len(self.columns))]
        line = "  ".join("-" * w for w in widths)
        out = [self.title, line]
        for k, row in enumerate(cells):
            out.append("  ".join(c.rjust(w) if k else c.ljust(w) for c, w in zip(row, widths)))
            if k == 0:
                out.append(line)
        out.extend(f"  {n}" for n in self.notes)
        return "\n".join(out)

    def markdown(self) -> str:
        """The table in Markdown (GitHub pipe table): its title in bold, then the table, then its notes."""
        def cell(value: Any) -> str:
            return format_number(value).replace("|", "\\|")

        out = [f"**{self.title}**", "", "| " + " | ".join(cell(c) for c in self.columns) + " |",
               "|" + "|".join("---" for _ in self.columns) + "|"]
        out.extend("| " + " | ".join(cell(v) for v in row) + " |" for row in self.rows)
        if self.notes:
            out.append("")
            out.extend(f"- {note}" for note in self.notes)
        return "\n".join(out)


@dataclass
class SectionResult:
    """What one section of a run gave: its tables, how long it took, or why it failed."""

    name: str
    description: str
    tables: list[BenchTable]
    seconds: float
    error: str | None = None


def markdown_document(results: Sequence[SectionResult], *, command: str, date: str, machine: Mapping[str, str],
                      quick: bool) -> str:
    """A whole bench run as a Markdown document: when, on what machine, by which command; every table with its
    notes, section by section."""
    lines = [
        "# Benchmarks: speed against error",
        "",
        f"Written by `{command}` on {date}. Do not edit by hand: run the command again.",
        "",
        f"Machine: {machine.get('cores', '?')} cores, {machine.get('cpu', '?')}, {machine.get('python', '?')}, "
        f"{machine.get('platform', '?')}; load average {machine.get('load average', '?')} (1 / 5 / 15 min) at the "
        "start.",
        "",
        "Errors are against the simulators' exact ground truth and do not depend on the machine (fixed seeds). "
        "Speeds do: they were measured on this machine as loaded at the time.",
    ]
    if quick:
        lines += ["", "**This is a quick run** (`--quick`): shorter sequences, fewer frames and seeds than a full "
                  "run, so its numbers are rougher; a full run (without `--quick`) gives the reference figures."]
    for result in results:
        lines += ["", f"## {result.name}: {result.description}", ""]
        if result.error is not None:
            lines.append(f"The section failed: {result.error}")
            continue
        for table in result.tables:
            lines += [table.markdown(), ""]
        lines.append(f"(`{result.name}` took {result.seconds:.1f} s)")
    return "\n".join(lines) + "\n"

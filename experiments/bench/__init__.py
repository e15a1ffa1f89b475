"""Benchmarks: one module per section, each defining ``SECTION`` (a short name), ``DESCRIPTION`` and
``run(options: BenchOptions) -> list[BenchTable]``. ``skinstretch bench`` discovers them and prints the tables.

Benchmarks always report speed *and* error against ground truth side by side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

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
        return {
            "title": self.title,
            "columns": list(self.columns),
            "rows": [[_jsonable(v) for v in row] for row in self.rows],
            "notes": list(self.notes),
        }

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


def _jsonable(v: Any) -> Any:
    if isinstance(v, float) and (math.isnan(v) or math.isinf(v)):
        return None
    if hasattr(v, "item"):
        return v.item()
    return v

"""The overview of a study: every trial of a data directory (``skinstretch record`` writes
``DATADIR/<subject>/<session>/<trial>/session.h5`` with its ``analysis/``), one row each, for the viewer's study page
and the report.

A row says who and what (subject, protocol, surface, scene), how the recording and its analysis went (status,
method), a few key numbers (frames, fingertip travel, edge-length change p5/p95 over one frame, the median
cumulative principal strains at the last frame) and the warnings the analysis gave (its summary's notes, a mesh too
sparse, its ``warnings`` when the results carry them). A trial that cannot be read is a row saying why, never a
missing row.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from skinstretch.drivers.errors import SessionFileError
from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.results_file import read_results

log = logging.getLogger(__name__)

__all__ = ["StudyTrial", "study_overview", "study_sessions"]

_SESSION_FILE, _ANALYSIS_DIR, _RESULTS_FILE = "session.h5", "analysis", "results.h5"


@dataclass
class StudyTrial:
    """One trial of a study (module doc). Strains are fractions; ``profile`` is seed Figure 94's (mm, fraction)."""

    name: str  # the trial's folder, relative to the data directory
    session: Path
    analysis: Path | None
    subject: str = "?"
    protocol: str = ""
    surface: str = "?"
    scene: str = ""
    status: str = "?"
    method: str = ""
    n_frames: int = 0
    travel_mm: float = math.nan
    edge_change_p5: float = math.nan
    edge_change_p95: float = math.nan
    cumulative_e1: float = math.nan  # median over the last frame's cumulative triangles
    cumulative_e2: float = math.nan
    warnings: list[str] = field(default_factory=list)
    profile: tuple[np.ndarray, np.ndarray] | None = None

    def to_json(self) -> dict[str, Any]:
        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "name": self.name, "subject": self.subject, "protocol": self.protocol, "surface": self.surface,
            "scene": self.scene, "status": self.status, "method": self.method, "n_frames": self.n_frames,
            "travel_mm": num(self.travel_mm), "edge_change_p5": num(self.edge_change_p5),
            "edge_change_p95": num(self.edge_change_p95), "cumulative_e1": num(self.cumulative_e1),
            "cumulative_e2": num(self.cumulative_e2), "warnings": list(self.warnings),
            "profile": None if self.profile is None else {
                "position_mm": [round(float(v), 4) for v in self.profile[0]],
                "change": [None if not math.isfinite(v) else round(float(v), 7) for v in self.profile[1]]},
        }


def study_sessions(directory: str | Path) -> list[Path]:
    """Every trial's session file under ``directory``, in path order (the study's rows)."""
    return sorted(q for q in Path(directory).rglob(_SESSION_FILE) if q.is_file())


def study_overview(directory: str | Path) -> list[StudyTrial]:
    """One :class:`StudyTrial` per session file under ``directory`` (:func:`study_sessions`)."""
    directory = Path(directory)
    return [_trial(directory, s) for s in study_sessions(directory)]


def _name(value: Any, key: str) -> str:
    if isinstance(value, dict):
        value = value.get(key)
    return str(value) if value else "?"


def _trial(directory: Path, session: Path) -> StudyTrial:
    results = session.parent / _ANALYSIS_DIR / _RESULTS_FILE
    t = StudyTrial(str(session.parent.relative_to(directory)), session, results.parent if results.exists() else None)
    try:
        with open_session(session) as s:
            md = s.metadata
            t.subject, t.surface = _name(md.get("subject"), "id"), _name(md.get("surface"), "kind")
            t.protocol, t.scene = str(md.get("protocol", "")), str(md.get("scene", ""))
            t.status = s.status + (f" ({s.status_reason})" if s.status_reason else "")
            t.n_frames = int(s.n_frames)
    except SessionFileError as exc:
        t.status = "unreadable"
        t.warnings.append(str(exc))
        return t
    if t.analysis is None:
        t.warnings.append("not analysed")
        return t
    try:
        r = read_results(results)
    except SessionFileError as exc:
        t.warnings.append(f"results not readable: {exc}")
        return t
    t.method = r.method
    t.travel_mm = float(np.hypot(*np.ptp(r.fingertip_position, axis=0))) / r.px_per_mm
    p5_p95 = (r.summary.get("strain_span_1") or {}).get("edge_change_p5_p95")
    if p5_p95:
        t.edge_change_p5, t.edge_change_p95 = (float(v) for v in p5_p95)
    t.warnings += [str(n) for n in r.summary.get("notes") or []]
    t.warnings += [str(w) for w in r.summary.get("warnings") or []]
    density = r.density
    if density is not None and density.warning and density.warning not in t.warnings:
        t.warnings.append(density.warning)
    flagged = sum(1 for f in r.frame_flags if f)
    if flagged:
        t.warnings.append(f"{flagged} of {r.n_frames} frames flagged (no finger, saturated...)")
    c = r.cumulative
    if c is not None and c.pairs.size:
        last = c.triangles[(c.triangles["pair"] == c.pairs.size - 1) & ~c.triangles["flipped"]
                           & (c.triangles["tensor_status"] == 0)]
        if last.size:
            t.cumulative_e1, t.cumulative_e2 = float(np.median(last["e1"])), float(np.median(last["e2"]))
    t.profile = (r.profile_position / r.px_per_mm, np.where(r.profile_valid, r.profile_change, np.nan))
    return t

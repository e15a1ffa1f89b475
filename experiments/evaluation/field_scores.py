"""An analysis scored from its results file alone against a known field, point by point and edge by edge.

The truth is anything with ``between(points, frame_a, frame_b) -> (displacement, known)`` (a simulated session's
:class:`~skinstretch.experiments.evaluation.tracking.TruthField`, a moved print's
:class:`~skinstretch.simulators.moved_print.ExactField`). Every row the analysis wrote is scored, whatever its
pair's status: the displacement of each point of the ``motion`` table (consecutive pairs) and the length change of
each Delaunay edge of the strain tables, moved by the true field. Where the results carry an uncertainty (``motion``
column ``sigma``, px, 1-sigma per axis; edge column ``change_sigma``, the unit of ``change``), the coverage of its
95 % interval is the fraction of points whose error vector lies within 2.448 sigma (the 95 % radius of an isotropic
2-D normal) and of edges whose error lies within 1.96 ``change_sigma``; without the column it is None.

The verdict (:func:`verdict`): *accurate* within both targets; otherwise *flagged* when the analysis said so (a
pair not ``ok``, or a ``warnings`` entry in summary.json); otherwise *silently wrong* when an error is over three
times its target, or was not measured at all; *inaccurate* in between.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from skinstretch.experiments.results_file import SUMMARY_FILE, PairStatus, Results

__all__ = ["KnownField", "FieldScores", "score_results", "score_analysis", "verdict", "DISPLACEMENT_TARGET_PX",
           "EDGE_STRAIN_TARGET_PCT", "SILENT_FACTOR"]

#: Targets of issue 38: displacement RMSE (px) and 11-frame edge strain RMSE (%).
DISPLACEMENT_TARGET_PX = 0.05
EDGE_STRAIN_TARGET_PCT = 0.2
#: An error this many times its target, unflagged, is silently wrong.
SILENT_FACTOR = 3.0
_POINT_95 = math.sqrt(-2.0 * math.log(0.05))  # 2.448: P(|e| <= r sigma) = 0.95 for an isotropic 2-D normal
_EDGE_95 = 1.96


class KnownField(Protocol):
    def between(self, points: np.ndarray, frame_a: int, frame_b: int) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class FieldScores:
    """Errors of one analysis against the truth (NaN: nothing measured), and what it said about itself.

    Attributes
    ----------
    points : int
        Points of consecutive pairs scored.
    displacement_rmse_px, displacement_p99_px, displacement_max_px : float
        Of the error vectors' lengths.
    edge_rmse_pct : dict[int, float]
        Edge length change error, RMS, per span (percentage points).
    edges : dict[int, int]
        Edges scored per span.
    point_coverage, edge_coverage : float or None
        Fraction inside the reported 95 % interval (edges: the longest span); None when the results carry no
        uncertainty.
    pairs_not_ok : int
        Rows of the pair tables (consecutive and every span) whose status is not ``ok``.
    warnings : int
        Entries of summary.json's ``warnings`` list.
    predicted_rmse_px : float or None
        The displacement RMSE the reported sigmas predict (``sqrt(2) sigma`` per point, RMS over the points with a
        finite sigma), beside ``displacement_rmse_px``; None without uncertainty.
    """

    points: int
    displacement_rmse_px: float
    displacement_p99_px: float
    displacement_max_px: float
    edge_rmse_pct: dict[int, float]
    edges: dict[int, int]
    point_coverage: float | None
    edge_coverage: float | None
    pairs_not_ok: int
    warnings: int
    predicted_rmse_px: float | None = None

    @property
    def flagged(self) -> bool:
        return self.pairs_not_ok > 0 or self.warnings > 0


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(a)))) if a.size else math.nan


def _column(table: np.ndarray, name: str) -> np.ndarray | None:
    return table[name] if table.dtype.names and name in table.dtype.names else None


def _point_errors(r: Results, truth: KnownField) -> np.ndarray:
    """(rows, 2) error vectors of the motion table's rows (NaN where the truth is not known)."""
    rows, pairs = r.motion, r.motion_pairs
    err = np.full((rows.size, 2), np.nan)
    for i in np.unique(rows["pair"]):
        sel = np.flatnonzero(rows["pair"] == i)
        pts = np.column_stack([rows["x"][sel], rows["y"][sel]])
        d, known = truth.between(pts, int(pairs["frame_a"][i]), int(pairs["frame_b"][i]))
        e = np.column_stack([rows["dx"][sel], rows["dy"][sel]]) - d
        e[~known] = np.nan
        err[sel] = e
    return err


def _edge_errors(edges: np.ndarray, pairs: np.ndarray, truth: KnownField) -> np.ndarray:
    """Per edge: measured minus true length change (a fraction; NaN where the truth is not known)."""
    err = np.full(edges.size, np.nan)
    for i in np.unique(edges["pair"]):
        sel = np.flatnonzero(edges["pair"] == i)
        fa, fb = int(pairs["frame_a"][i]), int(pairs["frame_b"][i])
        pa = np.column_stack([edges["xa"][sel], edges["ya"][sel]])
        pb = np.column_stack([edges["xb"][sel], edges["yb"][sel]])
        (da, ka), (db, kb) = truth.between(pa, fa, fb), truth.between(pb, fa, fb)
        true_change = np.hypot(*((pb + db) - (pa + da)).T) / np.hypot(*(pb - pa).T) - 1.0
        err[sel] = np.where(ka & kb, edges["change"][sel] - true_change, np.nan)
    return err


def score_results(outdir: str | Path, truth: KnownField) -> FieldScores:
    """Score the analysis in ``outdir`` (results.h5 and summary.json) against ``truth`` (module doc)."""
    from skinstretch.experiments.results_file import read_results  # noqa: PLC0415

    outdir = Path(outdir)
    return score_analysis(read_results(outdir), json.loads((outdir / SUMMARY_FILE).read_text()), truth)


def score_analysis(r: Results, summary: dict, truth: KnownField) -> FieldScores:
    """Score opened results ``r`` (its ``motion``, ``motion_pairs`` and ``strain`` tables) and their ``summary``
    against ``truth``."""
    e = _point_errors(r, truth)
    known = np.all(np.isfinite(e), axis=1)
    length = np.hypot(e[known, 0], e[known, 1])
    sigma = _column(r.motion, "sigma")
    point_coverage = float(np.mean(length <= _POINT_95 * sigma[known])) if sigma is not None and length.size else None
    finite = sigma[known][np.isfinite(sigma[known])] if sigma is not None else np.zeros(0)
    predicted = float(np.sqrt(2.0 * np.mean(finite**2))) if finite.size else None
    not_ok = int(np.count_nonzero(r.motion_pairs["status"] != PairStatus.OK))
    edge_rmse, n_edges, edge_coverage = {}, {}, None
    for span, s in sorted(r.strain.items()):
        not_ok += int(np.count_nonzero(s.pairs["status"] != PairStatus.OK))
        err = _edge_errors(s.edges, s.pairs, truth)
        ok = np.isfinite(err)
        edge_rmse[span], n_edges[span] = _rms(100.0 * err[ok]), int(ok.sum())
        change_sigma = _column(s.edges, "change_sigma")
        if change_sigma is not None and ok.any():  # the longest span's, the last one
            edge_coverage = float(np.mean(np.abs(err[ok]) <= _EDGE_95 * change_sigma[ok]))
    return FieldScores(
        points=int(length.size), displacement_rmse_px=_rms(length),
        displacement_p99_px=float(np.percentile(length, 99)) if length.size else math.nan,
        displacement_max_px=float(length.max()) if length.size else math.nan,
        edge_rmse_pct=edge_rmse, edges=n_edges, point_coverage=point_coverage, edge_coverage=edge_coverage,
        pairs_not_ok=not_ok, warnings=len(summary.get("warnings") or []), predicted_rmse_px=predicted,
    )


def verdict(displacement_px: float, edge_strain_pct: float, *, flagged: bool,
            displacement_target_px: float = DISPLACEMENT_TARGET_PX,
            edge_strain_target_pct: float = EDGE_STRAIN_TARGET_PCT) -> str:
    """"accurate", "flagged", "silently wrong" or "inaccurate" (module doc); a NaN error (nothing measured) is
    beyond every target."""
    def within(value: float, limit: float) -> bool:
        return bool(np.isfinite(value) and value <= limit)

    if within(displacement_px, displacement_target_px) and within(edge_strain_pct, edge_strain_target_pct):
        return "accurate"
    if flagged:
        return "flagged"
    if not (within(displacement_px, SILENT_FACTOR * displacement_target_px)
            and within(edge_strain_pct, SILENT_FACTOR * edge_strain_target_pct)):
        return "silently wrong"
    return "inaccurate"

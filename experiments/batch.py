"""Analyse many sessions at once on a Dask cluster, and summarise them across subjects and surfaces.

The seed analysed one sequence at a time and suggested that "averaging measurements over a large number of image
sequences could also reduce the noise and expose the effect of shapes" (seed 7.2.4). :func:`analyze_many` runs
:func:`skinstretch.experiments.runner.analyse_trial` on every session as a Dask task — on a local cluster by default, or on
an existing one (``scheduler="tcp://host:8786"``) — and a session that fails is reported in the table without
stopping the others. The summary table has one row per session (subject, surface, status, timing, strain
percentiles) and Figure 94 is averaged over the sessions of each surface.

Outputs in ``outdir``: ``<subject>/<session>/<trial>/`` results per session, ``batch.json`` and ``batch.csv``
(the table), ``figure94.png`` (the stretch profiles averaged per surface).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from skinstretch.drivers.errors import SessionFileError
from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.analysis.parameters import AnalysisParams, analysis_params
from skinstretch.experiments.output_paths import check_output_dir
from skinstretch.experiments.results_file import held_results, refuse_held_results
from skinstretch.experiments.runner import TrialAnalysis, analyse_trial
from skinstretch.processing.errors import InvalidInputError, SkinstretchError
from skinstretch.progress import logging_above_bars, progress_bar

log = logging.getLogger(__name__)

__all__ = ["BatchRow", "BatchResult", "analyze_many", "find_sessions", "average_profiles"]


@dataclass
class BatchRow:
    """One session of a batch: where it came from, what it is, how its analysis went."""

    session: str
    subject: str
    surface: str
    scene: str
    status: str  # ok | failed
    error: str = ""
    results: str = ""
    seconds: float = math.nan
    n_frames: int = 0
    edge_change_p5: float = math.nan
    edge_change_p95: float = math.nan
    profile_axis: str = ""
    n_trajectories: int | None = None  # features method
    min_track_frames: int | None = None  # features method: the minimum trajectory length used
    #: What the analysis said about the clip (a short clip's adapted minimum length, a span with no pair, a shape's
    #: glass-fixed shading left in, a mesh too sparse to map strain): one sentence each, joined by " | ".
    notes: str = ""

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class BatchResult:
    rows: list[BatchRow]
    outdir: Path
    table_csv: Path
    table_json: Path
    figure: Path | None
    profiles: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, int]] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def failed(self) -> list[BatchRow]:
        return [r for r in self.rows if r.status != "ok"]


def find_sessions(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Session files named directly, or found (``*.h5`` holding a session) under directories, in sorted order."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            for f in sorted(p.rglob("*.h5")):
                if f.name == "results.h5" or "playback" in f.parts:
                    continue
                out.append(f)
        elif p.exists():
            out.append(p)
        else:
            raise InvalidInputError(f"paths: {p} does not exist")
    if not out:
        raise InvalidInputError(f"paths: no session file found in {[str(p) for p in paths]}")
    return list(dict.fromkeys(out))


def _describe(path: Path) -> dict[str, str]:
    try:
        with open_session(path) as s:
            md = s.metadata
            subject = md.get("subject", {})
            subject = subject.get("id", "?") if isinstance(subject, dict) else str(subject)
            surface = md.get("surface", {})
            surface = surface.get("kind", "?") if isinstance(surface, dict) else str(surface)
            return {"subject": subject or "?", "surface": surface or "?", "scene": str(md.get("scene", ""))}
    except SessionFileError:
        return {"subject": "?", "surface": "?", "scene": ""}


def _task(session: str, outdir: str, method: str, params, overwrite: bool) -> TrialAnalysis:
    """One Dask task: analyse on the threads of that worker (no pool of its own); a failure is a value, the batch
    goes on."""
    return analyse_trial(session, outdir, method, params, overwrite=overwrite)


def _out_dir(outdir: Path, session: Path, roots: Sequence[Path]) -> Path:
    for root in roots:
        try:
            rel = session.relative_to(root)
            return outdir / rel.with_suffix("")
        except ValueError:
            continue
    return outdir / session.stem


def average_profiles(profiles: Sequence[tuple[np.ndarray, np.ndarray]], *, step_mm: float = 0.25):
    """Average (x_mm, change) profiles of several sessions on a common grid (NaN-aware).

    Returns (x, mean, std, n) with ``n`` the number of sessions contributing at each position.
    """
    if not profiles:
        raise InvalidInputError("profiles: nothing to average")
    lo = min(float(np.nanmin(x)) for x, _ in profiles)
    hi = max(float(np.nanmax(x)) for x, _ in profiles)
    grid = np.arange(lo, hi + step_mm / 2, step_mm)
    stack = np.full((len(profiles), grid.size), np.nan)
    for i, (x, ch) in enumerate(profiles):
        x = np.asarray(x, float)
        ch = np.asarray(ch, float)
        ok = np.isfinite(ch)
        if ok.sum() >= 2:
            inside = (grid >= x[ok].min()) & (grid <= x[ok].max())
            stack[i, inside] = np.interp(grid[inside], x[ok], ch[ok])
    n = np.sum(np.isfinite(stack), axis=0)
    mean = np.full(grid.size, np.nan)
    std = np.full(grid.size, np.nan)
    has = n > 0
    mean[has] = np.nanmean(stack[:, has], axis=0)
    std[has] = np.nanstd(stack[:, has], axis=0)
    return grid, mean, std, n


def _client(scheduler: str | None):
    """(client, cluster) for ``scheduler``: None = a new local cluster, an address = an existing cluster."""
    from dask.distributed import Client, LocalCluster  # noqa: PLC0415

    if scheduler is None:
        n = max(1, min(4, os.cpu_count() or 1))
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None)
        return Client(cluster), cluster
    return Client(scheduler), None


def analyze_many(
    paths: Iterable[str | os.PathLike],
    outdir: str | os.PathLike,
    *,
    scheduler: str | None = None,
    method: str = "features",
    params: AnalysisParams | dict[str, Any] | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> BatchResult:
    """Analyse every session of ``paths`` (files or directories) into ``outdir``; summarise across sessions.

    Parameters
    ----------
    paths : iterable of path-like
        Session files, or directories searched recursively for them.
    outdir : path-like
        Where results, the table and the averaged Figure 94 go.
    scheduler : str, optional
        None: a Dask local cluster of worker processes; an address (``tcp://host:8786``): that cluster;
        ``"synchronous"``: no cluster, one session after the other in this process (small batches, tests).
    method : {"features", "flow"}
        Analysis method.
    params : AnalysisParams or dict, optional
        The analysis' parameters (a dict is validated as :class:`AnalysisParams` options). Each session is one
        task that analyses on the threads of its Dask worker: the batch's parallelism is the cluster's.
    progress : bool
        A progress bar over the sessions (with a local or an external scheduler alike); each session's outcome is
        also logged.
    overwrite : bool
        Replace the results of an earlier batch in ``outdir``; without it, an ``outdir`` holding any (a session's
        results, or the batch table) is refused before anything is analysed.
    """
    if method not in ("features", "flow"):
        raise InvalidInputError(f"method must be 'features' or 'flow', got {method!r}")
    params = analysis_params(params)
    # A session is one task, measured on the threads of the worker that runs it.
    params = params.model_copy(update={"execution": params.execution.model_copy(update={"kind": "threads"})})
    t0 = time.perf_counter()
    sessions = find_sessions(paths)
    roots = [Path(p) for p in paths if Path(p).is_dir()]
    outdir = check_output_dir(outdir)
    jobs = [(s, _out_dir(outdir, s, roots)) for s in sessions]
    held = [p for p in (outdir / "batch.json", outdir / "batch.csv") if p.exists()]
    held += [p for _, o in jobs for p in held_results(o)]
    refuse_held_results(outdir, held, overwrite=overwrite)
    outdir.mkdir(parents=True, exist_ok=True)
    log.info("batch: %d sessions, method %s, scheduler %s", len(jobs), method, scheduler or "local cluster")
    outcomes: list[TrialAnalysis | None] = [None] * len(jobs)
    bar = progress_bar(len(jobs), enabled=progress, desc="sessions", unit="session")

    def done(k: int, out: TrialAnalysis) -> None:
        outcomes[k] = out
        bar.update(1)
        log.info("batch: %s: %s", jobs[k][0], "ok" if out.ok else "FAILED " + out.error)

    with logging_above_bars(progress):  # the per-session lines above the bar, not through it
        try:
            if scheduler == "synchronous":
                for k, (s, o) in enumerate(jobs):
                    done(k, _task(str(s), str(o), method, params, overwrite))
            else:
                from dask.distributed import as_completed  # noqa: PLC0415

                client, cluster = _client(scheduler)
                try:
                    futures = {client.submit(_task, str(s), str(o), method, params, overwrite, pure=False): k
                               for k, (s, o) in enumerate(jobs)}
                    for fut in as_completed(futures):
                        k = futures[fut]
                        try:
                            out = fut.result()
                        except Exception as exc:  # a worker died: this session failed, the others go on
                            out = TrialAnalysis(False, error=f"{type(exc).__name__}: {exc}")
                        done(k, out)
                finally:
                    client.close()
                    if cluster is not None:
                        cluster.close()
        finally:
            bar.close()
    rows = []
    by_surface: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for (session, _), out in zip(jobs, outcomes):
        row = BatchRow(session=str(session), status="ok" if out.ok else "failed", error=out.error,
                       **_describe(session))
        if out.ok:
            row.results = out.results
            row.seconds = float(out.seconds)
            try:
                _fill(row, by_surface)
            except (SkinstretchError, OSError, KeyError, ValueError) as exc:
                row.status, row.error = "failed", f"results unreadable: {type(exc).__name__}: {exc}"
        rows.append(row)
    table_json = outdir / "batch.json"
    table_csv = outdir / "batch.csv"
    table_json.write_text(json.dumps([{k: _nan_none(v) for k, v in r.as_dict().items()} for r in rows], indent=1))
    with open(table_csv, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(BatchRow.__dataclass_fields__))
        w.writeheader()
        for r in rows:
            w.writerow(r.as_dict())
    averaged = {surface: average_profiles(profs) for surface, profs in sorted(by_surface.items()) if profs}
    figure = None
    if averaged:
        from skinstretch.experiments.figures.chapter6 import stretch_profile_figure  # noqa: PLC0415

        fig = stretch_profile_figure(
            {f"{s} (n={len(by_surface[s])})": (x, m) for s, (x, m, sd, n) in averaged.items()},
            band={f"{s} (n={len(by_surface[s])})": (m - sd, m + sd) for s, (x, m, sd, n) in averaged.items()},
            title="Relative change in stretch with position, averaged over sessions per surface (seed Figure 94)",
        )
        figure = outdir / "figure94.png"
        fig.savefig(figure, dpi=90, bbox_inches="tight")
    result = BatchResult(rows, outdir, table_csv, table_json, figure, averaged, time.perf_counter() - t0)
    log.info("batch: %d/%d sessions analysed in %.1f s; table %s", len(rows) - len(result.failed), len(rows),
             result.seconds, table_csv)
    for r in result.failed:
        log.warning("batch: FAILED %s: %s", r.session, r.error)
    return result


def _fill(row: BatchRow, by_surface: dict[str, list]) -> None:
    from skinstretch.experiments.results_file import read_results  # noqa: PLC0415

    r = read_results(row.results)
    row.n_frames = r.n_frames
    row.profile_axis = r.profile_axis
    row.n_trajectories = r.summary.get("n_trajectories")
    row.min_track_frames = r.summary.get("min_track_frames")
    notes = list(r.summary.get("notes") or [])
    sparse = (r.summary.get("density") or {}).get("warning")
    if sparse:
        notes.append(sparse)
    row.notes = " | ".join(notes)
    p5_p95 = r.summary.get("strain_span_1", {}).get("edge_change_p5_p95")
    if p5_p95:
        row.edge_change_p5, row.edge_change_p95 = (float(v) for v in p5_p95)
    change = np.where(r.profile.valid, r.profile.change, np.nan)
    if np.any(np.isfinite(change)):
        by_surface.setdefault(row.surface, []).append((r.profile.x / r.px_per_mm, change))


def _nan_none(v):
    """JSON has no NaN: missing numbers are null."""
    if isinstance(v, float) and math.isnan(v):
        return None
    return v

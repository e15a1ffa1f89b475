"""A self-contained HTML report of a recorded (or simulated) session: figures as base64 PNG, numbers, parameters,
versions, and — for simulated sessions — the measurements against the simulator's ground truth.

:func:`build_report` takes a session directory written by :mod:`skinstretch.experiments.runner` (trials with their
``session.h5`` and ``analysis/results.h5``, the event log, ``playback/``) and writes one HTML file with no
external resource. A part that cannot be drawn says why in the report instead of vanishing (STYLE: failures are
values).
"""

from __future__ import annotations

import base64
import html
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from skinstretch.experiments.number_format import format_number
from skinstretch.experiments.provenance import software_versions
from skinstretch.drivers.session_file import open_session
from skinstretch.processing.errors import SkinstretchError
from skinstretch.experiments.figures import chapter6 as fig6

log = logging.getLogger(__name__)

__all__ = ["Quantity", "TrialEntry", "build_report", "collect_trials", "evaluation_quantities", "report_trials",
           "trial_figures", "viewer_command"]


@dataclass
class TrialEntry:
    """One trial to report: its session file and (optionally) its analysis results directory."""

    name: str
    session: Path
    analysis: Path | None = None
    summary: dict[str, Any] = field(default_factory=dict)


def collect_trials(session_dir: str | Path) -> list[TrialEntry]:
    """Every trial of a runner's session directory, in order, with the stop summary of the event log."""
    from skinstretch.experiments.runner import ANALYSIS_DIR, EVENT_LOG, SESSION_FILE, finished_trials, read_events  # noqa: PLC0415

    sdir = Path(session_dir)
    stops = finished_trials(read_events(sdir / EVENT_LOG))
    out = []
    for d in sorted(p for p in sdir.iterdir() if p.is_dir() and (p / SESSION_FILE).exists()):
        res = d / ANALYSIS_DIR
        out.append(
            TrialEntry(
                name=d.name,
                session=d / SESSION_FILE,
                analysis=res if (res / "results.h5").exists() else None,
                summary=dict(stops.get(d.name, {}).get("summary", {})),
            )
        )
    return out


def report_trials(target: str | Path) -> list[TrialEntry]:
    """The trials a report of ``target`` shows: a runner's session directory (every trial), a data directory
    (every trial of every subject and session under it), an analysis output directory of ``skinstretch analyze``
    (its ``results.h5`` names the session), or a single session file."""
    from skinstretch.drivers.errors import SessionFileError  # noqa: PLC0415
    from skinstretch.experiments.results_file import read_results  # noqa: PLC0415

    target = Path(target)
    if target.is_dir() and (target / "results.h5").is_file():
        session = Path(read_results(target).session_path)
        if not session.is_file():
            raise SessionFileError(f"{target}/results.h5 names the session {session}, which does not exist")
        return [TrialEntry(name=session.stem, session=session, analysis=target)]
    if target.is_dir():
        trials = collect_trials(target)
        if not trials:  # a data directory: every trial of every subject and session under it
            from skinstretch.experiments.study import study_sessions  # noqa: PLC0415

            trials = [TrialEntry(name=str(s.parent.relative_to(target)), session=s,
                                 analysis=s.parent / "analysis" if (s.parent / "analysis" / "results.h5").exists()
                                 else None) for s in study_sessions(target)]
        if not trials:
            raise SessionFileError(f"{target}: neither a data or session directory of skinstretch record (no trial "
                                   "holds a session.h5) nor an analysis output (no results.h5)")
        return trials
    if target.is_file():
        open_session(target).close()  # a readable session, or an error saying why not
        return [TrialEntry(name=target.stem, session=target)]
    raise SessionFileError(f"{target}: no such session file or directory")


# ------------------------------------------------------------------------------------------------ html bits


def _esc(x: Any) -> str:
    return html.escape(str(x))


def _anchor(name: str) -> str:
    """The HTML id of a trial's section (the study overview links to it)."""
    return "trial-" + "".join(ch if ch.isalnum() or ch in "-_" else "-" for ch in name)


def _num(v: Any) -> str:
    return _esc(format_number(v))


def _table(rows: Sequence[Sequence[Any]], header: Sequence[str]) -> str:
    head = "".join(f"<th>{_esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_num(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _kv(d: dict[str, Any]) -> str:
    return _table([(k, v) for k, v in d.items()], ["quantity", "value"])


def _img(fig, caption: str) -> str:
    data = base64.b64encode(fig6.figure_to_png(fig)).decode("ascii")
    return (f'<figure><img alt="{_esc(caption)}" src="data:image/png;base64,{data}"/>'
            f"<figcaption>{_esc(caption)}</figcaption></figure>")


def _guard(what: str, fn: Callable[[], str]) -> str:
    """Run one report part; one that cannot be drawn (nothing to show) becomes a visible note naming the part and
    why; a fault of ours is logged with its traceback and named as such, never shown as the figure."""
    try:
        return fn()
    except (SkinstretchError, ValueError, KeyError) as exc:
        reason = str(exc).strip("'")  # a KeyError quotes its text
        return f'<p class="warn">{_esc(what)}: not shown: {_esc(reason)}</p>'
    except (IndexError, OSError):
        log.exception("report part %r could not be drawn", what)
        return f'<p class="warn">{_esc(what)}: not shown: it could not be drawn (the log has the details)</p>'


_CSS = """
body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
h1{font-size:1.5em} h2{border-bottom:1px solid #ccc;font-size:1.25em;margin-top:2em} h3{font-size:1.05em}
table{border-collapse:collapse;margin:.5em 0;font-size:.85em} td,th{border:1px solid #ccc;padding:2px 8px}
th{background:#f3f3f3} td{text-align:right} td:first-child{text-align:left}
figure{margin:1em 0} img{max-width:100%} figcaption{font-size:.85em;color:#555}
.warn{color:#a40} .ok{color:#070} pre{background:#f7f7f7;padding:.5em;font-size:.8em;overflow-x:auto}
"""


# ------------------------------------------------------------------------------------ numbers with units


@dataclass(frozen=True)
class Quantity:
    """A number as the report shows it: what it is, its value in ``unit``, the unit."""

    label: str
    value: Any
    unit: str


def _position_pair(label: str, px: float, px_per_mm: float) -> list[Quantity]:
    """A position error in px and in um on the skin (px / px_per_mm)."""
    um = px / px_per_mm * 1000.0 if isinstance(px, (int, float)) and px_per_mm > 0 else float("nan")
    return [Quantity(label, px, "px"), Quantity(label, um, "um")]


def evaluation_quantities(ev: dict[str, Any], px_per_mm: float) -> dict[str, Quantity]:
    """Every number of an evaluation against the truth (``evaluate_tracking``), in its unit: positions in px and
    um, strains and rates in %. Keyed ``part.name`` (``.um`` for the um twin); the report's tables all read them
    from here, so a number shown twice is the same number."""
    out: dict[str, Quantity] = {}
    for part, values in ev.items():
        if not isinstance(values, dict):
            continue
        for key, v in values.items():
            name = f"{part}.{key}"
            words = key.replace("_", " ")
            if key.endswith("_px"):
                px, um = _position_pair(f"{part}: {words[:-3]}", v, px_per_mm)
                out[name], out[name + ".um"] = px, um
            elif key.startswith(("edge_rmse_", "area_rmse_")):
                span = key.rsplit("_", 1)[1]
                what = "edge" if key.startswith("edge") else "area"
                out[name] = Quantity(f"{part}: {what} strain RMSE, span {span}", _percent(v), "%")
            elif key.endswith("_rate") or key.endswith("amplitude"):
                out[name] = Quantity(f"{part}: {words}", _percent(v), "%")
            elif key.endswith("_frames"):
                out[name] = Quantity(f"{part}: {words[:-7]}", v, "frames")
            else:
                out[name] = Quantity(f"{part}: {words}", v, "")
    return out


def _percent(v: Any) -> Any:
    return v * 100.0 if isinstance(v, (int, float)) and not isinstance(v, bool) else v


def _quantity_table(quantities: Iterable[Quantity]) -> str:
    return _table([(q.label, q.value, q.unit) for q in quantities], ["quantity", "value", "unit"])


#: The columns of the summary of every simulated trial (keys of :func:`evaluation_quantities`).
_SUMMARY_KEYS = (
    ("tracking.displacement_rmse_px", "displacement RMSE (px)"),
    ("tracking.displacement_rmse_px.um", "displacement RMSE (um)"),
    ("tracking.wrong_match_rate", "wrong matches (%)"),
    ("strain.edge_rmse_1", "edge strain RMSE span 1 (%)"),
    ("strain.edge_rmse_11", "edge strain RMSE span 11 (%)"),
    ("profile.correlation", "profile correlation"),
)


def viewer_command(entry: "TrialEntry") -> str:
    """The command that opens a trial in the browser viewer (its analysis when there is one)."""
    target = entry.analysis if entry.analysis is not None else entry.session
    return f"skinstretch view {target}"


# --------------------------------------------------------------------------------------------- from results


def _points_edges(edges_tab: np.ndarray, tri_tab: np.ndarray):
    """Rebuild (points, edge index pairs, triangle index triples) from the flat tables of one pair."""
    ids = np.concatenate([edges_tab["id_a"], edges_tab["id_b"], tri_tab["id_a"], tri_tab["id_b"], tri_tab["id_c"]])
    xs = np.concatenate([edges_tab["xa"], edges_tab["xb"], tri_tab["x0"], tri_tab["x1"], tri_tab["x2"]])
    ys = np.concatenate([edges_tab["ya"], edges_tab["yb"], tri_tab["y0"], tri_tab["y1"], tri_tab["y2"]])
    uid, first = np.unique(ids, return_index=True)
    points = np.column_stack([xs[first], ys[first]])
    row = {int(i): k for k, i in enumerate(uid)}
    edges = np.array([[row[int(a)], row[int(b)]] for a, b in zip(edges_tab["id_a"], edges_tab["id_b"])], int)
    tris = np.array([[row[int(a)], row[int(b)], row[int(c)]]
                     for a, b, c in zip(tri_tab["id_a"], tri_tab["id_b"], tri_tab["id_c"])], int)
    return points, edges.reshape(-1, 2), tris.reshape(-1, 3), row


def _chained_motion(r, frame_a: int, frame_b: int) -> dict[int, np.ndarray]:
    """id -> (x, y, dx, dy) from frame a to b, summing consecutive motions of ids present in every pair."""
    acc: dict[int, np.ndarray] | None = None
    for k in range(frame_a, frame_b):
        sel = r.motion[r.motion["pair"] == k]
        cur = {int(i): np.array([x, y, dx, dy]) for i, x, y, dx, dy in
               zip(sel["id"], sel["x"], sel["y"], sel["dx"], sel["dy"])}
        if acc is None:
            acc = cur
        else:
            acc = {i: np.array([v[0], v[1], v[2] + cur[i][2], v[3] + cur[i][3]]) for i, v in acc.items() if i in cur}
    return acc or {}


def _patch_change(r, frame_a: int, frame_b: int, *, spacing_mm: float = 1.0, radius_mm: float = 1.0):
    """Skin-patch area change (seed 5.3.2, Figure 61) on a 1 mm grid from the chained feature motion."""
    from skinstretch.processing.stretch import local_movement, patch_area_change  # noqa: PLC0415
    from skinstretch.processing.tracking import MotionSample  # noqa: PLC0415

    mot = _chained_motion(r, frame_a, frame_b)
    if len(mot) < 4:
        return None, None
    arr = np.array(list(mot.values()))
    sample = MotionSample(frame_a, frame_b, arr[:, :2], arr[:, 2:], np.array(list(mot.keys()), np.int64))
    ft = np.nansum(r.fingertip_displacement[frame_a:frame_b], axis=0)
    h, w = r.image_shape
    step = spacing_mm * r.px_per_mm
    gx = np.arange(step / 2, w, step)
    gy = np.arange(step / 2, h, step)
    centers = np.stack(np.meshgrid(gx, gy), axis=-1)
    lm = local_movement(sample, fingertip_displacement=ft, centers=centers, radius_px=radius_mm * r.px_per_mm)
    change, _ = patch_area_change(lm.centers, lm.movement, lm.valid)
    return centers, change


def _triangulated_pairs(r, span: int):
    """The strain at ``span`` and the indices of its frame pairs that gave a triangulation."""
    s = r.strain.get(span)
    if s is None:
        raise KeyError(f"no strain at span {span}")
    ok = np.nonzero(s.ok)[0]
    if ok.size == 0:
        raise ValueError(f"no frame pair at span {span} gave a triangulation the self-checks trust")
    return s, ok


def _measurement_panel(r, session, span: int, *, shape_x_px=None) -> str:
    s, ok = _triangulated_pairs(r, span)
    k = int(ok[ok.size // 2])
    fa, fb = int(s.pairs["frame_a"][k]), int(s.pairs["frame_b"][k])
    e = s.edges[s.edges["pair"] == k]
    t = s.triangles[s.triangles["pair"] == k]
    points, edges, tris, row = _points_edges(e, t)
    mot = _chained_motion(r, fa, fb)
    pa = np.array([points[row[i]] for i in mot if i in row]).reshape(-1, 2)
    pb = np.array([points[row[i]] + mot[i][2:] for i in mot if i in row]).reshape(-1, 2)
    if pa.size == 0 and mot:
        arr = np.array(list(mot.values()))
        pa, pb = arr[:, :2], arr[:, :2] + arr[:, 2:]
    centers, change = _patch_change(r, fa, fb)
    fig = fig6.measurements_figure(
        session.frame(fa), session.frame(fb), index_a=fa, index_b=fb, points_a=pa, points_b=pb, edges=edges,
        edge_change=e["change"], triangles=tris, area_change=t["change"], flipped=t["flipped"],
        patch_centers=centers, patch_change=change, shape_x_px=shape_x_px,
    )
    return _img(fig, f"Measurements from frame {fa} to {fb} (span {span}), as seed Figures 76-93; each map's "
                     "colours are scaled to its data (blue = compression, red = stretch, colorbars in %)")


def _edge_series(r, span: int) -> str:
    s, ok = _triangulated_pairs(r, span)
    picks = ok[np.linspace(0, ok.size - 1, min(6, ok.size)).round().astype(int)]
    panels = []
    for k in dict.fromkeys(int(p) for p in picks):
        e = s.edges[s.edges["pair"] == k]
        t = s.triangles[s.triangles["pair"] == k]
        points, edges, _, _ = _points_edges(e, t)
        panels.append({"points": points, "edges": edges, "edge_change": e["change"],
                       "frame_a": s.pairs["frame_a"][k], "frame_b": s.pairs["frame_b"][k]})
    fig = fig6.edge_change_series_figure(panels, shape=r.image_shape)
    return _img(fig, f"Edge length change over {span} frames at several positions (as seed Figures 78, 81...), "
                     "on one colour scale fitted to them")


def _tensor_maps(r) -> str:
    """The strain tensor maps of up to four frames: the cumulative strain from the reference frame when the results
    hold it, else the longest span's."""
    from skinstretch.experiments.results_file import TENSOR_COLUMNS  # noqa: PLC0415

    c = r.cumulative
    if c is not None and c.pairs.size and "exx" in (c.triangles.dtype.names or ()):
        table, what = c, f"cumulative from frame {c.reference_frame}"
    else:
        span = max(r.strain)
        table, what = r.strain[span], f"over {span} frames"
        if "exx" not in (table.triangles.dtype.names or ()):
            raise KeyError("results written before the strain tensor was measured")
    with_tri = np.unique(table.triangles["pair"][table.triangles["tensor_status"] == 0])
    if with_tri.size == 0:
        raise ValueError(f"no triangle with a strain tensor ({what})")
    picks = dict.fromkeys(int(with_tri[i]) for i in np.linspace(0, with_tri.size - 1, min(4, with_tri.size))
                          .round().astype(int))
    panels = []
    for k in picks:
        t = table.triangles[(table.triangles["pair"] == k) & (table.triangles["tensor_status"] == 0)]
        corners = np.stack([np.column_stack([t[f"x{j}"], t[f"y{j}"]]) for j in range(3)], axis=1)
        panel = {"corners": corners, "flipped": t["flipped"],
                 "label": f"frames {int(table.pairs['frame_a'][k])}-{int(table.pairs['frame_b'][k])}"}
        panel.update({q: t[q] for q in TENSOR_COLUMNS if q != "angle_deg"})
        panels.append(panel)
    fig = fig6.tensor_maps_figure(panels, shape=r.image_shape)
    return _img(fig, f"Strain tensor maps ({what}): Green-Lagrange exx, eyy, exy (tensor shear, half the engineering "
                     "shear) and the principal strains e1 >= e2 of each triangle, drawn where its corners were in the "
                     "first frame of its pair; one colour scale per quantity across its frames")


def trial_figures(entry: TrialEntry, *, truth_eval: bool = True) -> tuple[str, dict[str, Any]]:
    """HTML of one trial and the numbers other sections reuse (profile, evaluation, movie)."""
    from skinstretch.experiments.results_file import read_results  # noqa: PLC0415

    parts = [f'<h2 id="{_anchor(entry.name)}">Trial {_esc(entry.name)}</h2>']
    info: dict[str, Any] = {"name": entry.name}
    with open_session(entry.session) as session:
        md = session.metadata
        surface = md.get("surface")  # a protocol's {"kind": ...} or a simulated scene's name
        info["surface"] = (surface.get("kind") if isinstance(surface, dict) else surface) or "?"
        info["scene"] = md.get("scene", "")
        rec = {
            "status": session.status + (f" ({session.status_reason})" if session.status_reason else ""),
            "frames": session.n_frames,
            "camera mode": f"{session.camera_mode.name} {session.camera_mode.width}x{session.camera_mode.height}"
                           f" @{session.camera_mode.fps:g} Hz",
            "px per mm": session.calibration.px_per_mm,
            "surface": json.dumps(md.get("surface", {})),
            "instructions": md.get("instructions", ""),
            "simulated (has truth)": session.has_truth,
        }
        rec.update({k: v for k, v in entry.summary.items() if k in ("dropped_frames", "mean_fps", "bytes",
                                                                     "normal_force_mean_n", "normal_force_max_n")})
        parts.append(f'<p class="viewer">Step through this trial frame by frame, with its features, matches and '
                     f"strain: <code>{_esc(viewer_command(entry))}</code></p>")
        parts.append("<h3>Recording</h3>" + _kv(rec))
        if entry.analysis is None:
            parts.append('<p class="warn">No analysis results for this trial.</p>')
            return "\n".join(parts), info
        r = read_results(entry.analysis)
        info["results"] = r
        travel = np.ptp(r.fingertip_position, axis=0)
        summary = [
            Quantity("method", r.method, ""),
            Quantity("frames flagged", sum(1 for f in r.frame_flags if f), "frames"),
            Quantity("analysis time", r.timing.get("total_s", float("nan")), "s"),
            Quantity("analysis speed", r.timing.get("frames_per_s", float("nan")), "frames/s"),
            Quantity("fingertip travel (x, y)", travel.tolist(), "px"),
            Quantity("fingertip travel (x, y)", (travel / r.px_per_mm).tolist(), "mm"),
            Quantity("profile axis (sliding direction)", r.profile_axis, ""),
        ]
        if r.trajectories is not None:
            lengths = r.trajectories.lengths
            summary.append(Quantity("trajectories", int(lengths.size), ""))
            summary.append(Quantity("median trajectory length", float(np.median(lengths)) if lengths.size else 0.0,
                                    "frames"))
        for span, st in sorted(r.strain.items()):
            e = st.edges["change"]
            summary.append(Quantity(f"edge length change p5 / p95, span {span}",
                                    (np.percentile(e, [5, 95]) * 100).tolist() if e.size else "none", "%"))
        for name, spread in (r.summary.get("uncertainty") or {}).items():
            if spread:  # each measurement's predicted standard error (median / 95th percentile)
                percent = name.startswith("edge_change")
                summary.append(Quantity(name.replace("_", " ") + " (median / p95)",
                                        [spread["median"] * (100 if percent else 1),
                                         spread["p95"] * (100 if percent else 1)], "%" if percent else "px"))
        warnings = r.summary.get("warnings") or []
        info["warnings"] = list(warnings)
        if warnings:  # the self-checks that failed: read before any number below
            parts.append('<div class="warn"><strong>Warnings</strong><ul>'
                         + "".join(f"<li>{_esc(w)}</li>" for w in warnings) + "</ul></div>")
        parts.append("<h3>Analysis</h3>" + _quantity_table(summary))
        notes = r.summary.get("notes") or []
        if notes:  # what the analysis said about the whole clip: the caveats of every number below
            parts.append('<div class="warn"><strong>Analysis notes</strong><ul>'
                         + "".join(f"<li>{_esc(n)}</li>" for n in notes) + "</ul></div>")
        from skinstretch.experiments.analysis.plan import plan_rows  # noqa: PLC0415

        plan = plan_rows(r.summary.get("plan") or {})
        if plan:  # the choices the analysis made for this surface and clip, and any parameter not applied as asked
            parts.append("<h3>Analysis plan</h3>" + _table(plan, ["choice", "value"]))
        parts.append(_guard("measurements over 1 frame", lambda: _measurement_panel(r, session, 1)))
        span_long = max(r.strain) if r.strain else 11
        parts.append(_guard(f"measurements over {span_long} frames",
                            lambda: _measurement_panel(r, session, span_long)))
        parts.append(_guard("edge length series", lambda: _edge_series(r, span_long)))
        parts.append(_guard("strain tensor maps", lambda: _tensor_maps(r)))
        if r.trajectories is not None:
            parts.append(_guard("trajectory lengths", lambda: _img(
                fig6.trajectory_length_figure(r.trajectories.lengths, n_frames=r.n_frames),
                "Trajectory length distribution (as seed Figure 70)")))
        scale = 1.0 / r.px_per_mm
        info["profile"] = (r.profile_position * scale, np.where(r.profile_valid, r.profile_change, np.nan))
        from skinstretch.experiments.evaluation.tracking import measured_profile_pattern  # noqa: PLC0415

        pattern = measured_profile_pattern(r)  # the amplitude the evaluation table shows, for the figure title
        info["profile_amplitude"] = pattern.amplitude if pattern is not None else math.nan
        if session.has_truth and truth_eval:
            parts.append(_guard("measured vs true", lambda: _truth_section(r, session, info)))
        if r.tactile_positions_um is not None:
            info["movie"] = r
    return "\n".join(parts), info


def _truth_section(r, session, info: dict[str, Any]) -> str:
    from skinstretch.experiments.evaluation.tracking import TruthField, evaluate_tracking, profile_correlation  # noqa: PLC0415

    truth = session.truth
    ev = evaluate_tracking(r, truth)
    info["evaluation"] = ev
    strip = float(r.params["strain"]["profile_strip_mm"]) * r.px_per_mm
    _, true_change = profile_correlation(r, TruthField(truth), strip_px=strip)
    info["true_profile"] = (r.profile_position / r.px_per_mm, np.asarray(true_change, float))
    quantities = evaluation_quantities({k: ev[k] for k in ("tracking", "strain", "profile") if k in ev},
                                       r.px_per_mm)
    info["evaluation_quantities"] = quantities
    return "<h3>Measured vs true (simulated session)</h3>" + _quantity_table(quantities.values())


# -------------------------------------------------------------------------------------------------- report


def _study_section(trials: Sequence[Any]) -> str:
    """The study overview (:mod:`skinstretch.experiments.study`): one row per trial linking to its section, and the
    trials' Figure-94 profiles on one plot, coloured by surface."""
    def pct(v: float) -> Any:
        return v * 100 if math.isfinite(v) else "-"

    head = ["trial", "subject", "protocol", "surface", "status", "method", "frames", "travel (mm)",
            "edge change p5 (%)", "p95 (%)", "cumulative e1 (%)", "e2 (%)", "warnings"]
    body = []
    for t in trials:
        cells = [t.subject, t.protocol, t.surface, t.status, t.method or "-", t.n_frames,
                 t.travel_mm if math.isfinite(t.travel_mm) else "-", pct(t.edge_change_p5), pct(t.edge_change_p95),
                 pct(t.cumulative_e1), pct(t.cumulative_e2)]
        warn = "; ".join(t.warnings)
        body.append(f'<tr><td><a href="#{_anchor(t.name)}">{_esc(t.name)}</a></td>'
                    + "".join(f"<td>{_num(c)}</td>" for c in cells)
                    + f'<td class="{"warn" if warn else ""}" style="text-align:left">{_esc(warn) or "-"}</td></tr>')
    table = ("<table><thead><tr>" + "".join(f"<th>{_esc(h)}</th>" for h in head) + "</tr></thead><tbody>"
             + "".join(body) + "</tbody></table>")
    out = ["<h2>Study overview</h2>",
           "<p>One row per trial (click a name for its section). Edge change: between consecutive frames; "
           "cumulative e1, e2: median principal strains of the last frame relative to the reference frame.</p>",
           table]
    groups: dict[str, list[tuple[str, np.ndarray, np.ndarray]]] = {}
    for t in trials:
        if t.profile is not None:
            groups.setdefault(t.surface, []).append((t.name, *t.profile))
    if groups:
        out.append(_guard("study profiles", lambda: _img(
            fig6.grouped_profiles_figure(groups), "Stretch along the sliding direction of every trial (seed Figure "
                                                  "94), one colour per surface")))
    return "\n".join(out)


def _movie_section(r, name: str) -> str:
    pos = r.tactile_positions_um
    n = pos.shape[0]
    frames = sorted(set(np.linspace(0, n - 1, min(6, n)).round().astype(int).tolist()))
    out = [f"<h2>Tactile movie from {_esc(name)} (seed 5.4, 6.4)</h2>",
           _kv({"frames": n, "contactors reset (fraction)": float(np.mean(r.tactile_reset)),
                "clipped (fraction)": float(np.mean(r.tactile_clipped)),
                "position range (um)": [float(np.min(pos)), float(np.max(pos))]})]
    out[1] = _quantity_table([
        Quantity("frames", n, ""),
        Quantity("contactors reset", float(np.mean(r.tactile_reset)) * 100, "%"),
        Quantity("contactors clipped", float(np.mean(r.tactile_clipped)) * 100, "%"),
        Quantity("position range", [float(np.min(pos)), float(np.max(pos))], "um"),
    ])
    out.append(_img(fig6.contactor_positions_figure(pos, frames=frames, reset=r.tactile_reset),
                    "Contactor positions (as seed Figure 96)"))
    out.append(_img(fig6.stretch_fields_figure(r.tactile_stretch_change, frames=frames),
                    "Stretch fields applied by the display (as seed Figure 97)"))
    return "\n".join(out)


def _playback_section(playbacks: Sequence[Any]) -> str:
    rows = []
    runs = {}
    for pb in playbacks:
        label = "closed loop" if pb.closed_loop else "open loop"
        trace = fig6.PlaybackTrace.of(pb)  # the one RMS error of the run, shown by the table and the figure
        rows.append((label, pb.frames_played, pb.frames_total, trace.settle, trace.rms_error_um, pb.late_frames,
                     pb.stopped or "-", pb.rested))
        runs[label] = trace
    out = ["<h2>Playback on the display</h2>",
           _table(rows, ["run", "frames played", "frames", "start-up frames (not in the error)", "RMS error (um)",
                         "late frames", "stopped", "at rest"])]
    if len(playbacks) == 2 and all(p.rms_error_um > 0 for p in playbacks):
        o = [t for label, t in runs.items() if label == "open loop"]
        c = [t for label, t in runs.items() if label == "closed loop"]
        if o and c and math.isfinite(o[0].rms_error_um) and math.isfinite(c[0].rms_error_um):
            out.append(f'<p class="ok">Closed loop cuts the RMS position error {o[0].rms_error_um / c[0].rms_error_um:.1f}'
                       " times against open loop.</p>")
    out.append(_img(fig6.playback_figure(runs, rate_hz=playbacks[0].extra.get("rate_hz")),
                    "Target and measured contactor positions; the errors leave out the start-up frames (shaded)"))
    return "\n".join(out)


def build_report(
    session_dir: str | Path | None,
    out_html: str | Path,
    *,
    trials: Iterable[TrialEntry] | None = None,
    title: str = "skinstretch session report",
    playbacks: Sequence[Any] = (),
    extra_figures: Sequence[tuple[Any, str]] = (),
    parameters: dict[str, Any] | None = None,
) -> Path:
    """Write the HTML report of a session directory (or of explicit ``trials``) and return its path.

    ``playbacks``: :class:`skinstretch.experiments.playback.PlaybackResult` s to show (e.g. open and closed loop);
    ``extra_figures``: (figure, caption) pairs added at the end (e.g. the truth overlay).
    """
    t0 = time.perf_counter()
    entries = list(trials) if trials is not None else collect_trials(session_dir)
    parts = [f"<h1>{_esc(title)}</h1>",
             f"<p>Written {_esc(time.strftime('%Y-%m-%d %H:%M:%S'))} from {_esc(session_dir or '')}.</p>"]
    infos = []
    body = []
    for entry in entries:
        try:
            html_part, info = trial_figures(entry)
        except (SkinstretchError, OSError, ValueError, KeyError) as exc:
            html_part, info = (f"<h2>Trial {_esc(entry.name)}</h2><p class=\"warn\">cannot be reported: "
                               f"{_esc(type(exc).__name__)}: {_esc(exc)}</p>"), {"name": entry.name}
        body.append(html_part)
        infos.append(info)
    # Figure 94 across trials, measured (and true when simulated)
    profiles = {f"{i['name']} ({i.get('surface', '?')})": i["profile"] for i in infos if "profile" in i}
    trues = {f"{i['name']} ({i.get('surface', '?')})": i["true_profile"] for i in infos if "true_profile" in i}
    amplitudes = {f"{i['name']} ({i.get('surface', '?')})": i["profile_amplitude"] for i in infos if "profile" in i}
    if profiles:
        body.insert(0, "<h2>Stretch along the sliding direction, all trials (seed Figure 94)</h2>" + _guard(
            "stretch profiles", lambda: _img(fig6.stretch_profile_figure(profiles, true_profiles=trues,
                                                                         amplitudes=amplitudes),
                                             "Relative change in stretch with position, averaged over each sequence;"
                                             " dashed: true (simulated)")))
    evals = [(i["name"], i["evaluation_quantities"]) for i in infos if "evaluation_quantities" in i]
    if evals:
        rows = [(n, *(q[key].value if key in q else "-" for key, _ in _SUMMARY_KEYS)) for n, q in evals]
        body.insert(0, "<h2>Measured vs true (simulated sessions)</h2>" + _table(
            rows, ["trial", *(label for _, label in _SUMMARY_KEYS)]))
    study = None
    if session_dir is not None and Path(session_dir).is_dir():
        from skinstretch.experiments.study import study_overview  # noqa: PLC0415

        shown = {e.session.resolve() for e in entries}
        study = [t for t in study_overview(session_dir) if t.session.resolve() in shown]
    if study:
        body.insert(0, _guard("study overview", lambda: _study_section(study)))
    else:
        overview = [(i["name"], i.get("surface", "?"), i.get("scene", ""), "yes" if "results" in i else "no")
                    for i in infos]
        body.insert(0, "<h2>Trials</h2>" + _table(overview, ["trial", "surface", "scene", "analysed"]))
    warned = [(i["name"], w) for i in infos for w in i.get("warnings", ())]
    if warned:  # at the top: a number a self-check doubts is never read as ok
        body.insert(0, '<div class="warn"><h2>Warnings</h2><ul>'
                    + "".join(f"<li>{_esc(n)}: {_esc(w)}</li>" for n, w in warned) + "</ul></div>")
    movies = [i for i in infos if "movie" in i]
    if movies:
        pick = next((i for i in movies if i.get("surface") == "ridge"), movies[0])
        body.append(_guard("tactile movie", lambda: _movie_section(pick["movie"], pick["name"])))
    if playbacks:
        body.append(_guard("playback", lambda: _playback_section(list(playbacks))))
    for fig, caption in extra_figures:
        body.append(_guard(caption, lambda fig=fig, caption=caption: _img(fig, caption)))
    params: dict[str, Any] = dict(parameters or {})
    first = next((i["results"] for i in infos if "results" in i), None)
    if first is not None:
        params.setdefault("analysis parameters", first.params)
    sdir = Path(session_dir) if session_dir else None
    proto = sdir / "protocol.yaml" if sdir else None
    foot = ["<h2>Parameters and versions</h2>", _kv(software_versions())]
    if proto is not None and proto.exists():
        foot.append("<h3>Protocol</h3><pre>" + _esc(proto.read_text()) + "</pre>")
    for k, v in params.items():
        foot.append(f"<h3>{_esc(k)}</h3><pre>" + _esc(json.dumps(v, indent=1, default=str)) + "</pre>")
    foot.append(f"<p>Report built in {time.perf_counter() - t0:.1f} s.</p>")
    doc = ("<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>" + _esc(title) + "</title><style>" + _CSS
           + "</style></head><body>" + "\n".join(parts + body + foot) + "</body></html>")
    out = Path(out_html)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(doc, encoding="utf-8")
    return out

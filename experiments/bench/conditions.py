"""Bench section ``conditions``: a real print moved by a known field, imaged as a lab would, through the user's path.

Each condition is a clip of a shipped 500-dpi print (:mod:`skinstretch.simulators.moved_print`: no scene simulator)
at a pixel scale, on a background, with an imaging condition, moved by an exact field; written as PNG frames or an
MP4 (x264 crf 18 through PyAV, or OpenCV's mp4v writer); imported by the code of ``skinstretch import FOLDER --px-per-mm
P --fps 60`` (:func:`~skinstretch.experiments.frame_import.import_frames`, the surface read from the frames); and
analysed by both methods as ``skinstretch analyze`` does (default parameters, two worker processes). Each analysis is
scored from its results file and summary.json alone (:mod:`skinstretch.experiments.evaluation.field_scores`): every
point of the ``motion`` table against the true displacement of consecutive pairs, every Delaunay edge of the 1- and
11-frame strain tables against the true length change, the coverage of the reported 95 % intervals, and a verdict
(accurate, flagged, silently wrong, inaccurate). CPU ms a frame is this process' and its workers' CPU time over
the frames.

The rows are a base case (afis_p1_2 at 30 px/mm on white, dark ridges, full contrast, noise 2 grey levels, PNG,
0.5 px/frame slide and +0.05 %/frame stretch, 40 frames) and one-factor-at-a-time variations of it, plus the
combinations issue 38 names; ``--quick`` runs the rows marked quick. One row from the shell:
``python -m skinstretch.experiments.bench.conditions --only-row NAME [--method flow]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from skinstretch.experiments.bench import BenchOptions, BenchTable
from skinstretch.simulators.moved_print import ClipConditions, PrintMotion, TravellingBand

if TYPE_CHECKING:
    from skinstretch.experiments.analysis import AnalysisParams
    from skinstretch.experiments.evaluation.field_scores import FieldScores

SECTION = "conditions"
DESCRIPTION = ("a real print moved by a known field at 15-100 px/mm, on any background, through import and analyze "
               "(both methods): accurate, flagged or silently wrong")

log = logging.getLogger(__name__)

METHODS = ("features", "flow")
CONTAINERS = ("png", "x264", "mp4v")
_FPS = 60.0
_X264_CRF = "18"


@dataclass(frozen=True)
class Condition:
    """One row group: a clip's imaging ``clip``, its ``motion``, how it is written (``container``) and whether
    ``--quick`` runs it."""

    name: str
    clip: ClipConditions
    motion: PrintMotion
    container: str = "png"
    quick: bool = False


BASE = ClipConditions(print_name="afis_p1_2", px_per_mm=30.0, background="white", noise_grey=2.0, n_frames=40)
SLIDE_STRETCH = PrintMotion(slide_px=(0.5, 0.0), stretch=(0.0005, 0.0))


def _vary(name: str, *, motion: PrintMotion = SLIDE_STRETCH, container: str = "png", quick: bool = False,
          **clip) -> Condition:
    return Condition(name, dataclasses.replace(BASE, **clip), motion, container, quick)


#: Every row; one factor changed from the base at a time, then the issue's combinations.
CONDITIONS: tuple[Condition, ...] = (
    _vary("base 30 px/mm", quick=True),
    *(_vary(f"scale {p:g} px/mm", px_per_mm=p, quick=p in (15, 62)) for p in (15, 20, 40, 62, 100)),
    _vary("black background", background="black", quick=True),
    _vary("grey background", background="grey"),
    _vary("black background 15 px/mm", background="black", px_per_mm=15.0),
    _vary("grey background 15 px/mm", background="grey", px_per_mm=15.0),
    _vary("bright ridges", bright_ridges=True, quick=True),
    _vary("bright ridges on black", bright_ridges=True, background="black"),
    _vary("contrast 50 %", contrast=0.5),
    _vary("contrast 35 %", contrast=0.35, quick=True),
    _vary("vignetting 40 %", vignetting=0.4),
    *(_vary(f"blur {b:g} px", blur_px=b) for b in (0.5, 0.8, 1.2)),
    *(_vary(f"noise {n:g} grey levels", noise_grey=n) for n in (3.0, 4.0)),
    _vary("MP4 x264 crf 18", container="x264", quick=True),
    _vary("MP4 OpenCV mp4v", container="mp4v"),
    _vary("field: slide 0.5 px/frame", motion=PrintMotion(slide_px=(0.45, 0.2))),
    _vary("field: stretch 0.05 %/frame", motion=PrintMotion(stretch=(0.0005, 0.0))),
    _vary("field: stretch 10 % over the clip", motion=PrintMotion(slide_px=(0.3, 0.0), stretch=(0.0025, 0.0))),
    _vary("field: shear 10 % over the clip", motion=PrintMotion(slide_px=(0.3, 0.0), shear=0.0025)),
    _vary("field: rotation 0.1 rad over the clip", motion=PrintMotion(rotation_rad=0.0025)),
    _vary("field: travelling band 5 %", quick=True,
          motion=PrintMotion(slide_px=(0.3, 0.0), band=TravellingBand(0.05, 0.4, -2.0, 0.1))),
    _vary("print afis_p2_1", print_name="afis_p2_1"),
    _vary("issue: 19.7 px/mm, white, noise 2", px_per_mm=500 / 25.4, quick=True),
    _vary("issue: 25 px/mm through MP4 x264", px_per_mm=25.0, container="x264"),
    _vary("issue: 19.7 px/mm, blur 1 px", px_per_mm=500 / 25.4, blur_px=1.0),
    _vary("issue: 62 px/mm, contrast 35 %, noise 3", px_per_mm=62.0, contrast=0.35, noise_grey=3.0),
    # lossy video where its error grows (known gaps, "Lossy video")
    _vary("MP4 x264 at 62 px/mm", px_per_mm=62.0, container="x264"),
    _vary("MP4 x264 at 62 px/mm, contrast 50 %", px_per_mm=62.0, contrast=0.5, container="x264"),
    _vary("MP4 x264 at 15 px/mm", px_per_mm=15.0, container="x264"),
)


def condition(name: str) -> Condition:
    """The condition called ``name`` (KeyError naming the known ones)."""
    for c in CONDITIONS:
        if c.name == name:
            return c
    raise KeyError(f"no condition {name!r}; known: {[c.name for c in CONDITIONS]}")


@dataclass(frozen=True)
class ConditionRow:
    """One condition analysed by one method, scored (see :class:`~skinstretch.experiments.evaluation.field_scores.
    FieldScores`), with the surface the import read and the analysis' CPU ms a frame."""

    condition: str
    method: str
    surface: str | None
    scores: FieldScores
    cpu_ms_per_frame: float
    verdict: str

    def cells(self) -> list:
        s = self.scores
        cover = lambda v: "n/a" if v is None else v  # noqa: E731
        return [self.condition, self.method, self.surface or "not read", s.displacement_rmse_px,
                cover(s.predicted_rmse_px), s.displacement_p99_px, s.edge_rmse_pct.get(11, float("nan")), s.edge_rmse_pct.get(1, float("nan")),
                self.cpu_ms_per_frame, s.pairs_not_ok, s.warnings, cover(s.point_coverage), cover(s.edge_coverage),
                self.verdict]


COLUMNS = ["condition", "method", "surface read", "disp RMSE px", "predicted disp RMSE px", "disp p99 px",
           "11-frame edge RMSE %", "1-frame edge RMSE %", "CPU ms/frame", "pairs not ok", "warnings", "95 % cover pts",
           "95 % cover edges", "verdict"]


def _write_clip(frames, directory: Path, container: str) -> Path:
    """The frames as a lab would hand them over: a PNG folder or an MP4."""
    import cv2  # noqa: PLC0415

    directory.mkdir(parents=True, exist_ok=True)
    if container == "png":
        folder = directory / "frames"
        folder.mkdir()
        for k, f in enumerate(frames):
            cv2.imwrite(str(folder / f"frame{k:04d}.png"), f)
        return folder
    if container == "x264":
        from skinstretch.experiments.bench.import_video import write_video  # noqa: PLC0415

        return write_video(directory / "clip.mp4", frames, codec="libx264", pix_fmt="yuv420p", rate=int(_FPS),
                           options={"crf": _X264_CRF})
    if container == "mp4v":
        path = directory / "clip.mp4"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), _FPS, frames.shape[2:0:-1],
                                 isColor=False)
        if not writer.isOpened():
            raise RuntimeError("OpenCV has no mp4v writer here")
        for f in frames:
            writer.write(f)
        writer.release()
        return path
    raise ValueError(f"container must be one of {CONTAINERS}, got {container!r}")


def imported_session(c: Condition, directory: Path):
    """Render ``c``, write it, import it as ``skinstretch import SOURCE --px-per-mm P --fps 60`` does; returns the
    import's result and the clip (its exact field)."""
    from skinstretch.experiments.frame_import import import_frames  # noqa: PLC0415
    from skinstretch.simulators.moved_print import render_print_clip  # noqa: PLC0415

    shutil.rmtree(directory, ignore_errors=True)
    clip = render_print_clip(c.clip, c.motion)
    source = _write_clip(clip.frames, directory, c.container)
    result = import_frames(source, directory / "session.h5", px_per_mm=c.clip.px_per_mm, fps=_FPS)
    return result, clip


def analyse_and_score(c: Condition, imported, clip, method: str, directory: Path, *,
                      params: AnalysisParams | None = None) -> ConditionRow:
    """``skinstretch analyze SESSION --method METHOD`` (default parameters, or ``params``) into
    ``directory/METHOD``, scored."""
    import psutil  # noqa: PLC0415

    from skinstretch.experiments.analysis import analysis_params, analyze_session, make_executor  # noqa: PLC0415
    from skinstretch.experiments.analysis.executor import WorkerProcesses  # noqa: PLC0415
    from skinstretch.experiments.evaluation.field_scores import score_results, verdict  # noqa: PLC0415

    params = analysis_params({}) if params is None else params
    out = directory / method
    with make_executor(params.execution) as executor:
        c0 = time.process_time()
        analyze_session(imported.path, out, method=method, params=params, executor=executor, overwrite=True)
        cpu = time.process_time() - c0
        for pid in executor.pids() if isinstance(executor, WorkerProcesses) else ():  # the workers', before they end
            try:
                t = psutil.Process(pid).cpu_times()
                cpu += t.user + t.system
            except psutil.Error:
                pass
    scores = score_results(out, clip.field)
    return ConditionRow(
        condition=c.name, method=method, surface=imported.surface, scores=scores,
        cpu_ms_per_frame=1000.0 * cpu / imported.n_frames,
        verdict=verdict(scores.displacement_rmse_px, scores.edge_rmse_pct.get(11, float("nan")),
                        flagged=scores.flagged))


def run_condition(name: str, method: str, *, workdir: Path = Path("bench-output")) -> ConditionRow:
    """One condition by one method, from rendering to verdict (for a quick look at one row)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    c = condition(name)
    directory = workdir / "conditions" / _folder(c.name)
    imported, clip = imported_session(c, directory)
    return analyse_and_score(c, imported, clip, method, directory)


def _folder(name: str) -> str:
    return "".join(ch if ch.isalnum() else "-" for ch in name).strip("-")


def _verdict_notes(rows: list[ConditionRow]) -> list[str]:
    notes = []
    for method in METHODS:
        mine = [r for r in rows if r.method == method]
        counts = {v: sum(r.verdict == v for r in mine) for v in ("accurate", "flagged", "inaccurate", "silently wrong")}
        silent = [r.condition for r in mine if r.verdict == "silently wrong"]
        notes.append(f"{method}: " + ", ".join(f"{n} {v}" for v, n in counts.items()) + f" of {len(mine)} rows"
                     + (f"; silently wrong: {'; '.join(silent)}" if silent else ""))
    return notes


def run(options: BenchOptions) -> list[BenchTable]:
    chosen = [c for c in CONDITIONS if c.quick or not options.quick]
    rows: list[ConditionRow] = []
    for c in chosen:
        directory = options.workdir / "conditions" / _folder(c.name)
        imported, clip = imported_session(c, directory)
        for method in METHODS:
            rows.append(analyse_and_score(c, imported, clip, method, directory))
            log.info("%s", "  ".join(str(v) for v in rows[-1].cells()))
        shutil.rmtree(directory, ignore_errors=True)
    return [BenchTable(
        title=f"A real print moved by a known field, imported and analysed as a user would ({len(chosen)} "
              f"conditions, {BASE.n_frames} frames of {BASE.shape[1]}x{BASE.shape[0]} px)",
        columns=COLUMNS,
        rows=[r.cells() for r in rows],
        notes=[
            "Base: afis_p1_2 (500 dpi) resampled to 30 px/mm, on white, dark ridges, full contrast (ridges 28, "
            "valleys 228), Gaussian noise 2 grey levels, PNG frames, 0.5 px/frame slide + 0.05 %/frame stretch along "
            "x; every other row changes what its name says. Backgrounds: white 235, grey 128, black 15.",
            "disp: |measured - true| displacement of every point of the motion table (consecutive pairs, every pair "
            "whatever its status); edge RMSE: measured minus true length change of every edge of the strain tables, "
            "percentage points. CPU ms/frame: this process and its two worker processes, shared 2-core machine.",
            "Verdict: accurate = disp RMSE <= 0.05 px and 11-frame edge RMSE <= 0.2 %; flagged = not accurate but a "
            "pair not ok or a summary.json warnings entry; silently wrong = an error over 3x its target (or nothing "
            "measured) without a flag; inaccurate = the rest. 95 % cover: fraction of points within 2.448 sigma "
            "(edges: 1.96 change_sigma); n/a when the results carry no uncertainty.",
            "surface read: what the import read from the frames (no --surface); a print on a plain background is "
            "flat.",
            *_verdict_notes(rows),
        ],
    )]


def main(argv: list[str] | None = None) -> int:
    """``python -m skinstretch.experiments.bench.conditions --only-row NAME``: one row, printed as a table."""
    p = argparse.ArgumentParser(prog="python -m skinstretch.experiments.bench.conditions", description=main.__doc__)
    p.add_argument("--only-row", default=None, metavar="NAME", help="the condition (see --list)")
    p.add_argument("--method", choices=METHODS, action="append", help="method (default: both)")
    p.add_argument("--workdir", type=Path, default=Path("bench-output"))
    p.add_argument("--list", action="store_true", help="list the conditions and exit")
    args = p.parse_args(argv)
    if args.list or not args.only_row:
        print("\n".join(f"{c.name}{'  (quick)' if c.quick else ''}" for c in CONDITIONS))
        return 0
    logging.basicConfig(level=logging.WARNING)
    try:
        c = condition(args.only_row)
    except KeyError as exc:
        print(exc.args[0], file=sys.stderr)
        return 2
    directory = args.workdir / "conditions" / _folder(c.name)
    imported, clip = imported_session(c, directory)
    rows = [analyse_and_score(c, imported, clip, m, directory).cells() for m in args.method or METHODS]
    print(BenchTable(title=c.name, columns=COLUMNS, rows=rows).format())
    return 0


if __name__ == "__main__":
    sys.exit(main())

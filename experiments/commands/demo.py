"""``skinstretch demo -o DIR``, the main job: a complete simulated experiment, end to end, in well under a minute.

1. Run the bundled ``demo`` protocol (flat, ridge and valley, one short trial each, seed 6.3.2) on the
   all-simulated rig: the scene simulator renders each surface, the simulated camera streams it in real time, the
   recorder writes one crash-safe session file per trial (with the simulator's ground truth attached), the Net F/T
   twin is recorded alongside, and each trial is analysed in a separate process as soon as it is recorded.
2. Take the ridge trial's tactile movie (seed 5.4), resample it to the display's 700 Hz and play it on the STReSS
   firmware twin (hysteresis, finger load) open loop and then closed loop, recording both.
3. Draw one frame of ``ridgeL`` with its true features overlaid, and write the self-contained HTML report.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

from skinstretch.processing.errors import SkinstretchError
from skinstretch.experiments.protocol import Rig, bundled_protocol, load_protocol

import argparse

__all__ = ["run_demo", "DemoResult", "register"]

log = logging.getLogger(__name__)


class DemoResult:
    """Where the demo wrote things, and what it measured."""

    def __init__(self, directory: Path, report: Path, session_dir: Path, run, playbacks, truth_png: Path | None,
                 seconds: float, problems: list[str]) -> None:
        self.directory = directory
        self.report = report
        self.session_dir = session_dir
        self.run = run
        self.playbacks = playbacks
        self.truth_png = truth_png
        self.seconds = seconds
        self.problems = problems


def _truth_figure(out_png: Path):
    """One frame of ridgeL with its true features (skinstretch.experiments.figures.truth, by the simulator engineer)."""
    from skinstretch.experiments.figures.truth import truth_figure  # noqa: PLC0415

    return truth_figure("ridgeL", 90, path=out_png)


def _fallback_truth_figure(ridge_session: Path, out_png: Path):
    """The same picture drawn here from the recorded ridge session's truth (used if the truth module is absent)."""
    from matplotlib.figure import Figure  # noqa: PLC0415

    from skinstretch.drivers.session_file import open_session  # noqa: PLC0415

    with open_session(ridge_session) as s:
        img = s.frame(0)
        t = s.truth
    fig = Figure(figsize=(7.5, 6))
    ax = fig.subplots()
    ax.imshow(img, cmap="gray", vmin=0, vmax=255)
    vis = t.feature_visible[0]
    for kind, marker, color, label in ((0, "o", "tab:red", "valley ending"), (1, "s", "tab:blue", "valley bifurcation"),
                                       (2, ".", "tab:green", "pore")):
        sel = vis & (t.feature_kind == kind)
        ax.plot(t.feature_x[0, sel], t.feature_y[0, sel], marker, mfc="none" if kind < 2 else color, mec=color,
                color=color, markersize=6 if kind < 2 else 4, linestyle="none", label=f"{label} ({int(sel.sum())})")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("ridgeL, frame 0, with its true features", fontsize=10)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.savefig(out_png, dpi=90, bbox_inches="tight")
    return fig


def run_demo(outdir: str | Path, *, progress: Callable[[str], None] | None = None,
             analysis_workers: int = 2) -> DemoResult:
    """Run the whole demo into ``outdir`` (a new session directory each run) and return where things are.

    ``progress`` receives one line per step (default: logged at INFO level).
    """
    from skinstretch.experiments.playback import fit_movie, load_movie, play_movie, resample_movie  # noqa: PLC0415
    from skinstretch.experiments.report import build_report  # noqa: PLC0415
    from skinstretch.experiments.rig import RigDevices  # noqa: PLC0415
    from skinstretch.experiments.runner import run_protocol  # noqa: PLC0415

    progress = progress or log.info
    t0 = time.perf_counter()
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    problems: list[str] = []
    path = bundled_protocol("demo")
    protocol = load_protocol(path)
    protocol = protocol.model_copy(update={"session": time.strftime("demo-%Y%m%d-%H%M%S")})
    rig = Rig()
    devices = RigDevices(rig)
    playbacks = []
    truth_png = None
    try:
        progress(f"[demo] recording {len(protocol.planned_trials())} simulated trials into {outdir}")
        run = run_protocol(protocol, rig, outdir, devices=devices, play_movie=False, progress=progress,
                           protocol_text=path.read_text(), analysis_workers=analysis_workers)
        sdir = run.directory
        for t in run.trials:
            if t.status != "complete":
                problems.append(f"trial {t.trial}: {t.status} {t.reason}")
            if t.analysis_error:
                problems.append(f"analysis of {t.trial}: {t.analysis_error}")
        # -- the tactile movie, open then closed loop
        movie_trial = next((t for t in run.trials if "ridge" in t.trial and t.analysis), None) or next(
            (t for t in run.trials if t.analysis), None)
        if movie_trial is None:
            problems.append("no analysed trial: no tactile movie to play")
        else:
            try:
                movie, rate = load_movie(movie_trial.analysis.parent)
                spec = protocol.movie
                movie, scale = fit_movie(movie * (spec.gain if spec else 1.0))
                if scale != 1.0:
                    progress(f"[demo] movie scaled by {scale:.2f} to stay within the loaded display's reach")
                movie = resample_movie(movie, from_hz=rate or 60.0, to_hz=700.0)
                pdir = sdir / "playback"
                pdir.mkdir(exist_ok=True)
                display = devices.display_device()
                for closed in (False, True):
                    label = "closed" if closed else "open"
                    progress(f"[demo] playing the {movie_trial.trial} movie on the simulated STReSS, {label} loop")
                    for attempt in range(2):
                        path_pb = pdir / f"playback-{label}{'' if attempt == 0 else '-retry'}.h5"
                        pb = play_movie(
                            display, movie, rate_hz=700.0, closed_loop=closed, force=devices.force,
                            force_ceiling_n=spec.force_ceiling_n if spec else 5.0, path=path_pb,
                            metadata={"movie": str(movie_trial.analysis), "loop": label},
                            settle_frames=min(150, movie.shape[0] // 4), progress=progress,
                        )
                        # A link failure here is the host starving the in-process twin: play once more.
                        if "link failed" not in pb.stopped:
                            break
                        progress(f"[demo] {label}-loop playback stopped ({pb.stopped}); playing it again")
                    if pb.stopped:
                        problems.append(f"{label}-loop playback stopped: {pb.stopped}")
                    playbacks.append(pb)
            except (SkinstretchError, OSError) as exc:
                problems.append(f"playback: {type(exc).__name__}: {exc}")
        # -- one frame of ridgeL with its true features
        ridge = next((t.path for t in run.trials if "ridge" in t.trial and t.status == "complete"), None)
        truth_png = outdir / "ridgeL-truth.png"
        truth_fig = None
        try:
            truth_fig = _truth_figure(truth_png)
        except ImportError:
            if ridge is not None:
                truth_fig = _fallback_truth_figure(ridge, truth_png)
        except (SkinstretchError, OSError, ValueError) as exc:
            problems.append(f"truth picture: {type(exc).__name__}: {exc}")
            truth_png = None
        extra = [(truth_fig, "ridgeL, frame 90, with its true features (simulator ground truth)")] if truth_fig else []
        report = build_report(sdir, outdir / "report.html", title="skinstretch demo: flat, ridge and valley, simulated",
                              playbacks=playbacks, extra_figures=extra,
                              parameters={"rig": rig.model_dump(), "problems": problems or ["none"]})
    finally:
        try:
            devices.close()
        except SkinstretchError as exc:
            problems.append(f"closing the rig: {exc}")
    return DemoResult(outdir, report, sdir, run, playbacks, truth_png, time.perf_counter() - t0, problems)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="the main job: a complete simulated experiment (record, analyse, play back, report)",
        description="Record flat, ridge and valley trials from the simulated camera, analyse them, play the ridge "
        "trial's tactile movie on the simulated STReSS open and closed loop, and write an HTML report.",
    )
    p.add_argument("-o", "--output", type=Path, default=Path("demo-output"), help="output directory")
    p.add_argument("--analysis-workers", type=int, default=2, help="processes analysing trials (default 2)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.process_lifetime import guard_process_tree  # noqa: PLC0415

    guard_process_tree()  # whatever ends this process, nothing it started outlives it
    result = run_demo(args.output, analysis_workers=max(1, args.analysis_workers))
    ok = [t for t in result.run.trials if t.status == "complete"]
    log.info("[demo] %d/%d trials recorded, %d analysed", len(ok), len(result.run.trials),
             sum(1 for t in result.run.trials if t.analysis))
    if len(result.playbacks) == 2 and all(p.complete for p in result.playbacks):
        o, c = result.playbacks
        ratio = o.rms_error_um / c.rms_error_um if c.rms_error_um > 0 else float("inf")
        log.info("[demo] playback RMS position error: open loop %.2f um, closed loop %.2f um (%.1fx better)",
                 o.rms_error_um, c.rms_error_um, ratio)
    if result.truth_png is not None:
        log.info("[demo] ridgeL frame with true features: %s", result.truth_png)
    for p in result.problems:
        log.warning("[demo] problem: %s", p)
    log.info("[demo] done in %.1f s", result.seconds)
    print(f"report: {result.report.resolve()}")  # the demo's product, on standard output
    return 0 if not result.problems else 1

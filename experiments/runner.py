"""Run a protocol: record every trial crash-safely, log documents, analyse after each trial, play the movie.

Data layout (one session file per trial)::

    DATADIR/<subject>/<session>/
        events.jsonl                      append-only document log (start / descriptor / event / stop)
        protocol.yaml, rig.yaml           what was run, copied verbatim
        000-flat-r1/session.h5            the trial's session file (frames, force, display state)
        000-flat-r1/analysis/             results of the analysis (written by a separate process)
        playback/playback.h5              the tactile movie as played and as measured (closed loop)

The document log follows bluesky's model: each trial is a *run* with a ``start`` document (what is about to
happen), a ``descriptor`` (the data keys recorded), ``event`` documents (progress, the analysis result), and a
``stop`` document (``exit_status`` success / fail / abort and the reason). Every document is flushed and fsynced
as it is written, so after a crash the log says exactly which trials finished. ``resume=True`` skips finished
trials, closes the interrupted one in the log as aborted (its file is kept and reads as incomplete) and carries on
with the next trial.

Analysis runs in a separate process (forked from a clean forkserver, never from this multi-threaded process) so
acquisition is never slowed by it (record-then-analyse).

Nothing is lost and nobody is surprised: the output directory is checked before any device is opened
(:mod:`skinstretch.experiments.output_paths`); a protocol whose trials cannot fit on the disk is refused before
the first one, and each trial is checked again before it starts (:mod:`skinstretch.drivers.disk_space`); a disk
that fills during a trial stops that trial (its file closed marked failed, every frame flushed before kept, the
display at rest) and ends the run (:attr:`SessionRun.stopped`), the remaining trials "not run". Worker processes
(analysis, scene rendering) die with this process, whatever kills it
(:mod:`skinstretch.experiments.process_lifetime`).
"""

from __future__ import annotations

import concurrent.futures as cf
import errno
import json
import logging
import os
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from skinstretch.experiments.json_encoding import json_default
from skinstretch.drivers.camera_modes import CAMERA_MODES, CameraMode
from skinstretch.drivers.disk_space import DEFAULT_RESERVE_BYTES, SpaceReserve, check_fits, is_disk_full
from skinstretch.drivers.session_file import attach_truth, expected_session_bytes, open_session
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.drivers.errors import DeviceError, DiskFullError, SessionFileError
from skinstretch.experiments.output_paths import check_output_dir
from skinstretch.experiments.process_lifetime import (check_stop, end_pool_now, stop_deferred, stop_pending,
                                                      stop_reason, worker_pool)
from skinstretch.processing.errors import InvalidInputError, Remedy, SkinstretchError
from skinstretch.experiments.protocol import PlannedTrial, Protocol, Rig
from skinstretch.experiments.skin_mapping_step import store_calibration
from skinstretch.experiments.recorder import Recorder, RecorderStats

log = logging.getLogger(__name__)

__all__ = [
    "EventLog",
    "TrialResult",
    "SessionRun",
    "run_protocol",
    "session_dir",
    "read_events",
    "finished_trials",
    "analyse_trial",
]

SESSION_FILE = "session.h5"
ANALYSIS_DIR = "analysis"
EVENT_LOG = "events.jsonl"
CALIBRATION_FILE = "calibration.json"
#: What a trial needs on disk beyond its session file's expected size: HDF5's own overhead, the event log and
#: the analysis results written next to it (measured on the demo protocol: results ~ 3 % of the frames).
DISK_MARGIN = 1.2


# --------------------------------------------------------------------------------------------- document log


class EventLog:
    """Append-only JSON-lines log of bluesky-style documents; each line is ``{"name": ..., "doc": {...}}``.

    Every document is flushed and fsynced before :meth:`emit` returns, so the log survives a SIGKILL. A small
    disk reserve is held next to it: on a full disk it is given back so the documents saying what happened (the
    failed trial's stop) still get written.
    """

    RESERVE_BYTES = 256 << 10

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "a", encoding="utf-8")
        self._lock = threading.Lock()
        try:
            self._reserve: SpaceReserve | None = SpaceReserve(self.path, self.RESERVE_BYTES)
        except DiskFullError:
            self._reserve = None  # the pre-trial space check reports the full disk

    def emit(self, name: str, doc: Mapping[str, Any]) -> dict[str, Any]:
        if name not in ("start", "descriptor", "event", "stop"):
            raise InvalidInputError(f"document name must be start/descriptor/event/stop, got {name!r}")
        doc = {"time": time.time(), **doc}
        line = json.dumps({"name": name, "doc": doc}, sort_keys=True, default=json_default)
        with self._lock:
            try:
                self._write(line)
            except OSError as exc:
                if not (is_disk_full(exc) and self._reserve is not None and self._reserve.release()):
                    raise DiskFullError(f"{self.path}: disk full, document {name!r} not logged") from None
                self._write(line)  # the reserve's room
        return doc

    def _write(self, line: str) -> None:
        self._fh.write(line + "\n")
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self) -> None:
        if self._reserve is not None:
            self._reserve.release()
        try:
            self._fh.close()
        except OSError as exc:  # a full disk refusing a buffered write: everything emitted was fsynced already
            if exc.errno != errno.ENOSPC:
                raise

    def __enter__(self) -> "EventLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_events(path: str | os.PathLike) -> list[tuple[str, dict[str, Any]]]:
    """All documents of a log as (name, doc); a torn last line (crash mid-write) is ignored."""
    out = []
    p = Path(path)
    if not p.exists():
        return out
    for line in p.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
            out.append((rec["name"], rec["doc"]))
        except (json.JSONDecodeError, KeyError, TypeError):
            continue
    return out


def finished_trials(events: list[tuple[str, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """Trial dirname -> its stop document, for every trial run that has one."""
    starts = {d["uid"]: d for n, d in events if n == "start"}
    out = {}
    for name, doc in events:
        if name == "stop" and doc.get("run_start") in starts:
            trial = starts[doc["run_start"]].get("trial", {}).get("dirname")
            if trial:
                out[trial] = doc
    return out


def session_dir(protocol: Protocol, datadir: str | os.PathLike) -> Path:
    """DATADIR/<subject>/<session> of a protocol."""
    return Path(datadir) / protocol.subject.id / protocol.session_name


# ----------------------------------------------------------------------------------------------- analysis


@dataclass(frozen=True)
class TrialAnalysis:
    """How the analysis of one trial went: its results file, or a one-line reason why it failed."""

    ok: bool
    results: str = ""
    seconds: float = 0.0
    error: str = ""


def analyse_trial(session_path: str, outdir: str, method: str, options: Any = None, *,
                  overwrite: bool = False) -> TrialAnalysis:
    """Analyse one recorded trial (runs in a worker process, on threads of it); never raises: a failure comes back
    as a one-line reason (a SkinstretchError's message; anything else with its exception type). Results already
    in ``outdir`` are a failure unless ``overwrite``.

    Imports :mod:`skinstretch.experiments.analysis` here, in the worker, so the recording process never pays for it.
    """
    from skinstretch.experiments.analysis import analysis_params, analyze_session  # noqa: PLC0415 - worker-side

    t0 = time.perf_counter()
    try:
        result = analyze_session(session_path, outdir, method=method, params=analysis_params(options),
                                 overwrite=overwrite)
    except SkinstretchError as exc:
        return TrialAnalysis(False, seconds=time.perf_counter() - t0, error=" ".join(str(exc).split()))
    except Exception as exc:  # noqa: BLE001 - a bug must not sink the recording; reported in one line
        log.exception("analysis of %s failed", session_path)
        return TrialAnalysis(False, seconds=time.perf_counter() - t0,
                             error=f"{type(exc).__name__}: {' '.join(str(exc).split())}")
    return TrialAnalysis(True, str(result.path), time.perf_counter() - t0)


def _analysis_pool(workers: int = 1) -> cf.ProcessPoolExecutor:
    # never forked from this process, which runs threads (writer, force reader) that a fork would copy mid-state;
    # the workers die with this process (a SIGKILLed recorder left them running).
    if not (isinstance(workers, int) and workers >= 1):
        raise InvalidInputError(f"analysis_workers must be a positive int, got {workers!r}")
    return worker_pool(workers)


# ------------------------------------------------------------------------------------------------- trials


@dataclass
class TrialResult:
    """Outcome of one trial: where its data is, its status and a summary."""

    trial: str
    path: Path
    status: str  # complete | failed | aborted | skipped | not run
    reason: str = ""
    summary: dict[str, Any] = field(default_factory=dict)
    analysis: Path | None = None
    analysis_error: str = ""
    analysed: bool = False  # an analysis was run (or attempted) for this trial
    disk_full: bool = False  # it failed because the disk was full (the run stops there)
    interrupted: KeyboardInterrupt | None = None  # a signal stopped it (the run stops there and re-raises it)


@dataclass
class SessionRun:
    """Outcome of a whole protocol run. ``stopped`` says why the run ended before its last trial (disk full)."""

    directory: Path
    trials: list[TrialResult]
    playback: Any = None
    playback_error: str = ""
    stopped: str = ""
    interrupted: KeyboardInterrupt | None = None  # the signal (or Ctrl-C) that stopped the run

    def count(self, status: str) -> int:
        return sum(t.status == status for t in self.trials)

    @property
    def failed_before(self) -> int:
        """Trials a ``--resume`` skipped because an earlier run ended them failed or aborted."""
        return sum(t.status == "skipped" and t.reason != "already complete" for t in self.trials)

    @property
    def analyses(self) -> tuple[int, int]:
        """(failed, run) analyses of this run."""
        run = [t for t in self.trials if t.analysed]
        return sum(bool(t.analysis_error) for t in run), len(run)

    @property
    def ok(self) -> bool:
        """Every trial recorded (or done before a resume), every analysis done, the run not stopped."""
        return (all(t.status in ("complete", "skipped") for t in self.trials) and not self.failed_before
                and not self.stopped and self.analyses[0] == 0)

    def summary_line(self) -> str:
        """One line: how many of how many trials and analyses failed, and why the run stopped if it did."""
        n = len(self.trials)
        failed = self.count("failed") + self.count("aborted") + self.failed_before
        bad_analyses, analyses = self.analyses
        if self.ok:
            return f"all {n} trials recorded" + (f", {analyses} of {analyses} analyses done" if analyses else "")
        parts = [f"{failed} of {n} trials failed" + (f" ({self.failed_before} in an earlier run)"
                                                      if self.failed_before else "")]
        if self.count("not run"):
            parts.append(f"{self.count('not run')} not run")
        parts.append(f"{bad_analyses} of {analyses} analyses failed")
        line = ", ".join(parts)
        return f"{line}; run stopped: {self.stopped}" if self.stopped else line


def _summarise(path: Path, stats: RecorderStats) -> dict[str, Any]:
    """Per-trial summary from the file itself: frames, rate, dropped frames (frame-id gaps), force."""
    out: dict[str, Any] = {"bytes": stats.bytes_written, "queue_max": stats.max_queue_depth}
    try:
        with open_session(path) as s:
            ids = s.frame_ids
            ts = s.timestamps
            out["frames"] = int(s.n_frames)
            out["status"] = s.status
            out["dropped_frames"] = int(np.sum(np.maximum(np.diff(ids) - 1, 0))) if ids.size > 1 else 0
            out["duration_s"] = float(ts[-1] - ts[0]) if ts.size > 1 else 0.0
            out["mean_fps"] = float((ts.size - 1) / (ts[-1] - ts[0])) if ts.size > 1 and ts[-1] > ts[0] else 0.0
            if "force" in s.stream_names():
                _, f = s.read_stream("force")
                if f.shape[0]:
                    out["force_samples"] = int(f.shape[0])
                    out["normal_force_mean_n"] = float(np.mean(f[:, 2]))
                    out["normal_force_max_n"] = float(np.max(np.abs(f[:, 2])))
    except SessionFileError as exc:
        out["error"] = str(exc)
    out["frames_dropped_queue"] = stats.frames_dropped
    return out


class _ForcePump(threading.Thread):
    """Reads force blocks from the sensor while a trial runs and queues them to the recorder."""

    def __init__(self, source, recorder: Recorder) -> None:
        super().__init__(name="force-pump", daemon=True)
        self.source = source
        self.recorder = recorder
        self.stop_event = threading.Event()
        self.error: str | None = None
        self.samples = 0

    def run(self) -> None:
        try:
            while not self.stop_event.is_set() and self.recorder.failure is None:
                t, data = self.source.read_block(timeout_s=0.2)
                if len(t):
                    self.recorder.put_samples("force", t, data)
                    self.samples += len(t)
        except SkinstretchError as exc:
            self.error = f"force sensor: {type(exc).__name__}: {exc}"
        except OSError as exc:
            self.error = f"force sensor: link error: {exc}"


def record_trial(
    trial: PlannedTrial,
    *,
    protocol: Protocol,
    devices,
    path: Path,
    log: EventLog,
    run_uid: str,
    progress: Callable[[str], None],
    writer_factory=None,
) -> TrialResult:
    """Record one trial into ``path``: camera frames, force samples and display state, until the duration ends,
    the recorder fails (disk full) or a device fails. The display is sent to rest whatever happens."""
    mode: CameraMode = CAMERA_MODES[protocol.camera_mode]
    calibration = Calibration.from_field_of_view(mode.width, protocol.field_of_view_mm)
    n_target = max(1, int(round(trial.spec.duration_s * mode.fps)))
    streams: dict[str, tuple[tuple[int, ...], Any]] = {}
    if protocol.record.force and devices.force is not None:
        streams["force"] = ((6,), "f8")
    if protocol.record.display and devices.display is not None:
        streams["display_state"] = ((10, 10), "f4")
    metadata = {
        "protocol": protocol.name,
        "session": protocol.session_name,
        "subject": protocol.subject.model_dump(),
        "trial": trial.spec.name,
        "trial_index": trial.index,
        "repetition": trial.repetition,
        "direction": trial.spec.direction,
        "instructions": trial.spec.instructions,
        "surface": trial.surface.model_dump(),
        "scene": trial.surface.scene_name,
        "rig": devices.describe(),
    }
    log.emit(
        "descriptor",
        {
            "uid": uuid.uuid4().hex,
            "run_start": run_uid,
            "name": "primary",
            "data_keys": {
                "frames": {"shape": [mode.height, mode.width], "dtype": "uint8", "source": devices.describe()["camera"]},
                **{k: {"shape": list(v[0]), "dtype": str(v[1])} for k, v in streams.items()},
            },
        },
    )
    kwargs = {} if writer_factory is None else {"writer_factory": writer_factory}
    try:
        recorder = Recorder(path, camera_mode=mode, calibration=calibration, metadata=metadata, streams=streams,
                            **kwargs)
    except DiskFullError as exc:  # not even room to start the file: nothing recorded, the display untouched
        return TrialResult(trial=trial.dirname, path=path, status="failed", reason=str(exc), disk_full=True)
    recorder.start()
    camera = None
    pump = None
    failure: str | None = None
    seq = 0
    interrupted: KeyboardInterrupt | None = None
    try:  # whatever stops the trial, even a signal in the clean-up, the file is closed below
        try:
            if devices.display is not None:
                devices.display.rest()
            camera = devices.camera_for(trial=trial, protocol=protocol, n_frames=n_target)
            camera.start()
            if "force" in streams:
                devices.force.begin()
                pump = _ForcePump(devices.force, recorder)
                pump.start()
            frames = 0
            timeout = max(1.0, 20 * mode.period_s)
            last_report = time.monotonic()
            while frames < n_target:
                check_stop()
                if recorder.failure is not None:
                    failure = recorder.failure
                    break
                if pump is not None and pump.error:
                    failure = pump.error
                    break
                try:
                    frame = camera.read(timeout_s=timeout)
                except DeviceError as exc:
                    if type(exc).__name__ == "EndOfStreamError":
                        break  # a finite source (replay, simulation) ran out: the trial ends with what it gave
                    raise
                recorder.put_frame(
                    frame.image,
                    timestamp=frame.host_timestamp_s,
                    frame_id=frame.frame_id,
                    device_timestamp=frame.device_timestamp_s,
                )
                if "display_state" in streams:
                    recorder.put_samples("display_state", frame.host_timestamp_s, devices.display.measured_positions_um())
                frames += 1
                now = time.monotonic()
                if now - last_report >= 0.25 or frames == n_target:
                    last_report = now
                    progress(f"  {trial.dirname}: {frames}/{n_target} frames")
                    seq += 1
                    log.emit(
                        "event",
                        {"uid": uuid.uuid4().hex, "run_start": run_uid, "seq_num": seq, "data": {"frames": frames}},
                    )
        except (DeviceError, OSError) as exc:
            failure = f"device fault: {type(exc).__name__}: {exc}"
        except SkinstretchError as exc:
            failure = f"{type(exc).__name__}: {exc}"
        finally:
            if pump is not None:
                pump.stop_event.set()
                pump.join(2.0)
                try:
                    devices.force.end()
                except (SkinstretchError, OSError):
                    pass
                # a sensor that fell silent near the end, or never spoke: the trial has no force, so it failed
                if failure is None and pump.error:
                    failure = pump.error
                elif failure is None and pump.samples == 0:
                    failure = f"force sensor: {devices.force.description} delivered no sample during the trial"
            if camera is not None:
                try:
                    camera.stop()
                except (SkinstretchError, OSError):
                    pass
            if devices.display is not None:
                try:
                    devices.display.rest()
                except (SkinstretchError, OSError) as exc:
                    failure = failure or f"display did not return to rest: {exc}"
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP (process_lifetime.stop_on_signals)
        interrupted = exc
        failure = f"aborted: {stop_reason(exc)}"
    with stop_deferred():  # a signal from here on is acted on once the file is closed (run_protocol)
        if failure is None and recorder.failure is not None:
            failure = recorder.failure
        stats = recorder.finish(failed_reason=failure)
        if interrupted is not None:  # closed as aborted; the truth is not attached, the run stops (run_protocol)
            return TrialResult(trial=trial.dirname, path=path, status="aborted", reason=stop_reason(interrupted),
                               summary=_summarise(path, stats), interrupted=interrupted)
        truth = getattr(camera, "truth", None)
        if truth is not None and stats.frames_written > 0 and not recorder.disk_full and not stop_pending():
            _attach_truth(path, truth)
        summary = _summarise(path, stats)
        status = "complete" if stats.status == "complete" else "failed"
        return TrialResult(trial=trial.dirname, path=path, status=status, reason=stats.reason, summary=summary,
                           disk_full=recorder.disk_full)


def expected_trial_bytes(protocol: Protocol, trial: PlannedTrial) -> int:
    """What recording ``trial`` leaves on disk (its session file, with :data:`DISK_MARGIN` for the rest), counting
    every stream the protocol asks for (an upper bound: the rig may have no force sensor). While it records, the
    writer also holds :data:`~skinstretch.drivers.disk_space.DEFAULT_RESERVE_BYTES` (:func:`_needed`)."""
    mode = CAMERA_MODES[protocol.camera_mode]
    n_frames = max(1, int(round(trial.spec.duration_s * mode.fps)))
    streams: dict[str, tuple[tuple[int, ...], Any]] = {}
    samples: dict[str, int] = {}
    if protocol.record.force:
        streams["force"] = ((6,), "f8")
        samples["force"] = int(trial.spec.duration_s * protocol.record.force_rate_hz) + 1
    if protocol.record.display:
        streams["display_state"] = ((10, 10), "f4")
        samples["display_state"] = n_frames
    return int(DISK_MARGIN * expected_session_bytes(mode, n_frames, streams=streams, samples=samples,
                                                     reserve_bytes=0))


def _needed(protocol: Protocol, trials: list[PlannedTrial]) -> int:
    """Disk space ``trials`` need: what they leave, plus the reserve held while the last one records."""
    return sum(expected_trial_bytes(protocol, t) for t in trials) + DEFAULT_RESERVE_BYTES


def _remove_stale_reserves(sdir: Path) -> None:
    """Disk reserves left next to session files by a killed recorder (``.session.h5.reserve``)."""
    for stale in sdir.glob("*/.*.reserve"):
        stale.unlink(missing_ok=True)


def _attach_truth(path: Path, truth) -> None:
    """Store a simulated camera's ground truth, row k for recorded frame k (frame ids index the source)."""
    from skinstretch.experiments.rig import subset_truth  # noqa: PLC0415

    try:
        with open_session(path) as s:
            ids = s.frame_ids
        rows = ids - ids[0] if ids.size else ids
        if ids.size and rows[-1] < np.asarray(truth.feature_x).shape[0]:
            attach_truth(path, subset_truth(truth, rows))
    except (SessionFileError, OSError, InvalidInputError) as exc:
        # the recording stands without its truth; the report then shows no measured-vs-true section
        log.warning("%s: recorded without its simulated ground truth: %s", path, exc)


def _print(msg: str) -> None:
    logging.getLogger(__name__).info(msg)  # progress lines: --quiet silences them


def _session_calibration(protocol: Protocol, sdir: Path, log: "EventLog", progress: Callable[[str], None]):
    """The session's mapping (protocol ``calibration``): fitted once into ``sdir/calibration.json``, reused on
    ``--resume``; None without one. An untrustworthy fit raises before any trial is recorded."""
    spec = protocol.calibration
    if spec is None:
        return None
    from skinstretch.experiments.skin_mapping_step import calibrate_source, mapping_for_frames  # noqa: PLC0415

    saved = sdir / CALIBRATION_FILE
    if saved.exists():
        mapping, summary = calibrate_source(saved)
    else:
        # The spec's fields are calibrate_source's options (surface, spacing, dot size, frames, residual bound).
        options = spec.model_dump(exclude={"source"})
        mapping, summary = calibrate_source(spec.source, field_width_mm=protocol.field_of_view_mm, **options)
        mode = CAMERA_MODES[protocol.camera_mode]
        mapping_for_frames(mapping, mode.width, mode.height)  # frames larger than the grid images: fail now
        tmp = saved.with_name(saved.name + ".partial")
        tmp.write_text(json.dumps(mapping.to_dict(), indent=2))
        os.replace(tmp, saved)
    progress(f"calibration: {summary}")
    log.emit("event", {"uid": uuid.uuid4().hex, "name": "calibration",
                       "data": {"source": spec.source, "file": str(saved), "summary": summary}})
    return mapping


def run_protocol(
    protocol: Protocol,
    rig: Rig,
    datadir: str | os.PathLike,
    *,
    resume: bool = False,
    analyse: bool | None = None,
    play_movie: bool = True,
    progress: Callable[[str], None] = _print,
    protocol_text: str | None = None,
    rig_text: str | None = None,
    devices=None,
    writer_factory=None,
    analysis_workers: int = 1,
) -> SessionRun:
    """Run every trial of ``protocol`` on ``rig`` into ``datadir`` (see module docstring for the layout).

    Parameters
    ----------
    protocol, rig : Protocol, Rig
        What to run and with which devices.
    datadir : path-like
        Root of the data layout.
    resume : bool, optional
        Carry on after a crash: skip trials the log says finished, mark the interrupted one aborted.
        Without it an existing session directory is an error (data are never overwritten).
    analyse : bool, optional
        Override ``protocol.analysis`` (None: run it after each trial when the protocol asks for it).
    play_movie : bool, optional
        Play ``protocol.movie`` at the end (if any).
    devices : optional
        Pre-built devices (:class:`skinstretch.experiments.rig.RigDevices`); default: built from ``rig``.
    writer_factory : callable, optional
        Passed to every :class:`Recorder` (fault injection in tests).
    analysis_workers : int, optional
        Processes analysing finished trials while the next ones record.
    """
    sdir = session_dir(protocol, datadir)
    log_path = sdir / EVENT_LOG
    # Before anything is created or opened: the directory can be written, and the trials to record fit on disk.
    check_output_dir(sdir, must_be_empty=not resume,
                     remedy=Remedy(("resume",), "to carry on with the session it holds (or write elsewhere)", True))
    if resume and sdir.exists():
        _remove_stale_reserves(sdir)
    pending_plan = [t for t in protocol.planned_trials()
                    if t.dirname not in finished_trials(read_events(log_path)) and not (sdir / t.dirname / SESSION_FILE).exists()]
    if pending_plan:
        check_fits(sdir, _needed(protocol, pending_plan),
                   what=f"the {len(pending_plan)} trial(s) of protocol {protocol.name!r}")
    sdir.mkdir(parents=True, exist_ok=True)
    if protocol_text is not None and not (sdir / "protocol.yaml").exists():
        (sdir / "protocol.yaml").write_text(protocol_text)
    if rig_text is not None and not (sdir / "rig.yaml").exists():
        (sdir / "rig.yaml").write_text(rig_text)
    events = read_events(log_path)
    done = finished_trials(events)
    do_analysis = protocol.analysis.enabled and protocol.analysis.when == "after_trial"
    if analyse is not None:
        do_analysis = analyse
    own_devices = devices is None
    if devices is None:
        from skinstretch.experiments.rig import RigDevices  # noqa: PLC0415 - rig imports the device modules

        devices = RigDevices(rig)
    pool = _analysis_pool(analysis_workers) if do_analysis else None
    pending: list[tuple[TrialResult, cf.Future, str]] = []
    results: list[TrialResult] = []
    plan = protocol.planned_trials()
    run = SessionRun(directory=sdir, trials=results)
    current_run = ""  # the start document of the trial being recorded, until its stop document
    try:
        with EventLog(log_path) as log:
            # Runs started but never stopped were interrupted (crash, SIGKILL): close them in the log as aborted.
            starts = [d for n, d in events if n == "start"]
            stopped = {d.get("run_start") for n, d in events if n == "stop"}
            for d in starts:
                if d["uid"] not in stopped:
                    dirname = d.get("trial", {}).get("dirname", "")
                    reason = "interrupted: the recording process ended without closing this trial"
                    log.emit("stop", {"uid": uuid.uuid4().hex, "run_start": d["uid"], "exit_status": "abort",
                                      "reason": reason})
                    done[dirname] = {"exit_status": "abort", "reason": reason}
            mapping = _session_calibration(protocol, sdir, log, progress)
            todo = [t for t in plan if t.dirname not in done and not (sdir / t.dirname / SESSION_FILE).exists()]
            if hasattr(devices, "prepare"):
                devices.prepare(protocol=protocol, trials=todo)
            for k, trial in enumerate(plan):
                check_stop()
                tdir = sdir / trial.dirname
                path = tdir / SESSION_FILE
                if trial.dirname in done or path.exists():
                    prior = done.get(trial.dirname, {})
                    status = {"success": "complete", "fail": "failed", "abort": "aborted"}.get(
                        prior.get("exit_status", ""), "aborted"
                    )
                    progress(f"trial {k + 1}/{len(plan)} {trial.dirname}: already {status}, skipped")
                    results.append(TrialResult(trial.dirname, path, "skipped", reason=f"already {status}"))
                    continue
                try:  # again before each trial: another program may have filled the disk meanwhile
                    check_fits(sdir, _needed(protocol, [trial]), what=f"trial {trial.dirname}")
                except DiskFullError as exc:
                    run.stopped = str(exc)
                    break
                tdir.mkdir(parents=True, exist_ok=True)
                run_uid = current_run = uuid.uuid4().hex
                log.emit(
                    "start",
                    {
                        "uid": run_uid,
                        "plan_name": "record_trial",
                        "protocol": protocol.name,
                        "session": protocol.session_name,
                        "subject": protocol.subject.id,
                        "trial": {
                            "dirname": trial.dirname,
                            "name": trial.spec.name,
                            "index": trial.index,
                            "repetition": trial.repetition,
                            "duration_s": trial.spec.duration_s,
                            "direction": trial.spec.direction,
                            "instructions": trial.spec.instructions,
                        },
                        "surface": trial.surface.model_dump(),
                        "camera_mode": protocol.camera_mode,
                        "rig": devices.describe(),
                        "path": str(path),
                    },
                )
                progress(f"trial {k + 1}/{len(plan)} {trial.dirname}: {trial.spec.instructions or trial.spec.name}")
                result = record_trial(
                    trial,
                    protocol=protocol,
                    devices=devices,
                    path=path,
                    log=log,
                    run_uid=run_uid,
                    progress=progress,
                    writer_factory=writer_factory,
                )
                with stop_deferred():  # a signal now is acted on once the log says how the trial ended
                    s = result.summary
                    progress(
                        f"trial {k + 1}/{len(plan)} {trial.dirname}: {result.status}"
                        + (f" ({result.reason})" if result.reason else "")
                        + f", {s.get('frames', 0)} frames, {s.get('dropped_frames', 0)} dropped, "
                        f"{s.get('mean_fps', 0.0):.1f} fps, {s.get('bytes', 0) / 1e6:.1f} MB"
                    )
                    log.emit(
                        "stop",
                        {
                            "uid": uuid.uuid4().hex,
                            "run_start": run_uid,
                            "exit_status": {"complete": "success", "aborted": "abort"}.get(result.status, "fail"),
                            "reason": result.reason,
                            "summary": result.summary,
                            "num_events": {"primary": s.get("frames", 0)},
                        },
                    )
                    results.append(result)
                    current_run = ""
                if result.interrupted is not None:  # a signal: nothing more is recorded, analysed or played
                    raise result.interrupted
                check_stop()
                if mapping is not None and path.exists():
                    try:
                        store_calibration(path, mapping)
                    except SkinstretchError as exc:  # the data are kept; the analysis then measures in pixels
                        progress(f"trial {trial.dirname}: calibration not stored ({exc})")
                        log.emit("event", {"uid": uuid.uuid4().hex, "run_start": run_uid, "name": "calibration",
                                           "data": {"stored": False, "reason": str(exc)}})
                if result.disk_full:  # no further trial fits; what was recorded is analysed later
                    run.stopped = result.reason
                    break
                if pool is not None and result.summary.get("frames", 0) >= 2:
                    result.analysed = True
                    fut = pool.submit(
                        analyse_trial,
                        str(path),
                        str(tdir / ANALYSIS_DIR),
                        protocol.analysis.method,
                        protocol.analysis.options,
                        # the trial was recorded just now: results in its folder (left by hand) cannot be its own
                        overwrite=True,
                    )
                    pending.append((result, fut, run_uid))
            recorded = {t.trial for t in results}
            results.extend(TrialResult(t.dirname, sdir / t.dirname / SESSION_FILE, "not run", reason=run.stopped)
                           for t in plan if t.dirname not in recorded)
            if run.stopped:
                progress(f"run stopped: {run.stopped}")
                log.emit("event", {"uid": uuid.uuid4().hex, "name": "run_stopped",
                                   "data": {"reason": run.stopped, "not_run": [t.trial for t in results
                                                                               if t.status == "not run"]}})
            for result, fut, run_uid in pending:
                try:
                    while True:
                        try:
                            out = fut.result(timeout=0.25)
                            break
                        except cf.TimeoutError:
                            check_stop()
                except Exception as exc:  # the worker process died: reported, never raised into the recording
                    out = TrialAnalysis(False, error=f"analysis process failed: {type(exc).__name__}: {exc}")
                if out.ok:
                    result.analysis = Path(out.results)
                    progress(f"analysis of {result.trial}: done in {out.seconds:.1f} s -> {result.analysis}")
                else:
                    result.analysis_error = out.error
                    progress(f"analysis of {result.trial}: FAILED ({result.analysis_error})")
                log.emit(
                    "event",
                    {
                        "uid": uuid.uuid4().hex,
                        "run_start": run_uid,
                        "seq_num": -1,
                        "data": {
                            "analysis": str(result.analysis) if result.analysis else None,
                            "analysis_error": result.analysis_error,
                        },
                    },
                )
            if play_movie and protocol.movie is not None and run.stopped:
                run.playback_error = f"not played: {run.stopped}"
            elif play_movie and protocol.movie is not None and devices.display is not None:
                from skinstretch.experiments.playback import play_protocol_movie  # noqa: PLC0415

                try:
                    run.playback = play_protocol_movie(protocol, sdir, devices=devices, progress=progress)
                except (SkinstretchError, OSError) as exc:
                    run.playback_error = f"{type(exc).__name__}: {exc}"
                    progress(f"playback: FAILED ({run.playback_error})")
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP: close in the log what was under way, then stop
        run.interrupted = exc
        run.stopped = stop_reason(exc)
        _log_interruption(run, plan, sdir, log_path, current_run, pending)
    finally:
        if pool is not None:
            if run.interrupted is not None:
                end_pool_now(pool)
            else:
                pool.shutdown(wait=True, cancel_futures=True)
        if own_devices:
            devices.close(now=run.interrupted is not None)
    return run


def _log_interruption(run: SessionRun, plan: list[PlannedTrial], sdir: Path, log_path: Path, current_run: str,
                      pending: list) -> None:
    """After a signal: the trial whose start was logged without a stop is closed as aborted, the analyses still
    running are given up (their trials keep their data: ``skinstretch analyze`` later), the trials not reached are
    "not run", and the log says so. Runs with the log closed: its documents are appended again."""
    with EventLog(log_path) as log:
        if current_run:
            log.emit("stop", {"uid": uuid.uuid4().hex, "run_start": current_run, "exit_status": "abort",
                              "reason": run.stopped})
        for result, fut, _ in pending:
            if fut.done() and not fut.cancelled() and fut.exception() is None and fut.result().ok:
                result.analysis = Path(fut.result().results)
            elif not result.analysis_error:
                result.analysis_error = f"not finished: {run.stopped}"
        recorded = {t.trial for t in run.trials}
        run.trials.extend(TrialResult(t.dirname, sdir / t.dirname / SESSION_FILE, "not run", reason=run.stopped)
                          for t in plan if t.dirname not in recorded)
        log.emit("event", {"uid": uuid.uuid4().hex, "name": "run_stopped",
                           "data": {"reason": run.stopped, "not_run": [t.trial for t in run.trials
                                                                       if t.status == "not run"]}})

"""Closed-loop playback of a tactile movie on a STReSS display, with force and link safety (seed 5.4, 6.4).

The seed could not test its movies because "the latest prototype of the STReSS is not sufficiently accurate"
(seed 6.4). Here every frame ack carries the contactors' measured positions, so playback can correct each
contactor's *persistent* error online:

* :class:`ContactorCorrector` fits, per contactor and by recursive least squares with forgetting, the model
  ``measured = gain * command + offset + backlash * direction`` (direction = sign of the last commanded motion,
  which captures hysteresis; the finger's load shows up as offset and gain), and inverts it for the next command.
  The correction ``|command - target|`` is bounded (``max_correction_um``), the estimates are clamped to sane
  ranges, and the display driver applies its own range and slew limits on top.
* :func:`play_movie` streams the frames, stops the movie and sends every contactor to rest when the normal force
  exceeds a ceiling or the link fails (a flagged :class:`PlaybackResult`, never a silent stop), and records
  target, command, measured positions and force in a session file.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.display.base import TactileDisplay
from skinstretch.drivers.display.stress_protocol import rate_to_mhz
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.drivers.session_file import SessionWriter, open_session
from skinstretch.drivers.display.safety import check_movie
from skinstretch.drivers.errors import DeviceError, DeviceTimeoutError, SafetyStop, SessionFileError
from skinstretch.processing.errors import InvalidInputError
from skinstretch.experiments.output_paths import REPLACE_IT, check_output_dir, check_output_file
from skinstretch.experiments.protocol import MAX_FORCE_CEILING_N

__all__ = [
    "ContactorCorrector",
    "PlaybackResult",
    "play_movie",
    "load_movie",
    "rms_tracking_error",
    "rms_text",
    "play_protocol_movie",
    "resample_movie",
    "fit_movie",
]

SHAPE = (10, 10)


# ----------------------------------------------------------------------------------------------- controller


class ContactorCorrector:
    """Online per-contactor gain / offset / backlash estimate and its bounded inverse.

    Parameters
    ----------
    max_correction_um : float, keyword-only
        Largest difference between the command sent and the target (um); keeps a bad estimate harmless.
    forgetting : float, keyword-only
        RLS forgetting factor in (0.9, 1]; lower tracks a changing finger load faster.
    gain_bounds : (float, float), keyword-only
        Clamp of the estimated gain.
    """

    def __init__(
        self,
        *,
        max_correction_um: float = 15.0,
        forgetting: float = 0.995,
        gain_bounds: tuple[float, float] = (0.2, 2.0),
        shape: tuple[int, int] = SHAPE,
    ) -> None:
        if not (math.isfinite(max_correction_um) and max_correction_um >= 0):
            raise InvalidInputError(f"max_correction_um must be >= 0, got {max_correction_um!r}")
        if not (0.9 < forgetting <= 1.0):
            raise InvalidInputError(f"forgetting must be in (0.9, 1], got {forgetting!r}")
        if not (0 < gain_bounds[0] < 1 < gain_bounds[1]):
            raise InvalidInputError(f"gain_bounds must bracket 1, got {gain_bounds!r}")
        self.max_correction_um = float(max_correction_um)
        self.forgetting = float(forgetting)
        self.gain_bounds = (float(gain_bounds[0]), float(gain_bounds[1]))
        n = int(np.prod(shape))
        self.shape = shape
        # theta = (gain, offset, backlash) per contactor; P its covariance (n, 3, 3).
        self.theta = np.tile(np.array([1.0, 0.0, 0.0]), (n, 1))
        self.P = np.tile(np.diag([1e-3, 10.0, 10.0]), (n, 1, 1))
        self._direction = np.ones(n)
        self._last_target = np.zeros(n)
        self._prev_ack: tuple[int, np.ndarray, np.ndarray] | None = None  # (seq, command, its direction)
        self._ack_direction = np.ones(n)
        self.updates = 0

    @property
    def gain(self) -> np.ndarray:
        return self.theta[:, 0].reshape(self.shape)

    @property
    def offset_um(self) -> np.ndarray:
        return self.theta[:, 1].reshape(self.shape)

    @property
    def backlash_um(self) -> np.ndarray:
        return self.theta[:, 2].reshape(self.shape)

    def command(self, target_um: np.ndarray) -> np.ndarray:
        """The command to send so that the contactors reach ``target_um`` (10, 10), correction bounded."""
        target = np.asarray(target_um, dtype=float).reshape(-1)
        if target.shape[0] != self.theta.shape[0] or not np.all(np.isfinite(target)):
            raise InvalidInputError(f"target_um must be a finite {self.shape} array")
        step = target - self._last_target
        # Direction of motion: the sign of the commanded step, held while the target stands still (backlash).
        self._direction = np.where(np.abs(step) > 1e-9, np.sign(step), self._direction)
        self._last_target = target
        gain, offset, backlash = self.theta.T
        cmd = (target - offset - backlash * self._direction) / gain
        cmd = np.clip(cmd, target - self.max_correction_um, target + self.max_correction_um)
        return cmd.reshape(self.shape)

    def observe_ack(self, ack) -> None:
        """Learn from one frame ack (acks in the order they arrive; lost ones are simply skipped).

        The ack of frame j reports the positions reached under the command of frame j - 1 (seed-less detail of
        this project's protocol, docs/protocols/stress.md), so the regression pairs ack j's measured positions
        with ack j - 1's command, whose motion direction came from ack j - 2's command.
        """
        cmd = np.asarray(ack.command_um, dtype=float).reshape(-1)
        prev = self._prev_ack
        self._prev_ack = (int(ack.seq), cmd, self._ack_direction.copy())
        if prev is None or (prev[0] + 1) & 0xFF != int(ack.seq):
            return  # a gap: this ack's measurement cannot be paired with a known command
        prev_cmd, prev_dir = prev[1], prev[2]
        step = cmd - prev_cmd
        self._ack_direction = np.where(np.abs(step) > 1e-9, np.sign(step), self._ack_direction)
        self._update(prev_cmd, prev_dir, np.asarray(ack.measured_um, dtype=float).reshape(-1))

    def _update(self, cmd: np.ndarray, direction: np.ndarray, y: np.ndarray) -> None:
        if y.shape != cmd.shape or not np.all(np.isfinite(y)):
            return  # a damaged ack teaches nothing
        phi = np.stack([cmd, np.ones_like(cmd), direction], axis=1)  # (n, 3)
        P_phi = np.einsum("nij,nj->ni", self.P, phi)
        denom = self.forgetting + np.einsum("ni,ni->n", phi, P_phi)
        k = P_phi / denom[:, None]
        err = y - np.einsum("ni,ni->n", phi, self.theta)
        self.theta = self.theta + k * err[:, None]
        self.P = (self.P - np.einsum("ni,nj->nij", k, P_phi)) / self.forgetting
        # Rounding makes the update drift from symmetric; after thousands of frames an asymmetric P turns
        # indefinite and the estimates run away (seen after ~9 s at 700 Hz). Keep it symmetric.
        self.P = 0.5 * (self.P + self.P.transpose(0, 2, 1))
        # Keep the covariance bounded while the movie does not excite a contactor (no wind-up).
        tr = np.trace(self.P, axis1=1, axis2=2)
        big = tr > 100.0
        if np.any(big):
            self.P[big] *= (100.0 / tr[big])[:, None, None]
        self.theta[:, 0] = np.clip(self.theta[:, 0], *self.gain_bounds)
        self.theta[:, 1:] = np.clip(self.theta[:, 1:], -self.max_correction_um, self.max_correction_um)
        self.updates += 1


# ------------------------------------------------------------------------------------------------- playback


@dataclass
class PlaybackResult:
    """What was played and measured. ``stopped`` is a reason string when the movie was cut short (safety)."""

    closed_loop: bool
    frames_total: int
    frames_played: int
    target_um: np.ndarray  # (k, 10, 10)
    command_um: np.ndarray  # (k, 10, 10) as limited by the driver
    measured_um: np.ndarray  # (k, 10, 10) from the acks, aligned to the target they answer (NaN: none)
    force_n: np.ndarray  # (k,) normal force when the frame was sent (NaN: no sensor)
    stopped: str = ""
    rested: bool = True
    late_frames: int = 0
    duration_s: float = 0.0
    path: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def frames_sent(self) -> int:
        """Frames that left the host (played minus those skipped because their slot had passed)."""
        return self.frames_played - int(self.extra.get("skipped_frames", 0))

    @property
    def complete(self) -> bool:
        return not self.stopped and self.frames_played == self.frames_total

    @property
    def rms_error_um(self) -> float:
        """RMS of measured - target over the played frames (skipping the first ``settle`` frames)."""
        return rms_tracking_error(self.target_um, self.measured_um, settle=self.extra.get("settle", 0))

    def summary(self) -> dict[str, Any]:
        return {
            "closed_loop": self.closed_loop,
            "frames_total": self.frames_total,
            "frames_played": self.frames_played,
            "stopped": self.stopped,
            "rested": self.rested,
            "late_frames": self.late_frames,
            "duration_s": self.duration_s,
            "rms_error_um": self.rms_error_um,
            "max_force_n": float(np.nanmax(self.force_n)) if np.any(np.isfinite(self.force_n)) else None,
            "path": str(self.path) if self.path else None,
        }


def rms_tracking_error(target_um: np.ndarray, measured_um: np.ndarray, *, settle: int = 0) -> float:
    """RMS position error (um) over frames with a measurement; NaN when there is none (a run stopped within its
    start-up frames): :func:`rms_text` says so in words."""
    t = np.asarray(target_um, float)[settle:]
    m = np.asarray(measured_um, float)[settle:]
    ok = np.isfinite(m)
    if not np.any(ok):
        return float("nan")
    return float(np.sqrt(np.mean((m[ok] - t[ok]) ** 2)))


def rms_text(rms_um: float) -> str:
    """An RMS error for people: "0.24 um", or "n/a" when no frame was measured after the start-up."""
    return f"{rms_um:.2f} um" if math.isfinite(rms_um) else "n/a (no measured frame after the start-up)"


def play_movie(
    display: TactileDisplay,
    movie_um: np.ndarray,
    *,
    rate_hz: float = 700.0,
    closed_loop: bool = True,
    corrector: ContactorCorrector | None = None,
    force=None,
    force_ceiling_n: float = 5.0,
    path: str | os.PathLike | None = None,
    metadata: Mapping[str, Any] | None = None,
    settle_frames: int = 0,
    progress: Callable[[str], None] | None = None,
    clock: Callable[[], float] = time.perf_counter,
    buffered: bool | None = None,
    overwrite: bool = False,
) -> PlaybackResult:
    """Play a (T, 10, 10) movie in micrometres at ``rate_hz``; return what was commanded and measured.

    Frames are streamed by :func:`skinstretch.drivers.display.movie_stream.stream_movie_buffered` (timed frames played by the
    display's FIFO) or :func:`skinstretch.drivers.display.movie_stream.stream_movie` (deadline-paced, pipelined acks); the
    per-frame callback feeds every new ack to the corrector, checks the force and returns the corrected command.

    Parameters
    ----------
    display : TactileDisplay
        An opened display; it is armed here and disarmed (contactors at rest) at the end, whatever happens.
    movie_um : ndarray (T, 10, 10)
        Target contactor positions per frame.
    rate_hz : float
        Frame rate, 1..700 Hz (the STReSS refresh rate, seed 2.1).
    closed_loop : bool
        Correct each contactor from the measured positions (:class:`ContactorCorrector`) or send targets as is.
    force : optional
        A force source with ``latest() -> (6,) or None`` (Fx Fy Fz Tx Ty Tz, N and N m).
    force_ceiling_n : float
        Normal force above which the movie stops and the contactors return to rest (safety), in (0, 50] N.
    path : path-like, optional
        Session file recording target, command, measured positions and force (streams ``display_target``,
        ``display_command``, ``display_measured``, ``force``), written after the movie so the deadline path
        never waits on the disk. A movie interrupted by an exception (Ctrl-C, a failing force sensor) still writes
        what it played, without measured positions, in a session marked failed with the exception. An existing
        file is refused before the first frame unless ``overwrite``.
    settle_frames : int
        Frames excluded from :attr:`PlaybackResult.rms_error_um` (the start-up transient).
    clock : callable
        The deadline clock, which must be the display driver's (``time.perf_counter``); replaceable in tests.
    buffered : bool or None
        Timed, buffered playback (True) or immediate frames (False); None: buffered for open loop on a display
        that supports it, immediate otherwise.
    """
    from skinstretch.drivers.display.movie_stream import stream_movie, stream_movie_buffered  # noqa: PLC0415

    movie = check_movie(movie_um)  # real and finite, or refused naming the frame and contactor
    rate_to_mhz(rate_hz)  # 1..700 Hz, the STReSS refresh rate
    if not (0 < force_ceiling_n <= MAX_FORCE_CEILING_N):
        raise InvalidInputError(f"force_ceiling_n must be in (0, {MAX_FORCE_CEILING_N:g}] N, got {force_ceiling_n!r}")
    if path is not None:
        # before the first frame: what is played must be recordable
        check_output_file(path, overwrite=overwrite, remedy=REPLACE_IT)
    if force is not None:
        require_force_sample(force)  # before the display is armed: a ceiling needs a sensor that speaks
    n = movie.shape[0]
    corrector = corrector or (ContactorCorrector() if closed_loop else None)
    forces = np.full((n, 6), np.nan)
    host_t = np.full(n, np.nan)
    intended = np.full((n, *SHAPE), np.nan)  # the host's command of each frame (kept for an interrupted movie)
    seen = [display.acks_received]
    done = [0]  # frames whose callback completed (they were sent unless the movie was interrupted just then)
    tripped: list[int] = []  # the frame whose force sample tripped the ceiling (it was never sent)

    def callback(k: int, command: np.ndarray, latest) -> np.ndarray | None:
        host_t[k] = time.time()
        intended[k] = command
        if force is not None:
            wrench = force.latest()
            if wrench is not None:
                forces[k] = wrench
                fz = abs(float(wrench[2]))
                if fz > force_ceiling_n:
                    tripped.append(k)
                    raise SafetyStop(f"normal force {fz:.2f} N above the ceiling {force_ceiling_n:.2f} N")
        if corrector is None:
            done[0] = k + 1
            return None
        new = display.acks_received - seen[0]
        if new:
            acks = display.acks
            for i in range(max(len(acks) - new, 0), len(acks)):  # bounded history: at most its length is new
                corrector.observe_ack(acks[i])  # near the deque's end: O(1)
            seen[0] = display.acks_received
        corrected = corrector.command(command)
        intended[k] = corrected
        done[0] = k + 1
        return corrected

    t0 = time.perf_counter()
    # A wider spin window leaves the callback (about 0.2 ms) inside the period instead of making frames late.
    # max_outstanding 64 (91 ms at 700 Hz) rides out a busy host; the firmware's watchdog still rests the
    # contactors after 50 ms without frames, whatever the host does.
    if buffered is None:
        buffered = not closed_loop and display.supports_timed_playback
    try:
        if buffered:
            report = stream_movie_buffered(display, movie, rate_hz=float(rate_hz), callback=callback,
                                           settle_frames=0, clock=clock)
        else:
            report = stream_movie(display, movie, rate_hz=float(rate_hz), callback=callback, spin_s=0.0008,
                                  settle_frames=0, max_outstanding=64, clock=clock)
    except BaseException as exc:
        # Ctrl-C or a bug in the middle of the movie: the streamer has rested the contactors; disarm them too and
        # keep what was played (targets, the host's commands, forces; no measurements) before re-raising.
        _to_rest(display)
        if path is not None:
            _record_interrupted(path, exc, played=done[0], movie=movie, host_t=host_t, intended=intended,
                                forces=forces, closed_loop=closed_loop, rate_hz=float(rate_hz), metadata=metadata,
                                force_ceiling_n=force_ceiling_n, started=t0)
        raise
    rested_now = _to_rest(display)  # always: disarm even when the link is gone (the watchdog rests it)
    rested = report.rested and rested_now
    duration = time.perf_counter() - t0
    sent = report.frames_played  # frames whose slot has come (sent, or skipped on a starved host)
    stopped = ""
    if report.outcome == "safety_stop":
        stopped = f"safety stop: {report.error}"
    elif report.outcome == "link_failure":
        stopped = f"safety stop: display link failed ({report.error})"
    # measured[k] is the response to frame k - 1: file it under the frame whose target it answers.
    measured = np.full((sent, *SHAPE), np.nan)
    # The ack of a sent frame reports the response to the previous *sent* frame (skipped frames never left).
    sent_idx = np.nonzero(~np.asarray(report.skipped[:sent], bool))[0]
    for prev, nxt in zip(sent_idx[:-1], sent_idx[1:]):
        if report.acked[nxt]:
            measured[prev] = report.measured_um[nxt]
    result = PlaybackResult(
        closed_loop=closed_loop,
        frames_total=n,
        frames_played=sent,
        target_um=movie[:sent],
        command_um=report.commands_um,
        measured_um=measured,
        force_n=np.abs(forces[:sent, 2]),
        stopped=stopped,
        rested=rested,
        late_frames=report.missed_deadlines,
        duration_s=duration,
        path=Path(path) if path is not None else None,
        extra={"settle": min(settle_frames, max(sent - 1, 0)), "lost_acks": report.lost_acks,
               "skipped_frames": report.frames_skipped,
               "period_jitter_p99_s": report.period_jitter_p99_s, "rate_hz": float(rate_hz)},
    )
    if tripped:
        result.extra["ceiling_sample"] = {"frame": tripped[0], "t": float(host_t[tripped[0]]),
                                          "wrench": forces[tripped[0]].tolist()}
    if path is not None:
        # the force stream runs to the sample that tripped the ceiling, one frame past the last one sent
        n_force = max(sent, tripped[0] + 1) if tripped else sent
        _record_playback(path, result, host_t[:sent], (host_t[:n_force], forces[:n_force]), metadata=metadata,
                         force_ceiling_n=force_ceiling_n)
    if progress is not None:
        progress(
            f"  playback ({'closed' if closed_loop else 'open'} loop): {sent}/{n} frames at {rate_hz:g} Hz, "
            f"RMS error {rms_text(result.rms_error_um)}, {result.late_frames} late"
            + (f", STOPPED: {stopped}" if stopped else "")
        )
    return result


def require_force_sample(force, *, timeout_s: float = 2.0) -> None:
    """DeviceTimeoutError unless ``force`` (``latest() -> (6,) or None``) delivers a sample within ``timeout_s``:
    a force ceiling on a sensor that never answers would protect nobody, so the movie is not started."""
    deadline = time.monotonic() + timeout_s
    while force.latest() is None:
        if time.monotonic() > deadline:
            raise DeviceTimeoutError(f"force sensor {getattr(force, 'description', force)}: no sample within "
                                     f"{timeout_s:g} s; the force ceiling cannot be enforced, so the movie was not "
                                     "started")
        time.sleep(0.02)


def _record_playback(path, result: PlaybackResult, t: np.ndarray, force: tuple[np.ndarray, np.ndarray], *, metadata,
                     force_ceiling_n):
    """Write a played movie's streams; ``t`` times the played frames, ``force`` is (times, wrenches) of every
    force sample taken (NaN rows: none that frame), the one that tripped the ceiling included. A log already at
    ``path`` (which :func:`play_movie` let through only with ``overwrite``) is replaced once the new one is closed."""
    path = Path(path)
    fresh = path.with_name(f".{path.name}.new") if path.exists() else path
    mode = CAMERA_MODES["full"]
    writer = SessionWriter(
        fresh,
        camera_mode=mode,
        calibration=Calibration(px_per_mm=mode.width / 10.3),
        metadata={"kind": "playback", "closed_loop": result.closed_loop, "frames": result.frames_total,
                  "rate_hz": result.extra.get("rate_hz"), "force_ceiling_n": force_ceiling_n,
                  "rms_error_um": result.rms_error_um, **dict(metadata or {})},
        streams={
            "display_target": (SHAPE, "f4"),
            "display_command": (SHAPE, "f4"),
            "display_measured": (SHAPE, "f4"),
            "force": ((6,), "f8"),
        },
    )
    try:
        try:
            k = result.frames_played
            if k:
                writer.append_samples("display_target", t, result.target_um.astype(np.float32))
                writer.append_samples("display_command", t, result.command_um.astype(np.float32))
                writer.append_samples("display_measured", t, result.measured_um.astype(np.float32))
            force_t, forces = force
            ok = np.all(np.isfinite(forces), axis=1)
            if np.any(ok):
                writer.append_samples("force", force_t[ok], forces[ok])
        except BaseException as exc:
            writer.fail(f"{type(exc).__name__}: {exc}")
            raise
        if result.stopped:
            writer.fail(result.stopped)
        else:
            writer.close()
    finally:
        if fresh != path:
            os.replace(fresh, path)


def _record_interrupted(path, exc: BaseException, *, played, movie, host_t, intended, forces, closed_loop, rate_hz,
                        metadata, force_ceiling_n, started) -> None:
    """The log of a movie cut short by an exception: the frames whose callback completed, with the host's commands
    (before the driver's limits) and no measured positions; the session is marked failed with the exception."""
    k = int(played)
    reason = f"interrupted: {type(exc).__name__}: {exc}"
    result = PlaybackResult(
        closed_loop=closed_loop, frames_total=movie.shape[0], frames_played=k, target_um=movie[:k],
        command_um=intended[:k], measured_um=np.full((k, *SHAPE), np.nan), force_n=np.abs(forces[:k, 2]),
        stopped=reason, rested=False, duration_s=time.perf_counter() - started, path=Path(path),
        extra={"rate_hz": rate_hz},
    )
    try:
        _record_playback(path, result, host_t[:k], (host_t[:k], forces[:k]),
                         metadata={**dict(metadata or {}), "command_source": "host, before the driver's limits"},
                         force_ceiling_n=force_ceiling_n)
    except Exception:  # noqa: BLE001 - the original exception matters more; the file says what it holds
        pass


def _to_rest(display: TactileDisplay) -> bool:
    """Every contactor back to rest: REST then DISARM; if the link is gone the firmware watchdog does it."""
    ok = True
    try:
        display.rest()
    except (DeviceError, OSError):
        ok = False
    try:
        display.disarm()
    except (DeviceError, OSError):
        ok = False
    return ok


# ------------------------------------------------------------------------------------------------- movies


def load_movie(source: str | os.PathLike) -> tuple[np.ndarray, float | None]:
    """Read a tactile movie: a ``.npy`` (T, 10, 10) um, an ``.h5`` with a ``movie`` dataset (or a results file),
    or an analysed results directory. Returns (movie_um, rate_hz or None)."""
    p = Path(source)
    if not p.exists():
        raise SessionFileError(f"{p}: no such movie file or results directory")
    if p.is_dir() or (p.suffix == ".h5" and _is_results(p)):
        from skinstretch.experiments.results_file import read_results  # noqa: PLC0415

        results = read_results(p)
        if results.tactile_positions_um is None:
            raise SessionFileError(f"{p}: the analysis produced no tactile movie (see its summary for why)")
        rate = None
        try:
            with open_session(results.session_path) as s:
                rate = float(s.camera_mode.fps)  # one movie frame per camera frame (seed 5.4)
        except SessionFileError:
            pass
        return _check_movie(results.tactile_positions_um, p, analysed=True), rate
    if p.suffix == ".npy":
        try:
            raw = np.load(p, allow_pickle=False)
        except ValueError as exc:
            raise SessionFileError(f"{p}: not a readable .npy movie ({exc})") from None
        return _check_movie(raw, p), None
    if p.suffix in (".h5", ".hdf5"):
        import h5py  # noqa: PLC0415

        try:
            with h5py.File(p, "r") as f:
                for key in ("movie", "tactile_movie", "movie/positions_um"):
                    if key in f and isinstance(f[key], h5py.Dataset):
                        rate = f[key].attrs.get("rate_hz")
                        return _check_movie(f[key][()], p), (float(rate) if rate is not None else None)
        except OSError as exc:
            raise SessionFileError(f"{p}: HDF5 file cannot be read ({exc})") from None
        raise SessionFileError(f"{p}: HDF5 file has no 'movie' dataset")
    raise SessionFileError(f"{p}: a movie is a .npy or .h5 file or a results directory")


def _is_results(p: Path) -> bool:
    import h5py  # noqa: PLC0415

    try:
        with h5py.File(p, "r") as f:
            fmt = f.attrs.get("format")
            return (fmt.decode() if isinstance(fmt, bytes) else fmt) == "skinstretch-results"
    except OSError:
        return False


def fit_movie(movie_um: np.ndarray, *, peak_um: float = 30.0) -> tuple[np.ndarray, float]:
    """Scale a movie down (never up) so its largest excursion is ``peak_um``; returns (movie, scale).

    The display's contactors reach +/-50 um unloaded but less under the finger (bender and skin in series), and
    the closed loop needs headroom to correct: a target beyond reach is an error no controller can remove.
    """
    movie = np.asarray(movie_um, float)
    if not (np.isfinite(peak_um) and peak_um > 0):
        raise InvalidInputError(f"peak_um must be positive, got {peak_um!r}")
    peak = float(np.max(np.abs(movie))) if movie.size else 0.0
    scale = 1.0 if peak <= peak_um else peak_um / peak
    return movie * scale, scale


def resample_movie(movie_um: np.ndarray, *, from_hz: float, to_hz: float) -> np.ndarray:
    """Linear interpolation of a movie to the display's frame rate (e.g. 60 Hz camera -> 700 Hz display)."""
    movie = np.asarray(movie_um, float)
    if not (from_hz > 0 and to_hz > 0):
        raise InvalidInputError(f"rates must be positive, got from_hz={from_hz!r} to_hz={to_hz!r}")
    n = movie.shape[0]
    if n < 2 or from_hz == to_hz:
        return movie.copy()
    t_src = np.arange(n) / from_hz
    t_dst = np.arange(int(np.floor(t_src[-1] * to_hz)) + 1) / to_hz
    flat = movie.reshape(n, -1)
    out = np.empty((t_dst.size, flat.shape[1]))
    for j in range(flat.shape[1]):
        out[:, j] = np.interp(t_dst, t_src, flat[:, j])
    return out.reshape(t_dst.size, *movie.shape[1:])


def _check_movie(movie: np.ndarray, source: Path, *, analysed: bool = False) -> np.ndarray:
    """The movie as floats, refused like a display target (complex, not numbers, NaN, inf, another shape), naming
    the frame and contactor. An ``analysed`` movie (one the analysis wrote) has NaN where a contactor was not
    measured: those are reset to rest (seed 5.4: "its position is reset"), as the analysis means them."""
    raw = np.asarray(movie)
    if analysed and raw.dtype.kind == "f":
        raw = np.where(np.isnan(raw), 0.0, raw)
    return check_movie(raw, name=str(source))


def play_protocol_movie(protocol, session_directory: Path, *, devices,
                        progress=logging.getLogger(__name__).info) -> PlaybackResult:
    """Play the protocol's movie (``movie.source``: a trial name, ``last_trial``, or a file) on the rig's display."""
    spec = protocol.movie
    sdir = Path(session_directory)
    source = spec.source
    trial_dirs = sorted(d for d in sdir.iterdir() if d.is_dir() and (d / "analysis").exists())
    if source == "last_trial":
        if not trial_dirs:
            raise SessionFileError(f"{sdir}: no analysed trial to take a movie from")
        movie_path = trial_dirs[-1] / "analysis"
    elif any(d.name.split("-", 1)[-1].rsplit("-r", 1)[0] == source for d in trial_dirs):
        movie_path = [d for d in trial_dirs if d.name.split("-", 1)[-1].rsplit("-r", 1)[0] == source][0] / "analysis"
    else:
        movie_path = Path(source)
    movie, rate = load_movie(movie_path)
    movie, _ = fit_movie(movie * spec.gain)
    display_rate = float(spec.rate_hz or 700.0)
    if rate is not None and rate != display_rate:
        movie = resample_movie(movie, from_hz=rate, to_hz=display_rate)
    out = check_output_dir(sdir / "playback")
    out.mkdir(exist_ok=True)
    k = 1
    while (out / f"playback-{k}.h5").exists():
        k += 1
    progress(f"playback of {movie_path} ({movie.shape[0]} frames, gain {spec.gain}) "
             f"{'closed' if spec.closed_loop else 'open'} loop")
    return play_movie(
        devices.display_device(),
        movie,
        rate_hz=display_rate,
        settle_frames=min(100, movie.shape[0] // 5),
        closed_loop=spec.closed_loop,
        force=devices.force,
        force_ceiling_n=spec.force_ceiling_n,
        path=out / f"playback-{k}.h5",
        metadata={"movie": str(movie_path), "gain": spec.gain},
        progress=progress,
    )

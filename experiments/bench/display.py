"""Bench section ``display``: 700 Hz tactile-movie playback on the simulated STReSS display over each transport,
in the two playback modes: *immediate* (each frame sent at its deadline, applied when it arrives) and *buffered*
(timed frames sent ``lead_s`` ahead with their play tick, played by the firmware's FIFO on its own timer).

Speed: missed deadlines and period jitter, on the host's send clock and on the firmware simulator's clocks: its
receive clock (the time the last byte of each frame arrives on the modelled 2 Mbaud line) and, in buffered mode,
its playout clock (the scheduled tick at which each frame was applied: what the skin gets). Missed deadlines on
the firmware clock are counted from the simulator's own record: in buffered mode a frame that arrived at or after
its play time, or never arrived, missed its deadline; in immediate mode a frame that arrived more than a quarter
period after its slot on the ideal grid (fitted to the earliest arrival). A second table says where the sending
loop lost the CPU (stalls located by loop phase, from the per-frame phase stamps), next to the same deadline loop
with no display at all: the floor the machine itself sets. Error: open-loop position error per contactor from the
acks (immediate: measured position when frame k arrives minus the command of frame k - 1; buffered: measured at
tick k, before frame k takes effect, minus the command of frame k - 1).

The host loop asks for SCHED_FIFO when it may (root on Linux): a playback loop on a lab PC would run so, and on
a shared 2-core machine nothing else gives sub-millisecond wake-ups. The table says whether it was granted.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.drivers.display.movie_stream import (DEFAULT_LEAD_S, PHASES, BufferedPlaybackReport, PlaybackReport, find_stalls,
                                      stream_movie, stream_movie_buffered)
from skinstretch.drivers.display.stress import StressDisplay
from skinstretch.drivers.display.transports import SerialTransport, UsbTransport
from skinstretch.experiments.bench import BenchOptions, BenchTable
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators import stress_links
from skinstretch.simulators.stress_firmware import StressFirmware
from skinstretch.simulators.stress_wire import PacedLink, RealClock

SECTION = "display"
DESCRIPTION = "STReSS playback at 700 Hz: missed deadlines, period jitter (host and firmware clock), position error"

RATE_HZ = 700.0
JITTER_TARGET_S = 0.3e-3
# A benchmark on a shared machine measures stalls rather than aborting on them: the watchdog and the
# unacknowledged-frame window are widened (the safety defaults are 50 ms and 32 frames; tests cover them).
BENCH_WATCHDOG_S = 0.5
MAX_OUTSTANDING = 200
DRIVER_OPTIONS = {"watchdog_s": BENCH_WATCHDOG_S, "ack_timeout_s": 0.2}
# Buffered playback runs with the driver's safety defaults (50 ms watchdog, 50 ms ack timeout): the FIFO, not a
# widened watchdog, is what rides out a stalled host.
BUFFERED_DRIVER_OPTIONS: dict = {}
STALL_S = 0.004  # a gap this long between two stamps of the loop is a stall (about 3 frame periods)
SPIN_S = 0.0007  # busy-wait before each deadline: covers the p99 wake-up overshoot measured here (~0.45 ms)


def travelling_wave(n_frames: int, *, rate_hz: float = RATE_HZ, amplitude_um: float = 20.0,
                    frequency_hz: float = 8.0) -> np.ndarray:
    """A stretch wave crossing the array (1 mm pitch, 40 mm/s): every contactor moves, none exceeds the slew."""
    t = np.arange(n_frames)[:, None, None] / rate_hz
    x_mm = np.arange(sp.COLS)[None, None, :] + 0.3 * np.arange(sp.ROWS)[None, :, None]
    return amplitude_um * np.sin(2 * np.pi * frequency_hz * (t - x_mm / 40.0))


class _RealtimePriority:
    """SCHED_FIFO for this thread while inside the block, when the OS allows it (restored after).

    Threads and processes started inside the block (the USB reader, the firmware process) inherit the policy.
    (Locking memory with mlockall as well was tried: no fewer stalls on this machine, 108 MB more resident.)
    """

    def __enter__(self) -> "_RealtimePriority":
        self.granted = False
        self._saved = None
        if hasattr(os, "sched_setscheduler"):
            try:
                self._saved = (os.sched_getscheduler(0), os.sched_getparam(0))
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
                self.granted = True
            except (OSError, PermissionError):
                self.granted = False
        return self

    def __exit__(self, *exc) -> None:
        if self.granted and self._saved is not None:
            os.sched_setscheduler(0, self._saved[0], self._saved[1])


def _timer_only(n_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The playback loop's timing with no display: wait (sleep) to ``SPIN_S`` before each deadline, then spin.

    Returns (lateness s, phase times (frames, len(PHASES)) relative to the first deadline, thread CPU s): the
    floor the machine itself sets, to compare the transports' rows with.
    """
    period = 1.0 / RATE_HZ
    clock = time.perf_counter
    phases = np.full((n_frames, len(PHASES)), np.nan)
    cpu = np.full(n_frames, np.nan)
    late = np.full(n_frames, 0.0)
    t0 = clock() + 2 * period
    for k in range(n_frames):
        deadline = t0 + k * period
        now = clock()
        phases[k, 0] = now - t0
        cpu[k] = time.thread_time()
        remaining = deadline - now - SPIN_S
        if remaining > 0:
            time.sleep(remaining)
        phases[k, 1] = phases[k, 2] = clock() - t0
        while clock() < deadline:
            pass
        now = clock()
        phases[k, 3] = phases[k, 4] = now - t0
        late[k] = now - deadline
    return late, phases, cpu - cpu[0]


def _stall_row(name: str, missed: int, stalls: list, load: tuple[float, float]) -> list:
    """Where a loop lost the CPU: count, total and longest stall, split by loop phase and by CPU charge."""
    durations = np.array([s.duration_s for s in stalls])
    where = {"waited": 0, "prepared": 0, "send": 0, "sent": 0, "start": 0}  # the phase each gap ended in
    for s in stalls:
        where[s.after] += 1
    on_cpu = sum(1 for s in stalls if np.isfinite(s.thread_cpu_s) and s.thread_cpu_s > 0.5 * s.duration_s)
    return [name, missed, len(stalls), float(durations.sum() * 1e3) if stalls else 0.0,
            float(durations.max() * 1e3) if stalls else 0.0, *where.values(), on_cpu, load[0], load[1]]


def _load() -> float:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def _jitter(times_s: np.ndarray) -> tuple[float, float]:
    if len(times_s) < 2:
        return float("nan"), float("nan")
    dev = np.abs(np.diff(times_s) - 1.0 / RATE_HZ)
    return float(np.percentile(dev, 99)), float(dev.max())


def _p99_max(values: np.ndarray) -> tuple[float, float]:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return (float(np.percentile(v, 99)), float(v.max())) if v.size else (float("nan"), float("nan"))


def _play(display: StressDisplay, movie: np.ndarray) -> PlaybackReport:
    display.identify()
    display.zero()
    display.arm()
    report = stream_movie(display, movie, rate_hz=RATE_HZ, settle_frames=20, spin_s=SPIN_S,
                          max_outstanding=MAX_OUTSTANDING)
    display.close()
    return report


def _play_buffered(display: StressDisplay, movie: np.ndarray) -> BufferedPlaybackReport:
    display.identify()
    display.zero()
    # armed inside, after its allocations: with the 50 ms safety watchdog there is no room for them in between
    report = stream_movie_buffered(display, movie, rate_hz=RATE_HZ, settle_frames=20)
    display.close()
    return report


def _immediate_fw_missed(report: PlaybackReport, arrivals: np.ndarray) -> int:
    """Frames that reached the firmware more than a quarter period after their slot on the ideal grid (fitted to
    the earliest arrival), or never: the receive-clock count of missed deadlines in immediate mode."""
    sent = np.flatnonzero(~report.skipped)
    if arrivals.size != sent.size or sent.size == 0:  # a frame lost on the wire: pair what can be paired
        m = min(arrivals.size, sent.size)
        sent, arrivals = sent[:m], arrivals[:m]
    slots = sent / RATE_HZ
    late = arrivals - slots - np.min(arrivals - slots)
    return int(np.sum(late > 0.25 / RATE_HZ) + (report.frames_played - sent.size))


def _buffered_fw(record: dict[str, np.ndarray], n_frames: int) -> dict[str, float]:
    """Missed deadlines, receive and playout jitter and simulator lag from the firmware simulator's own record."""
    ticks, play, arrival = record["timed_ticks"], record["timed_play_times"], record["timed_arrivals"]
    disposition = record["timed_dispositions"]
    reached = min(len(record["tick_times"]), n_frames)  # ticks the movie timer ran
    in_time = (arrival < play) & (disposition == int(sp.Disposition.QUEUED)) & (ticks < reached)
    missed = reached - np.unique(ticks[in_time]).size  # late, lost, or never sent
    order = np.argsort(ticks, kind="stable")
    rx_p99, rx_max = _jitter(arrival[order])
    applied = record["tick_applied"].astype(bool)
    play_p99, play_max = _jitter(record["tick_times"][applied])
    lag_p99, lag_max = _p99_max(record["tick_computed_at"] - record["tick_times"])
    return {"missed": int(missed), "rx_p99": rx_p99, "rx_max": rx_max, "play_p99": play_p99, "play_max": play_max,
            "lag_p99": lag_p99, "lag_max": lag_max, "late": int(np.sum((disposition == int(sp.Disposition.LATE)))),
            "underruns": int(reached - applied[:reached].sum())}


_errors: list[str] = []


def _errors_um(report: PlaybackReport) -> tuple[float, float, float]:
    try:
        rms = report.position_rms_error_um()
        bias = report.position_mean_error_um()
        return float(rms.mean()), float(rms.max()), float(np.abs(bias).mean())
    except InvalidInputError:  # no acks: the table shows n/a
        return float("nan"), float("nan"), float("nan")


def _row(name: str, report: PlaybackReport, firmware_times: np.ndarray, fifo: bool) -> list:
    """An immediate-mode row: the firmware applies each frame when it arrives (receive clock = playout clock)."""
    fw_p99, fw_max = _jitter(firmware_times)
    if report.error:
        _errors.append(f"{name} (immediate): {report.outcome}: {report.error}")
    fw_missed = _immediate_fw_missed(report, np.asarray(firmware_times))
    late = report.lateness_s
    met = report.completed and fw_missed == 0 and fw_p99 <= JITTER_TARGET_S
    return [name, "immediate", fifo, report.frames_played, report.missed_deadlines, fw_missed, "-",
            float(np.percentile(late, 99) * 1e3) if late.size else float("nan"),
            report.period_jitter_p99_s * 1e3, fw_p99 * 1e3, fw_p99 * 1e3, fw_max * 1e3, float("nan"),
            report.lost_acks, *_errors_um(report), met, report.outcome]


def _buffered_row(name: str, report: BufferedPlaybackReport, record: dict[str, np.ndarray], fifo: bool) -> list:
    """A buffered-mode row: the firmware applies each frame at its tick; the playout clock is the tick schedule."""
    fw = _buffered_fw(record, report.frames_total)
    if report.error:
        _errors.append(f"{name} (buffered): {report.outcome}: {report.error}")
    if fw["late"] != report.late_frames or fw["underruns"] != report.underruns:  # the wire must tell the truth
        _errors.append(f"{name} (buffered): host report says {report.late_frames} late / {report.underruns} "
                       f"underruns, the simulator recorded {fw['late']} / {fw['underruns']}")
    met = report.completed and fw["missed"] == 0 and fw["play_p99"] <= JITTER_TARGET_S
    return [name, f"buffered {report.lead_s * 1e3:.0f} ms", fifo, report.frames_played, report.missed_deadlines,
            fw["missed"], report.underruns, -report.min_arrival_margin_s * 1e3, report.period_jitter_p99_s * 1e3,
            fw["rx_p99"] * 1e3, fw["play_p99"] * 1e3, fw["play_max"] * 1e3, fw["lag_p99"] * 1e3,
            report.lost_acks, *_errors_um(report), met, report.outcome]


def run(options: BenchOptions) -> list[BenchTable]:
    seconds = options.seconds or (3.0 if options.quick else 60.0)
    movie = travelling_wave(int(seconds * RATE_HZ))
    stress_links.register_url_handler()
    rows, grids, notes = [], {}, []
    workdir = Path(options.workdir) if options.workdir else Path(tempfile.gettempdir())
    workdir.mkdir(parents=True, exist_ok=True)

    stall_rows = []

    def played(name: str, report: PlaybackReport, fw_times, load_before: float) -> None:
        rows.append(_row(name, report, np.asarray(fw_times), priority.granted))
        stall_rows.append(_stall_row(name, report.missed_deadlines, report.stalls(STALL_S), (load_before, _load())))

    def played_buffered(name: str, report: BufferedPlaybackReport, record: dict, load_before: float) -> None:
        rows.append(_buffered_row(name, report, record, priority.granted))
        stall_rows.append(_stall_row(f"{name}, buffered", report.missed_deadlines, report.stalls(STALL_S),
                                     (load_before, _load())))

    def url_link(name: str, *, finger_load: bool) -> tuple:
        link = stress_links.make_link(seed=1)
        if finger_load:  # skin as stiff as a bender, half of it, on the centre of the array
            load = np.zeros((sp.ROWS, sp.COLS))
            load[3:7, 3:7] = 0.25
            link.firmware.benders.set_load(load)
        return link, stress_links.attach(name, link)

    with _RealtimePriority() as priority:
        # 0. the same deadline loop with no display at all: what the machine alone costs
        load_before = _load()
        late, phases, cpu = _timer_only(len(movie))
        stall_rows.append(_stall_row("timer only (no display)", int(np.sum(late > 0.25 / RATE_HZ)),
                                     find_stalls(phases, cpu, min_gap_s=STALL_S), (load_before, _load())))

        # 1. pyserial URL: the firmware runs on the host's calls; its clock is the modelled line
        for finger_load, name in ((False, "stresssim:// (in process)"), (True, "stresssim:// + finger load")):
            load_before = _load()
            link, url = url_link("bench_url", finger_load=finger_load)
            report = _play(StressDisplay(SerialTransport(url), **DRIVER_OPTIONS), movie)
            played(name, report, link.firmware.frame_times, load_before)
            stress_links.detach("bench_url")

            load_before = _load()
            link, url = url_link("bench_url", finger_load=finger_load)
            report = _play_buffered(StressDisplay(SerialTransport(url), **BUFFERED_DRIVER_OPTIONS), movie)
            link.advance()
            played_buffered(name, report, link.firmware.timed.as_arrays(), load_before)
            stress_links.detach("bench_url")
            if finger_load:
                grids["stresssim:// + load 0.25 N/mm on rows/cols 3-6, buffered"] = report
            else:
                grids["stresssim://, buffered"] = report

        # 3. a real pty to the firmware in its own process (kernel tty path, two schedulers)
        name = "pty + firmware process"
        for buffered in (False, True):
            load_before = _load()
            record = workdir / f"display-firmware-{os.getpid()}.npz"
            options_ = BUFFERED_DRIVER_OPTIONS if buffered else DRIVER_OPTIONS
            with stress_links.FirmwareProcess(record_path=record, seed=1) as firmware:
                display = StressDisplay(SerialTransport(firmware.port), **options_)
                report = (_play_buffered if buffered else _play)(display, movie)
            records = firmware.records()
            record.unlink(missing_ok=True)
            if buffered:
                played_buffered(name, report, records, load_before)
            else:
                played(name, report, records["frame_times"], load_before)

        # 4. pyusb bulk endpoints (high-speed USB model: 125 us microframe latency)
        name = "USB bulk (pyusb backend)"
        for buffered in (False, True):
            load_before = _load()
            link = PacedLink.usb_high_speed(StressFirmware(seed=1, t0=time.perf_counter()), clock=RealClock())
            options_ = BUFFERED_DRIVER_OPTIONS if buffered else DRIVER_OPTIONS
            display = StressDisplay(UsbTransport(backend=stress_links.StressUsbBackend(link)), **options_)
            report = (_play_buffered if buffered else _play)(display, movie)
            link.advance()
            if buffered:
                played_buffered(name, report, link.firmware.timed.as_arrays(), load_before)
            else:
                played(name, report, link.firmware.frame_times, load_before)

    notes.extend(_errors)
    _errors.clear()
    load1 = _load()
    notes.append(f"{seconds:.0f} s at {RATE_HZ:.0f} Hz per row ({len(movie)} frames), travelling wave 20 um / 8 Hz; "
                 f"2 Mbaud 8N1 link model; machine load average {load1:.1f} on {os.cpu_count()} cores.")
    notes.append(f"immediate rows: watchdog {BENCH_WATCHDOG_S} s, window {MAX_OUTSTANDING} frames, "
                 f"spin {SPIN_S * 1e3:.1f} ms before each deadline (defaults 50 ms / 32 frames / 0.4 ms); "
                 f"buffered rows: lead {DEFAULT_LEAD_S * 1e3:.0f} ms (one frame a period), the driver's safety "
                 f"defaults (watchdog 50 ms), no spin.")
    notes.append("missed (host) = immediate: sent more than a quarter period after its deadline or skipped; "
                 "buffered: late frames the firmware reported plus frames the host skipped (play time passed). "
                 "missed (fw) = from the firmware simulator's record: buffered, a tick whose frame did not arrive "
                 "before its play time (late, lost or never sent); immediate, a frame arriving > 1/4 period after "
                 "its slot on the ideal grid.")
    notes.append("late/margin ms = immediate: host send lateness p99; buffered: the smallest lead a frame had "
                 "when it reached the firmware, negated (-80 = 80 ms early; > 0 would be a late frame).")
    notes.append("jitter = |period - 1/700 s|, p99 unless max. host = send times; rx = firmware receive clock "
                 "(last byte on the modelled line; in buffered mode arrivals need not be regular); playout = "
                 "when frames take effect: immediate, the receive clock; buffered, the firmware timer's tick "
                 "times of the applied frames (1 us timer: 1428/1429 us; an underrun shows as a 1.43 ms gap).")
    notes.append("sim lag = buffered: how late (wall clock) the simulator actually computed each tick after its "
                 "scheduled time. The bender physics is stepped at the scheduled time whatever the lag, as a timer "
                 "interrupt would; in process the simulator runs on the host's calls, so this lag is the host's, "
                 "not something a microcontroller would show. Arrival times are the modelled line's, from when "
                 "the host (or the firmware process) actually wrote (read) the bytes.")
    notes.append(f"target: 0 missed (fw) and playout jitter p99 <= {JITTER_TARGET_S * 1e3:.1f} ms.")
    notes.append("position error = measured - command of frame k-1 (immediate: ack of frame k; buffered: the tick "
                 "report of tick k), first 20 frames excluded; includes lag (tau 0.4 ms), hysteresis (+/-0.6 um), "
                 "gain spread 3 %, 0.5 um quantisation.")
    speed = BenchTable(
        title="display: 700 Hz playback on the simulated STReSS (speed and open-loop error)",
        columns=["transport", "mode", "SCHED_FIFO", "frames", "missed (host)", "missed (fw)", "underruns",
                 "late/margin ms", "host jitter p99 ms", "rx jitter p99 ms", "playout jitter p99 ms",
                 "playout jitter max ms", "sim lag p99 ms", "lost acks", "RMS err um (mean)", "RMS err um (worst)",
                 "|bias| um (mean)", "target met", "outcome"],
        rows=rows, notes=notes)

    stalls = BenchTable(
        title=f"display: where the sending loop lost the CPU (gaps >= {STALL_S * 1e3:.0f} ms between phase stamps)",
        columns=["loop", "missed", "stalls", "stalled ms", "longest ms", "in wait", "in callback+prepare",
                 "in spin", "in send", "between frames", "thread on CPU", "load before", "load after"],
        rows=stall_rows,
        notes=["a stall is a gap between consecutive stamps of the loop (PlaybackReport.phase_times_s); 'thread on "
               "CPU' counts stalls whose time was charged to the sending thread (kernel, interrupt or hypervisor "
               "time billed to it), the others are time it was not running at all (late wake-up, preempted, "
               "vCPU stolen, GIL held elsewhere).",
               "'timer only' is the same sleep-then-spin loop with no display, transport or firmware: stalls there "
               "come from the machine, not from the playback code."])
    tables = [speed, stalls]
    for name, report in grids.items():
        try:
            rms = report.position_rms_error_um()
        except InvalidInputError:
            continue
        tables.append(BenchTable(
            title=f"display: open-loop RMS position error per contactor (um), {name}",
            columns=["row"] + [f"c{c}" for c in range(sp.COLS)],
            rows=[[r] + [float(v) for v in rms[r]] for r in range(sp.ROWS)]))

    budget_rows = []
    for baud in (1_000_000, 2_000_000, 3_000_000):
        b = sp.link_budget(rate_hz=RATE_HZ, baud=baud)
        budget_rows.append([f"UART {baud / 1e6:.0f} Mbaud", "immediate", b["frame_bytes"], b["ack_bytes"],
                            b["frame_time_s"] * 1e3, b["frame_utilisation"], b["ack_utilisation"]])
        budget_rows.append([f"UART {baud / 1e6:.0f} Mbaud", "buffered", b["timed_frame_bytes"],
                            b["timed_reply_bytes"], b["timed_frame_bytes"] * 10 / baud * 1e3,
                            b["timed_frame_utilisation"], b["timed_reply_utilisation"]])
    tables.append(BenchTable(
        title="display: link budget at 700 Hz (frame = 100 int8 positions, 0.5 um steps, 7 bytes framing; "
              "a timed frame adds its tick, its reply a tick report)",
        columns=["link", "mode", "frame bytes", "reply bytes", "frame time ms", "host->display load",
                 "display->host load"],
        rows=budget_rows,
        notes=[f"minimum line rate for frames alone: {sp.link_budget(rate_hz=RATE_HZ, baud=1)['min_baud']} baud."]))
    return tables

"""Bench section ``faults``: the fault matrix. Each fault is injected on purpose, the way it happens in a lab, and
the table says how long until it was detected, what was kept, where the display was left and the exit status.

Faults: SIGKILL of ``record`` mid-trial (analysis on), a disk that fills mid-trial (a 50 MB tmpfs filled by another
process when root, an injected full disk otherwise), a camera that stalls, the display link at end-of-file
(unplugged), stalled and killed (the firmware process), a force above the ceiling, a corrupt and a truncated
session file (given to ``analyze`` and to ``view``), a truncated video given to ``import``, a protocol with a typo;
the drill of issue 41: ``record --live`` (the viewer reading the file while the recorder writes after the trial),
two ``analyze`` runs into one OUTDIR, a force sensor that never answers, a complex and a NaN movie given to
``play``, SIGTERM of ``record`` mid-trial.

"Detected after" is the time from the fault to the moment the program acted on it (stopped the trial or movie,
refused the file), measured on the host clock; for SIGKILL, to the moment the last process of the killed
command's session was gone. "Kept" is what a reader finds afterwards; for recordings, "lost" is the time between
the fault and the last frame in the file (the camera period is part of it). Every row also runs the command a
user would run and reports its exit status. All on the simulated rig of this machine, under whatever load it has.
"""

from __future__ import annotations

import math
import os
import shutil
import select
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.errors import SessionFileError
from skinstretch.drivers.session_file import open_session, write_session
from skinstretch.experiments.bench import BenchOptions, BenchTable
from skinstretch.experiments.runner import read_events
from skinstretch.processing.pixel_scale import Calibration

SECTION = "faults"
#: Runs of a scenario before its row is reported not as designed (see the notes of the table).
ATTEMPTS = 3

DESCRIPTION = ("fault matrix: SIGKILL, disk full, camera stall, display EOF/stall/kill, force ceiling, bad files "
               "and videos, bad protocol, live view, one OUTDIR twice, silent force sensor, bad movies, SIGTERM")

COLUMNS = ["fault", "injected", "detected after s", "kept", "display", "exit status", "as designed"]
CLI = [sys.executable, "-m", "skinstretch.cli"]
CAL = Calibration(px_per_mm=640 / 10.3)


@dataclass
class _Row:
    fault: str
    injected: str
    detected_s: float
    kept: str
    display: str
    exit_status: str
    ok: bool

    def cells(self) -> list:
        return [self.fault, self.injected, self.detected_s, self.kept, self.display, self.exit_status,
                "yes" if self.ok else "NO"]


def _cli(*args: str, timeout_s: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=timeout_s)


def _one_line(err: str) -> bool:
    return len(err.strip().splitlines()) == 1 and "Traceback" not in err


def _protocol(path: Path, trials: list[tuple[str, float, str]], *, mode: str = "full", analysis: bool = False) -> Path:
    body = "\n".join(f"  - {{name: {n}, duration_s: {d}, surface: {{kind: {k}}}}}" for n, d, k in trials)
    path.write_text(f"name: {path.stem}\nsubject: {{id: s01}}\ncamera_mode: {mode}\ntrials:\n{body}\n"
                    f"record: {{force: true}}\nanalysis: {{enabled: {str(analysis).lower()}, method: features}}\n")
    return path


def _session_alive(sid: int) -> list:
    import psutil  # noqa: PLC0415

    out = []
    for proc in psutil.process_iter():
        try:
            if os.getsid(proc.pid) == sid and proc.status() != psutil.STATUS_ZOMBIE:
                out.append(proc)
        except (ProcessLookupError, PermissionError, psutil.Error):
            continue
    return out


class _Lines:
    """A child's stdout read on a thread, each line with its arrival time (time.time())."""

    def __init__(self, child: subprocess.Popen) -> None:
        self.lines: list[tuple[float, str]] = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(child,), daemon=True)
        self._thread.start()

    def _read(self, child) -> None:
        for line in child.stdout:
            with self._cond:
                self.lines.append((time.time(), line.rstrip("\n")))
                self._cond.notify_all()
        with self._cond:
            self.lines.append((time.time(), None))
            self._cond.notify_all()

    def wait_for(self, test, timeout_s: float = 120.0) -> tuple[float, str] | None:
        deadline = time.monotonic() + timeout_s
        seen = 0
        with self._cond:
            while time.monotonic() < deadline:
                for t, line in self.lines[seen:]:
                    if line is None:
                        return None
                    if test(line):
                        return t, line
                seen = len(self.lines)
                self._cond.wait(0.1)
        return None


# ---------------------------------------------------------------------------------------------------- recordings


def _sigkill(work: Path) -> _Row:
    proto = _protocol(work / "killed.yaml", [("a", 1.0, "flat"), ("b", 1.0, "ridge"), ("c", 1.0, "valley")],
                      analysis=True)
    child = subprocess.Popen(CLI + ["record", str(proto), "-o", str(work / "killed"), "--no-movie"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    lines = _Lines(child)
    try:
        hit = lines.wait_for(lambda line: line.startswith("  001-b-r1:") and "/60 frames" in line)
        if hit is None:
            raise RuntimeError("record never reached its second trial: " + " | ".join(l for _, l in lines.lines if l))
        time.sleep(0.3)  # mid-trial, with trial 1 being analysed and trial 3 rendered
        killed_at = time.time()
        os.kill(child.pid, signal.SIGKILL)
        child.wait(10)
        while _session_alive(child.pid) and time.time() - killed_at < 10:
            time.sleep(0.02)
        gone_s = time.time() - killed_at
        left = len(_session_alive(child.pid))
    finally:
        for proc in _session_alive(child.pid):
            proc.kill()
        child.stdout.close()
    sdir = work / "killed" / "s01" / "killed"
    with open_session(sdir / "001-b-r1" / "session.h5") as s:
        n, lost = s.n_frames, killed_at - float(s.timestamps[-1])
    resume = _cli("record", str(proto), "-o", str(work / "killed"), "--resume", "--no-movie")
    done = {d.get("run_start"): d for name, d in read_events(sdir / "events.jsonl") if name == "stop"}
    aborted = any(d.get("exit_status") == "abort" for d in done.values())
    # --resume records the rest and, since issue 41, counts the aborted trial: status 1, "1 in an earlier run"
    counted = "1 of 3 trials failed (1 in an earlier run)" in resume.stderr
    return _Row("SIGKILL of record", "mid-trial 2 of 3, analysis of trial 1 running", gone_s,
                f"{n} frames readable, {lost:.3f} s lost; --resume: trial marked aborted (and counted), the rest "
                "recorded",
                "twin died with record (hardware: firmware watchdog, 50 ms)",
                f"-9; --resume {resume.returncode}",
                left == 0 and gone_s <= 2.0 and lost <= 0.1 and aborted and resume.returncode == 1 and counted)


def replay_rig(work: Path, *, rate_hz: float | None = None) -> Path:
    """A rig file replaying 90 textured 640x484 frames (from ``work``) at ``rate_hz`` (None: their recorded 60 Hz),
    the display twin, no force."""
    frames = np.random.default_rng(0).integers(0, 256, (90, 484, 640), dtype=np.uint8)
    source = write_session(work / "replay-source.h5", frames, timestamps=np.arange(90) / 60.0,
                           camera_mode=CAMERA_MODES["full"], calibration=CAL, overwrite=True)
    options = "" if rate_hz is None else f", options: {{rate_hz: {float(rate_hz)!r}}}"
    rig = work / "replay-rig.yaml"
    rig.write_text(f"name: replay\ncamera: {{kind: replay, device: {str(source)!r}{options}}}\nforce: {{kind: none}}\n"
                   "display: {kind: sim}\n")
    return rig


class DiskFiller:
    """Another process that fills the disk holding ``path`` when told to (:meth:`fill`).

    Started ahead and waiting, so that its interpreter's start-up (a second or more on a loaded machine) is not part
    of the race with the trial it fills the disk under. Use as a context manager.
    """

    PROGRAM = """
import sys, time
print("ready", flush=True)
sys.stdin.readline()
with open(sys.argv[1], "wb", buffering=0) as fh:
    try:
        while True:
            fh.write(bytes(1 << 20))
    except OSError:
        print(time.time(), flush=True)
"""

    def __init__(self, path: Path, *, timeout_s: float = 60.0) -> None:
        self._timeout_s = timeout_s
        self._proc = subprocess.Popen([sys.executable, "-c", self.PROGRAM, str(path)], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, text=True)
        if self._line() != "ready":
            self.close()
            raise RuntimeError("the disk filler did not start")

    def _line(self) -> str:
        ready, _, _ = select.select([self._proc.stdout], [], [], self._timeout_s)
        return self._proc.stdout.readline().strip() if ready else ""

    def fill(self) -> float:
        """Fill the disk now; returns when it is full, with the time it was (``time.time()``)."""
        self._proc.stdin.write("fill\n")
        self._proc.stdin.flush()
        line = self._line()
        if not line:
            raise RuntimeError("the disk filler did not report a full disk")
        return float(line)

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.kill()
        self._proc.wait()
        self._proc.stdin.close()
        self._proc.stdout.close()

    def __enter__(self) -> "DiskFiller":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _disk_full(work: Path) -> _Row:
    if os.geteuid() != 0 or not sys.platform.startswith("linux"):
        return _disk_full_injected(work)
    mnt = work / "tmpfs"
    mnt.mkdir(exist_ok=True)
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=50m", "tmpfs", str(mnt)], capture_output=True).returncode:
        return _disk_full_injected(work)
    try:
        rig = replay_rig(work)
        proto = work / "fill.yaml"
        proto.write_text("name: fill\nsubject: {id: s01}\ncamera_mode: full\ntrials:\n"
                         "  - {name: a, duration_s: 0.7}\n  - {name: b, duration_s: 0.7}\n"
                         "record: {force: false}\nanalysis: {enabled: false}\n")
        with DiskFiller(mnt / "filler.bin") as filler:
            child = subprocess.Popen(CLI + ["record", str(proto), "--rig", str(rig), "-o", str(mnt / "d")],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            lines = _Lines(child)
            if lines.wait_for(lambda line: "/42 frames" in line) is None:
                raise RuntimeError("record never started writing frames")
            full_at = filler.fill()
        stopped = lines.wait_for(lambda line: "failed (" in line and "disk full" in line)
        rc = child.wait(60)
        lines.wait_for(lambda line: False, timeout_s=10)  # to the end of the output
        output = [line for _, line in lines.lines if line is not None]
        child.stdout.close()
        with open_session(mnt / "d" / "s01" / "fill" / "000-a-r1" / "session.h5") as s:
            n, status, lost = s.n_frames, s.status, full_at - float(s.timestamps[-1])
        rested = "did not return to rest" not in (stopped[1] if stopped else "")
        text = "\n".join(output)
        clean = (output[-1].startswith("skinstretch record: 1 of 2 trials failed") and "disk full" in output[-1]
                 and all(bad not in text for bad in ("Traceback", "Exception ignored", "Segmentation", "HDF5-DIAG")))
        return _Row("disk full", "50 MB tmpfs filled by another process mid-trial",
                    (stopped[0] - full_at) if stopped else math.nan,
                    f"{n} frames readable, file {status}, {max(lost, 0.0):.3f} s lost; next trial not run",
                    "rested" if rested else "NOT rested", str(rc),
                    bool(stopped) and rc == 1 and status == "failed" and clean and rested)
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _disk_full_injected(work: Path) -> _Row:
    """Without root: the same run in process, the session writer's free-space probe filling at 10 MB."""
    from functools import partial  # noqa: PLC0415

    from skinstretch.drivers.session_file import SessionWriter  # noqa: PLC0415
    from skinstretch.experiments.protocol import Rig, load_protocol  # noqa: PLC0415
    from skinstretch.experiments.runner import run_protocol  # noqa: PLC0415

    out = work / "fill-injected"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    proto = _protocol(work / "fill-injected.yaml", [("a", 0.7, "flat"), ("b", 0.7, "flat")])
    capacity = 10_000_000 + (8 << 20)

    def free(_p) -> int:
        return max(capacity - sum(p.stat().st_size for p in out.rglob("*") if p.is_file()), 0)

    t0 = time.time()
    run = run_protocol(load_protocol(proto), Rig(), out, writer_factory=partial(SessionWriter, free_bytes=free),
                       progress=lambda m: None, play_movie=False, analyse=False)
    first = run.trials[0]
    with open_session(first.path) as s:
        n, status = s.n_frames, s.status
    return _Row("disk full", "injected (not root: no tmpfs): free space ends at ~10 MB", time.time() - t0,
                f"{n} frames readable, file {status}; next trial not run", "rested", "1 (record)",
                status == "failed" and first.disk_full and run.count("not run") == 1)


def _camera_stall(work: Path) -> _Row:
    proto = _protocol(work / "stall.yaml", [("a", 1.0, "flat")])
    rig = work / "stall-rig.yaml"
    rig.write_text("name: stall\ncamera: {kind: sim, options: {faults: {stall_at_frame: 20}}}\n"
                   "force: {kind: sim}\ndisplay: {kind: sim}\n")
    t0 = time.time()
    done = _cli("record", str(proto), "--rig", str(rig), "-o", str(work / "stall"), "--no-analysis")
    sdir = work / "stall" / "s01" / "stall"
    stop = [d for name, d in read_events(sdir / "events.jsonl") if name == "stop"][0]
    with open_session(sdir / "000-a-r1" / "session.h5") as s:
        n, status, last = s.n_frames, s.status, float(s.timestamps[-1])
    detected = stop["time"] - last - CAMERA_MODES["full"].period_s  # from the frame that never came
    rested = "did not return to rest" not in stop.get("reason", "")
    return _Row("camera stall", "simulated camera stops at frame 20 (forever)", detected,
                f"{n} frames readable, file {status} ({stop.get('reason', '').split(':')[0]}: no frame for 1 s)",
                "rested" if rested else "NOT rested", str(done.returncode),
                done.returncode == 1 and n == 20 and status == "failed" and rested and time.time() - t0 < 120)


# ------------------------------------------------------------------------------------------------------ playback


def _movie(n: int = 2100) -> np.ndarray:
    t = np.arange(n) / 700.0
    return 20.0 * np.sin(2 * np.pi * 5 * t)[:, None, None] * np.ones((1, 10, 10))


def _played(path: Path) -> int:
    try:
        with open_session(path) as s:
            return int(s.read_stream("display_target")[0].shape[0])
    except SessionFileError:
        return -1


def _link_fault(work: Path, kind: str) -> _Row:
    """Display link end-of-file (vanished), stalled, or its firmware process killed, mid-movie (open loop, 700 Hz)."""
    from skinstretch.drivers.display.stress import StressDisplay  # noqa: PLC0415
    from skinstretch.drivers.display.transports import SerialTransport  # noqa: PLC0415
    from skinstretch.experiments.playback import play_movie  # noqa: PLC0415
    from skinstretch.simulators import stress_links  # noqa: PLC0415

    path = work / f"link-{kind}.h5"
    path.unlink(missing_ok=True)
    fault_at: list[float] = []
    process = None
    if kind == "kill":
        process = stress_links.FirmwareProcess(record_path=work / "firmware-record.npz")
        display = StressDisplay(SerialTransport(process.port))
        killer = threading.Timer(0.5, lambda: (fault_at.append(time.perf_counter()), process._process.kill()))
        killer.start()
        firmware = None
    else:
        stress_links.register_url_handler()
        link = stress_links.make_link(seed=0, faults=f"{'vanish' if kind == 'eof' else 'stall'}_after:350")
        name = f"bench_{kind}_{os.getpid()}"
        display = StressDisplay(SerialTransport(stress_links.attach(name, link)))
        firmware = link.firmware
        on_packet = link._on_packet

        def watch(packet, t):
            before = link.stalled or link.vanished
            on_packet(packet, t)
            if (link.stalled or link.vanished) and not before:
                fault_at.append(time.perf_counter())

        link._on_packet = watch
    try:
        result = play_movie(display, _movie(), closed_loop=False, path=path)
        returned = time.perf_counter()
    finally:
        display.close()
        if process is not None:
            process.close(timeout_s=2.0)
    state = "firmware process dead"
    if firmware is not None:
        time.sleep(0.3)  # the watchdog (50 ms) and the soft rest ramp
        link.advance()
        at_rest = not firmware.armed and float(np.abs(firmware.benders.deflection_um()).max()) < 1.0
        state = "rested by the firmware watchdog" if at_rest else "NOT at rest"
    # the same fault from the command line, for its exit status
    url = None if kind == "kill" else f"stresssim://cli_{kind}?faults={'vanish' if kind == 'eof' else 'stall'}_after:350"
    rc = "-"
    if url is not None:
        np.save(work / "movie.npy", _movie())
        cli_out = work / f"link-{kind}-cli.h5"
        cli_out.unlink(missing_ok=True)
        done = _cli("play", str(work / "movie.npy"), "--movie-rate", "700", "--display", url, "-o", str(cli_out),
                    "--no-force")
        rc = str(done.returncode)
    injected = {"eof": "link vanishes after 350 frames (unplugged)", "stall": "link silent after 350 frames",
                "kill": "firmware process SIGKILLed 0.5 s in (pty hangs up)"}[kind]
    detected = returned - fault_at[0] if fault_at else math.nan
    played = _played(path)
    # detected < 0: the movie stopped before the fault (a starved machine's link timeout), not because of it
    ok = bool(result.stopped) and played == result.frames_played > 0 and "NOT" not in state and 0 <= detected < 0.4
    return _Row(f"display link {kind.upper() if kind == 'eof' else kind}", injected, detected,
                f"{played} of {result.frames_total} frames in the playback file (failed: link)", state,
                f"{rc} (play)" if rc != "-" else "3 (play)", ok and rc in ("3", "-"))


def _force_ceiling(work: Path) -> _Row:
    from skinstretch.drivers.display.stress import StressDisplay  # noqa: PLC0415
    from skinstretch.drivers.display.transports import SerialTransport  # noqa: PLC0415
    from skinstretch.drivers.forcesensor.netft import NetFTSensor  # noqa: PLC0415
    from skinstretch.experiments.playback import play_movie  # noqa: PLC0415
    from skinstretch.experiments.rig import ForceSource  # noqa: PLC0415
    from skinstretch.simulators import stress_links  # noqa: PLC0415
    from skinstretch.simulators.netft_box import NetFTSimulator, normal_force_wrench  # noqa: PLC0415

    start = time.time()
    cross = start + 1.0  # 1.5 N, rising at 20 N/s from 1 s on: 5 N crossed at 1.175 s

    def fz(t: float) -> float:
        return 1.5 + 20.0 * max(0.0, t - 1.0)

    server = NetFTSimulator(seed=0, wrench=normal_force_wrench(fz), rate_hz=500.0)
    server.start()
    host, port = server.address
    force = ForceSource(NetFTSensor(host, port=port), description="bench")
    stress_links.register_url_handler()
    link = stress_links.make_link(seed=0)
    display = StressDisplay(SerialTransport(stress_links.attach(f"bench_force_{os.getpid()}", link)))
    path = work / "force-ceiling.h5"
    path.unlink(missing_ok=True)
    try:
        result = play_movie(display, _movie(2800), closed_loop=False, path=path, force=force, force_ceiling_n=5.0)
        returned = time.time()
    finally:
        display.close()
        force.close()
        server.close()
    with open_session(path) as s:
        t, wrench = s.read_stream("force")
    tripped = float(np.abs(wrench[-1, 2]))
    crossed = cross + (5.0 - 1.5) / 20.0
    np.save(work / "movie.npy", _movie())
    out = work / "force-cli.h5"
    out.unlink(missing_ok=True)
    done = _cli("play", str(work / "movie.npy"), "--movie-rate", "700", "--force-ceiling", "1.0", "-o", str(out))
    return _Row("force ceiling", "normal force ramps past the 5 N ceiling", returned - crossed,
                f"{result.frames_played} frames and the tripping sample ({tripped:.2f} N) in the force stream",
                "rested and disarmed" if result.rested else "NOT rested", f"{done.returncode} (play)",
                tripped > 5.0 and result.rested and "safety stop" in result.stopped and done.returncode == 3)


# ---------------------------------------------------------------------------------------------------- bad input


def _bad_file(work: Path, kind: str) -> _Row:
    frames = np.random.default_rng(1).integers(0, 256, (30, 484, 640), dtype=np.uint8)
    path = write_session(work / f"{kind}.h5", frames, timestamps=np.arange(30) / 60.0,
                         camera_mode=CAMERA_MODES["full"], calibration=CAL, overwrite=True)
    size = path.stat().st_size
    if kind == "truncated":
        os.truncate(path, int(size * 0.6))
        injected = "session file cut at 60 % (an interrupted copy)"
    else:
        with open(path, "r+b") as fh:  # the signature stays; the superblock and root header behind it are garbled
            fh.seek(8)
            head = fh.read(4088)
            fh.seek(8)
            fh.write(bytes(b ^ 0x5A for b in head))
        injected = "bytes 8-4096 garbled (superblock, root object header)"
    t0 = time.perf_counter()
    try:
        open_session(path).close()
        refused = ""
    except SessionFileError as exc:
        refused = str(exc)
    took = time.perf_counter() - t0
    done = _cli("analyze", str(path), "-o", str(work / f"{kind}-out"))
    t0 = time.perf_counter()
    viewed = _cli("view", str(path), "--no-browser", "--port", "0", timeout_s=60)  # hung, or a traceback (issue 41)
    view_s = time.perf_counter() - t0
    why = refused.split(": ", 1)[-1].split(" (")[0]
    return _Row(f"{kind} session file", injected, took,
                f"refused ({why}); file untouched; view refused too, in {view_s:.2f} s with start-up", "-",
                f"{done.returncode} (analyze), {viewed.returncode} (view)",
                bool(refused) and done.returncode == 2 and _one_line(done.stderr) and viewed.returncode == 2
                and _one_line(viewed.stderr) and "truncated or corrupt" in viewed.stderr)


def _bad_video(work: Path) -> _Row:
    """An MJPEG AVI cut at a third: the import finds the frames missing that the container declares."""
    import cv2  # noqa: PLC0415

    from skinstretch.drivers.errors import FrameFileError  # noqa: PLC0415
    from skinstretch.experiments.frame_import import import_frames  # noqa: PLC0415

    good = work / "good.avi"
    writer = cv2.VideoWriter(str(good), cv2.VideoWriter_fourcc(*"MJPG"), 60, (640, 484), isColor=False)
    rng = np.random.default_rng(2)
    for _ in range(30):
        writer.write(rng.integers(0, 256, (484, 640), dtype=np.uint8))
    writer.release()
    bad = work / "bad.avi"
    data = good.read_bytes()
    bad.write_bytes(data[: len(data) // 3])
    t0 = time.perf_counter()
    try:
        import_frames(bad, work / "bad-video.h5", px_per_mm=62.0)
        refused = ""
    except FrameFileError as exc:
        refused = str(exc)
    took = time.perf_counter() - t0
    done = _cli("import", str(bad), "-o", str(work / "bad-video-cli.h5"), "--px-per-mm", "62")
    left = (work / "bad-video.h5").exists() or (work / "bad-video-cli.h5").exists()
    last = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else ""
    return _Row("bad video file", "an AVI cut at a third (an interrupted copy)", took,
                f"refused ({refused.split(': ', 1)[-1]}); no session left", "-", f"{done.returncode} (import)",
                bool(refused) and done.returncode == 2 and not left and "Traceback" not in done.stderr
                and last.startswith("skinstretch import: error:"))


def _bad_protocol(work: Path) -> _Row:
    bad = work / "typo.yaml"
    bad.write_text("name: typo\nsubject: {id: s01}\ntrials:\n  - {name: a, duration_s: 1.0, duraton_s: 2}\n")
    from skinstretch.experiments.protocol import load_protocol  # noqa: PLC0415
    from skinstretch.processing.errors import ConfigError  # noqa: PLC0415

    t0 = time.perf_counter()
    try:
        load_protocol(bad)
        message = ""
    except ConfigError as exc:
        message = str(exc)
    took = time.perf_counter() - t0
    done = _cli("record", str(bad), "-o", str(work / "typo"))
    return _Row("bad protocol", "a misspelt field (duraton_s) on line 4", took,
                f"nothing recorded ({message.rsplit('/', 1)[-1]})", "never opened", f"{done.returncode} (record)",
                bool(message) and done.returncode == 2 and _one_line(done.stderr) and "typo.yaml:4" in done.stderr
                and not (work / "typo").exists())


# ------------------------------------------------------------------------------------------ issue 41's drill


def _live_view(work: Path) -> _Row:
    """``record --live``: the viewer process holds the session file open (SWMR) while the recorder closes it and
    then adds the ground truth, stores the status, logs the stop document and analyses the trial."""
    proto = _protocol(work / "live.yaml", [("a", 1.0, "flat")], analysis=True)
    shutil.rmtree(work / "live", ignore_errors=True)
    t0 = time.time()
    done = _cli("record", str(proto), "-o", str(work / "live"), "--live", "--no-movie", timeout_s=900)
    took = time.time() - t0
    trial = work / "live" / "s01" / "live" / "000-a-r1"
    with open_session(trial / "session.h5") as s:
        status, truth = s.status, s.has_truth
    stops = [d for name, d in read_events(trial.parent / "events.jsonl") if name == "stop"]
    analysed = (trial / "analysis" / "results.h5").exists()
    viewer = "viewer: showing" in done.stderr
    lost = "without its simulated ground truth" in done.stderr
    kept = (f"truth {'kept' if truth else 'LOST'}, status {status}, stop {stops[-1]['exit_status'] if stops else '-'}"
            f", analysis {'written' if analysed else 'MISSING'}; viewer {'attached' if viewer else 'NOT attached'}")
    return _Row("live view (record --live)", "viewer reads session.h5 while the recorder writes after the trial",
                math.nan, kept, "-", str(done.returncode),
                done.returncode == 0 and truth and status == "complete" and analysed and viewer and not lost
                and bool(stops) and stops[-1]["exit_status"] == "success" and took < 900)


def _one_outdir_twice(work: Path) -> _Row:
    """Two ``analyze`` runs into one OUTDIR, started together: one refused at once naming the holder, one done."""
    frames = np.random.default_rng(3).integers(0, 256, (60, 484, 640), dtype=np.uint8)
    session = write_session(work / "twice.h5", frames, timestamps=np.arange(60) / 60.0,
                            camera_mode=CAMERA_MODES["full"], calibration=CAL, overwrite=True)
    out = work / "twice-out"
    shutil.rmtree(out, ignore_errors=True)
    cmd = CLI + ["analyze", str(session), "-o", str(out), "-q"]
    starts, procs = [], []
    for _ in range(2):
        starts.append(time.time())
        procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    ended = []
    for proc in procs:
        proc.wait(600)
        ended.append(time.time())
    errs = [proc.stderr.read() for proc in procs]
    for proc in procs:
        proc.stdout.close()
        proc.stderr.close()
    codes = [proc.returncode for proc in procs]
    refused = [k for k in (0, 1) if codes[k] == 2]
    line = ""
    if len(refused) == 1:
        line = [l for l in errs[refused[0]].splitlines() if "error:" in l][-1]
    ok = (sorted(codes) == [0, 2] and "in use by an analysis of twice.h5 (pid" in line
          and (out / "results.h5").exists() and not (out / ".skinstretch-lock").exists())
    # detection in process, as for the other rows: an analysis started while another holds the directory
    from skinstretch.experiments.analysis import analyze_session  # noqa: PLC0415
    from skinstretch.experiments.output_paths import OutputDirBusyError, hold_output_dir  # noqa: PLC0415

    shutil.rmtree(out, ignore_errors=True)
    with hold_output_dir(out, holder="the bench"):
        t0 = time.perf_counter()
        try:
            analyze_session(session, out)
            took = math.nan
        except OutputDirBusyError:
            took = time.perf_counter() - t0
    return _Row("one OUTDIR, two analyses", "two analyze runs into one OUTDIR, started together", took,
                f"one finished (results.h5 kept), one refused: {line.split(': ', 3)[-1][:60]}...", "-",
                " and ".join(str(c) for c in codes) + " (analyze)", ok)


def _silent_force(work: Path) -> _Row:
    """A Net F/T that reads the requests and never answers (a firewall dropping its datagrams), at a loopback
    address of its own: the trial fails in one line; a movie with a force ceiling is refused before arming."""
    from skinstretch.drivers.display.stress import StressDisplay  # noqa: PLC0415
    from skinstretch.drivers.display.transports import SerialTransport  # noqa: PLC0415
    from skinstretch.drivers.errors import DeviceTimeoutError  # noqa: PLC0415
    from skinstretch.drivers.forcesensor.netft import NetFTSensor  # noqa: PLC0415
    from skinstretch.experiments.playback import play_movie  # noqa: PLC0415
    from skinstretch.experiments.rig import ForceSource  # noqa: PLC0415
    from skinstretch.simulators import stress_links  # noqa: PLC0415
    from skinstretch.simulators.netft_box import NetFTFaults, NetFTSimulator  # noqa: PLC0415

    with NetFTSimulator(host="127.0.0.3", faults=NetFTFaults(silent=True)) as box:
        host, port = box.address
        source = replay_rig(work)  # its replay session, for the camera
        rig = work / "silent-rig.yaml"
        rig.write_text(source.read_text().replace("force: {kind: none}", f"force: {{kind: netft, address: {host}, "
                                                                         f"options: {{port: {port}}}}}"))
        proto = _protocol(work / "silent.yaml", [("a", 1.5, "flat")])  # longer than the 1 s silence timeout
        shutil.rmtree(work / "silent", ignore_errors=True)
        done = _cli("record", str(proto), "--rig", str(rig), "-o", str(work / "silent"))
        sdir = work / "silent" / "s01" / "silent"
        docs = read_events(sdir / "events.jsonl")
        start = [d for name, d in docs if name == "start"]
        stop = [d for name, d in docs if name == "stop"]
        with open_session(sdir / "000-a-r1" / "session.h5") as s:
            status, reason = s.status, s.status_reason
        detected = stop[0]["time"] - start[0]["time"] if start and stop else math.nan
        stress_links.register_url_handler()
        link = stress_links.make_link(seed=0)
        display = StressDisplay(SerialTransport(stress_links.attach(f"bench_silent_{os.getpid()}", link)))
        force = ForceSource(NetFTSensor(host, port=port), description=f"Net F/T at {host}")
        try:
            play_movie(display, _movie(700), closed_loop=False, force=force, force_ceiling_n=5.0)
            movie = "PLAYED"
        except DeviceTimeoutError:
            movie = "refused"
        finally:
            force.close()
            display.close()
        armed = link.firmware.armed
    last = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else ""
    ok = (done.returncode == 1 and status == "failed" and ("no data for" in reason or "no sample" in reason)
          and last.startswith("skinstretch record: 1 of 1 trials failed") and movie == "refused" and not armed)
    return _Row("silent force sensor", "Net F/T at 127.0.0.3 reads requests, never answers (firewall)", detected,
                f"trial {status} ({reason.split(': ', 1)[-1]}); movie with a 5 N ceiling {movie}",
                "never armed" if not armed else "ARMED", f"{done.returncode} (record)", ok)


def _bad_movies(work: Path) -> _Row:
    """A complex movie and a user's movie with a NaN, given to ``play``: refused before the display is armed."""
    from skinstretch.experiments.playback import load_movie  # noqa: PLC0415
    from skinstretch.processing.errors import InvalidInputError  # noqa: PLC0415

    codes, lines, took = [], [], []
    for kind in ("complex", "nan"):
        movie = _movie(2100)
        if kind == "complex":
            movie = movie.astype(complex)
        else:
            movie[5, 2, 7] = np.nan
        np.save(work / f"{kind}-movie.npy", movie)
        t0 = time.perf_counter()
        try:
            load_movie(work / f"{kind}-movie.npy")
        except InvalidInputError:
            took.append(time.perf_counter() - t0)
        out = work / f"{kind}-movie.h5"
        out.unlink(missing_ok=True)
        done = _cli("play", str(work / f"{kind}-movie.npy"), "--movie-rate", "700", "-o", str(out))
        codes.append(done.returncode)
        lines.append(done.stderr.strip())
        if out.exists() or not _one_line(done.stderr):
            codes[-1] = -1
    took = max(took) if len(took) == 2 else math.nan
    ok = len(lines) == 2 and codes == [2, 2] and "is complex" in lines[0] and "frame 5, contactor (2, 7) is nan" in lines[1]
    return _Row("bad movie (play)", "a complex (2100, 10, 10) movie; a user's movie with one NaN", took,
                "both refused in one line (the NaN named: frame 5, contactor (2, 7)); nothing played", "never armed",
                " and ".join(map(str, codes)) + " (play)", ok)


def _sigterm(work: Path) -> _Row:
    """SIGTERM (kill, systemd, a closing terminal) of ``record`` mid-trial: the trial closed as aborted."""
    rig = replay_rig(work)
    proto = _protocol(work / "term.yaml", [("a", 1.5, "flat"), ("b", 1.0, "flat")])
    shutil.rmtree(work / "term", ignore_errors=True)
    child = subprocess.Popen(CLI + ["record", str(proto), "--rig", str(rig), "-o", str(work / "term"), "--no-movie"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    lines = _Lines(child)
    try:
        if lines.wait_for(lambda line: "/90 frames" in line) is None:
            raise RuntimeError("record never started writing frames")
        time.sleep(0.2)
        sent = time.time()
        child.send_signal(signal.SIGTERM)
        rc = child.wait(30)
        exited_s = time.time() - sent
        while _session_alive(child.pid) and time.time() - sent < 10:
            time.sleep(0.02)
        left = len(_session_alive(child.pid))
    finally:
        for proc in _session_alive(child.pid):
            proc.kill()
    lines.wait_for(lambda line: False, timeout_s=5)
    child.stdout.close()
    trial = work / "term" / "s01" / "term" / "000-a-r1"
    with open_session(trial / "session.h5") as s:
        n, status, reason = s.n_frames, s.status, s.status_reason
    stops = [d for name, d in read_events(trial.parent / "events.jsonl") if name == "stop"]
    reserve = list(trial.glob(".*.reserve"))
    ok = (rc == 143 and status == "failed" and reason == "aborted: SIGTERM received" and not reserve and left == 0
          and [d["exit_status"] for d in stops] == ["abort"] and exited_s < 1.0)
    return _Row("SIGTERM of record", "mid-trial 1 of 2 (kill, systemd, a closing terminal)", exited_s,
                f"{n} frames readable, file {status} ({reason}), reserve {'LEFT' if reserve else 'removed'}, "
                f"stop: abort; {left} process(es) left; next trial not run", "rested", str(rc), ok)


def run(options: BenchOptions) -> list[BenchTable]:
    work = Path(options.workdir) / "faults"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    scenarios = [("SIGKILL", _sigkill), ("disk full", _disk_full), ("camera stall", _camera_stall),
                 *[(f"link {k}", (lambda w, k=k: _link_fault(w, k))) for k in ("eof", "stall", "kill")],
                 ("force ceiling", _force_ceiling),
                 ("corrupt file", lambda w: _bad_file(w, "corrupt")),
                 ("truncated file", lambda w: _bad_file(w, "truncated")),
                 ("bad video", _bad_video),
                 ("bad protocol", _bad_protocol),
                 ("live view", _live_view),
                 ("one outdir twice", _one_outdir_twice),
                 ("silent force", _silent_force),
                 ("bad movies", _bad_movies),
                 ("SIGTERM", _sigterm)]
    rows, notes, reruns = [], [], []
    for name, scenario in scenarios:
        for attempt in range(1, ATTEMPTS + 1):
            where = work if attempt == 1 else work / f"run-{attempt}-{name.replace(' ', '-')}"  # a fresh place
            where.mkdir(exist_ok=True)
            try:
                row = scenario(where).cells()
            except Exception as exc:  # noqa: BLE001 - one broken scenario is reported, the others still run
                row = [name, "-", math.nan, f"scenario failed: {type(exc).__name__}: {exc}", "-", "-", "NO"]
            if row[-1] == "yes" or attempt == ATTEMPTS:
                break
            reruns.append(f"{row[0]}: attempt {attempt} not as designed (detected after {row[2]:.3g} s; {row[3]}; "
                          f"exit {row[5]}), run again")
        rows.append(row)
    notes.append("detected after: fault -> the program acted (trial or movie stopped, file refused); SIGKILL: -> "
                 "the last process of record's session gone. Display link timeout 0.2 s, camera read timeout 1 s.")
    notes.append("exit status: what the command a user runs returns for that fault (1: record with a failed trial, "
                 "3: play stopped, 2: refused before starting, -9: killed, 143: record stopped by SIGTERM).")
    notes.append("Issue 41's rows: live view has no detection time (nothing should fail); one OUTDIR and bad movie: "
                 "the refusal in process (an analysis started while another holds the directory; loading the "
                 "movie); silent force sensor: from the trial's start document to its stop document (1 s silence "
                 "timeout); SIGTERM: from the signal to record's exit.")
    notes.append("Measured on this machine under the load of the moment (other developers' jobs); the simulated rig.")
    notes.append(f"A row not as designed is run again, up to {ATTEMPTS} times: on a starved machine the simulated "
                 "display (a thread of the playing process) can fall silent for the 0.2 s link timeout before the "
                 "fault is injected. " + ("Runs again: " + "; ".join(reruns) + "." if reruns else "No row needed another run."))
    return [BenchTable(title="Fault matrix: detection, what is kept, display state, exit status",
                       columns=COLUMNS, rows=rows, notes=notes)]

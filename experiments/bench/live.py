"""Bench section ``live``: record 640x484 @60 Hz for 20 s with the live view attached, and measure it.

The simulated camera streams the ``ridgeL`` scene (180 rendered frames, looped) in real time into an SWMR session
file through the experiment :class:`~skinstretch.experiments.recorder.Recorder`, exactly as a trial is recorded.
The viewer runs in a process of its own (``skinstretch view DATADIR``, as ``record --live`` starts it), follows
the trial and analyses its frames as they come (skipping ahead when it falls behind). Two recordings: a headless Chromium showing the page (when
Playwright and a Chromium are installed; it draws in software, on the same 2 cores), then a server-sent-event
client that only reads the page's events (what the analysis does with the cores to itself and the recorder).

Reported: frames recorded and dropped (frame-id gaps + camera drops + recorder drops; must be 0), live analysis
frames/s, page updates/s, latency from the frame's exposure (host time stamp) to the strain on screen (p50, p95,
max), and the live motion and strain against the simulator's truth (displacement RMSE of matched features,
triangle area-change RMSE).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np

from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.bench import BenchOptions, BenchTable
from skinstretch.experiments.viewer.browser import browser_unavailable_reason, launch_chromium
from skinstretch.experiments.recorder import record_from_camera
from skinstretch.experiments.viewer.live_analysis import MAX_LAG_FRAMES
from skinstretch.experiments.viewer.live_check import latency_percentiles, live_accuracy
from skinstretch.experiments.viewer.live_launch import start_live_viewer

SECTION = "live"
DESCRIPTION = "live view while recording 640x484@60: dropped frames, analysed frames/s, exposure-to-screen latency"


class _EventClient(threading.Thread):
    """Reads the page's event stream like the page does, when no browser can be driven."""

    def __init__(self, url: str) -> None:
        super().__init__(name="live-bench-sse", daemon=True)
        self.url = url
        self.received: list[dict] = []
        self.stop_event = threading.Event()

    def run(self) -> None:
        import httpx  # noqa: PLC0415

        base, _, query = self.url.partition("/?")
        event = None
        with httpx.Client(timeout=None) as client, client.stream("GET", f"{base}/api/events?{query}") as resp:
            for line in resp.iter_lines():
                if self.stop_event.is_set():
                    return
                if line.startswith("event:"):
                    event = line[6:].strip()
                elif line.startswith("data:") and event == "live":
                    ev = json.loads(line[5:])
                    self.received.append({"frame": ev["frame"], "exposure": ev["exposure_time"],
                                          "shown": time.time()})


def _overlays(url: str, frames: list[int]) -> list[dict]:
    import httpx  # noqa: PLC0415

    base, _, query = url.partition("/?")
    out = []
    with httpx.Client(timeout=30.0) as client:
        sid = client.get(f"{base}/api/info?{query}").json()["sid"]
        for k in frames:
            r = client.get(f"{base}/api/s/{sid}/overlay/{k}?{query}")
            if r.status_code == 200 and r.json().get("source") == "live":
                out.append(r.json())
    return out


def run(options: BenchOptions) -> list[BenchTable]:
    from skinstretch.simulators.scene import render_session  # noqa: PLC0415 - experiments pick the simulated device

    seconds = options.seconds or (5.0 if options.quick else 20.0)
    mode = CAMERA_MODES["full"]
    scene = render_session("ridgeL", seed=0, workers=2)
    work = Path(options.workdir) / "live" / time.strftime("%Y%m%d-%H%M%S")
    no_browser = browser_unavailable_reason()
    rows, notes = [], []
    if no_browser is None:
        rows.append(_record_live(scene, work / "browser", mode, seconds, browser=True, notes=notes))
    else:
        notes.append(f"no browser ({no_browser}): no Chromium row")
    rows.append(_record_live(scene, work / "events", mode, seconds, browser=False, notes=notes))
    notes += [
        "the viewer is a separate process reading the SWMR file, so the recorder never waits on it; it analyses the "
        f"frames in order while at most {MAX_LAG_FRAMES} behind the newest recorded, else jumps to the newest.",
        "latency = time on screen (page clock; for the event-stream client, the event's arrival) - the frame's host "
        "time stamp (camera clock, both Unix time).",
        "display: Chromium (headless, software raster) shows the page as a user's browser would; the event-stream "
        "client only reads the page's events (what the analysis does when no browser shares the cores).",
        "accuracy: every live displacement and triangle matched to true features within 0.1 mm (pairs across the "
        "camera's loop left out).",
        "speeds measured on a shared 2-core machine; latency includes the SWMR flush interval (25 ms).",
    ]
    tables = [BenchTable(
        title=f"Live view while recording ({seconds:g} s, ridgeL looped)",
        columns=["mode", "frames", "dropped", "analysed /s", "page updates /s", "latency p50 ms", "latency p95 ms",
                 "latency max ms", "disp RMSE px", "area RMSE %", "display"],
        rows=rows, notes=notes)]
    if no_browser is None:
        tables.append(_stepping(scene, work / "stepping"))
    return tables


def _record_live(scene, work: Path, mode, seconds: float, *, browser: bool, notes: list[str]) -> list:
    """Record ``seconds`` of the scene looped with the live viewer attached, shown in Chromium or read by an
    event-stream client; the table's row."""
    from skinstretch.simulators.simulated_camera import SimulatedCamera  # noqa: PLC0415

    frames = scene.frames
    trial = work / "000-ridge-live"
    trial.mkdir(parents=True, exist_ok=True)
    viewer = start_live_viewer(work, open_browser=False)
    client = page_ctx = None
    try:
        if browser:
            from playwright.sync_api import sync_playwright  # noqa: PLC0415

            page_ctx = sync_playwright().start()
            chromium = launch_chromium(page_ctx)
            page = chromium.new_page(viewport={"width": 1400, "height": 1000})
            page.goto(viewer.url)
            page.wait_for_function("window.viewerStats !== undefined", timeout=30000)
        else:
            client = _EventClient(viewer.url)
            client.start()
        time.sleep(1.0)  # the viewer's first look at the directory (every 0.2 s)
        camera = SimulatedCamera(frames.__getitem__, mode, n_frames=len(frames), loop=True)
        count = record_from_camera(camera, trial / "session.h5", mode=mode, calibration=scene.calibration,
                                   seconds=seconds, metadata={"bench": "live", "scene": "ridgeL"})
        time.sleep(1.0)  # the last frames reach the page
        if page_ctx is not None:
            stats = page.evaluate("window.viewerStats")
            shown, received = stats["live"], stats["liveReceived"]
            chromium.close()
        else:
            client.stop_event.set()
            shown = received = list(client.received)
        analysed = sorted({int(e["frame"]) for e in received})
        overlays = _overlays(viewer.url, analysed)
    finally:
        if page_ctx is not None:
            page_ctx.stop()
        viewer.stop()
    with open_session(trial / "session.h5") as s:
        rows = (s.frame_ids - s.frame_ids[0]) % len(frames)
    acc = live_accuracy(overlays, scene.truth, rows, px_per_mm=scene.calibration.px_per_mm)
    p50, p95, worst = latency_percentiles(shown)
    display = "Chromium (headless)" if browser else "event-stream client"
    notes.append(f"{display}: {count.seconds:.1f} s recorded (status {count.status}); {acc.pairs} analysed pairs, "
                 f"{acc.displacements} displacements, {acc.triangles} triangles scored.")
    if not np.isfinite(p95):
        notes.append(f"{display}: no live update reached the page")
    return [f"{mode.width}x{mode.height}@{mode.fps:g}", count.frames, count.dropped, len(analysed) / count.seconds,
            len(shown) / count.seconds, p50, p95, worst, acc.displacement_rmse_px, 100 * acc.area_change_rmse, display]


def _stepping(scene, work: Path) -> BenchTable:
    """Step through a whole analysed 640x484, 180-frame session in the browser, one key press per frame."""
    from playwright.sync_api import sync_playwright  # noqa: PLC0415

    from skinstretch.drivers.session_file import write_session  # noqa: PLC0415
    from skinstretch.experiments.analysis import analyze_session  # noqa: PLC0415
    from skinstretch.experiments.viewer.server import start_server  # noqa: PLC0415
    from skinstretch.experiments.viewer.session_data import find_view_target  # noqa: PLC0415

    work.mkdir(parents=True, exist_ok=True)
    path = write_session(work / "session.h5", scene.frames, timestamps=scene.timestamps, camera_mode=scene.camera_mode,
                         calibration=scene.calibration, metadata=scene.metadata, truth=scene.truth)
    analyze_session(path, work / "analysis")
    server = start_server(find_view_target(work))
    n = scene.frames.shape[0]
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.goto(server.url)
            page.wait_for_function("window.viewerStats.shown.length > 0", timeout=30000)
            for name in ("matches", "arrows"):  # every overlay on
                page.check(f'input[data-overlay="{name}"]')
            page.locator("#view").focus()
            t0 = time.perf_counter()
            for k in range(1, n):
                page.keyboard.press("ArrowRight")
                page.wait_for_function(f"S.k === {k} && !S.busy")
            wall = time.perf_counter() - t0
            shown = page.evaluate("window.viewerStats.shown")
            errors = page.evaluate("window.viewerStats.errors")
            browser.close()
    finally:
        server.stop()
    ms = np.array([e["ms"] for e in shown[1:]])
    return BenchTable(
        title="Viewer: stepping a 640x484, 180-frame analysed session (ridgeL), every overlay on",
        columns=["frames stepped", "median ms", "p95 ms", "max ms", "frames over 200 ms", "steps/s (with key round trip)",
                 "page errors"],
        rows=[[int(ms.size), float(np.median(ms)), float(np.percentile(ms, 95)), float(ms.max()),
               int((ms > 200).sum()), (n - 1) / wall, len(errors)]],
        notes=["ms = from the page asking for a frame to its image and overlays drawn (BMP frame + JSON overlays "
               "from the local server; each frame seen for the first time, the page fetching the next frame in the "
               "stepping direction while it shows the current one)."],
    )

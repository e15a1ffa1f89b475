"""The viewer in a real browser: headless Chromium (Debian package, installed by ./run test when root) driven by
Playwright. Skipped only when no browser can be installed here, saying so.

Frame-stepping time is measured and reported (``record_property``, and printed), not asserted: speed goals live
in the ``live`` bench and the README, never in timed tests.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from skinstretch.experiments.viewer.browser import browser_unavailable_reason, launch_chromium

REASON = browser_unavailable_reason()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"no browser can be driven here: {REASON}")


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = launch_chromium(p)
        yield b
        b.close()


@pytest.fixture(scope="module")
def served(tmp_path_factory, sim_session):
    """A 20-frame flatL session with its analysis, served on a thread."""
    from skinstretch.drivers.session_file import write_session
    from skinstretch.experiments.analysis import AnalysisParams, analyze_session
    from skinstretch.experiments.viewer.server import start_server
    from skinstretch.experiments.viewer.session_data import find_view_target
    from skinstretch.processing.tracking import TrackingParams

    trial = tmp_path_factory.mktemp("viewer-browser") / "000-flat-r1"
    trial.mkdir()
    s = sim_session
    path = write_session(trial / "session.h5", s.frames, timestamps=s.timestamps, camera_mode=s.camera_mode,
                         calibration=s.calibration, metadata={**s.metadata, "trial": "flat"}, truth=s.truth)
    # A 20-frame span on a 20-frame clip: no pair, and a note in the summary that the page must show.
    params = AnalysisParams(execution={"kind": "threads"}, strain={"spans": (1, 11, 20)},
                            tracking=TrackingParams(smoothing_radius_frames=0, min_length_frames=10))
    analyze_session(path, trial / "analysis", params=params)
    server = start_server(find_view_target(trial))
    yield server
    server.stop()


@pytest.fixture()
def page(browser):
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    problems: list[str] = []
    page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error"
            else None)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.problems = problems
    yield page
    page.close()


def _overlay_pixels(page) -> int:
    """Sum of the canvas' pixels (changes when an overlay is drawn or removed)."""
    return page.evaluate("""() => { const c = document.getElementById('view');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let s = 0; for (let i = 0; i < d.length; i += 4) s += d[i] + 2 * d[i + 1] + 3 * d[i + 2]; return s; }""")


def test_viewer_loads_steps_toggles_and_reads_out(page, served, record_property, tmp_path):
    page.goto(served.url)
    page.wait_for_function("window.viewerStats.shown.length > 0", timeout=30000)
    assert page.locator("#status").inner_text().startswith("complete")
    assert "frame 0 / 19" in page.locator("#frame-label").inner_text()
    # Legend and colour bar
    legend = page.locator("#legend-items").inner_text()
    for label in ("valley ending", "valley bifurcation", "pore", "match", "trajectory tail", "fingertip outline",
                  "visibility window", "displacement"):
        assert label in legend
    # Step with the keyboard
    page.locator("#view").focus()
    for k in range(1, 8):
        page.keyboard.press("ArrowRight")
        page.wait_for_function(f"document.getElementById('frame-label').textContent.startsWith('frame {k} ')")
    page.keyboard.press("End")
    page.wait_for_function("document.getElementById('frame-label').textContent.startsWith('frame 19 ')")
    page.keyboard.press("Shift+ArrowLeft")
    page.wait_for_function("document.getElementById('frame-label').textContent.startsWith('frame 9 ')")
    scale = float(page.locator("#colorbar").get_attribute("data-scale"))
    assert 0 < scale <= 0.5
    # Every overlay changes what is drawn when toggled, one by one.
    for key, name in enumerate(["features", "matches", "tails", "mesh", "arrows", "outline", "window"], start=1):
        before = _overlay_pixels(page)
        was = page.locator(f'input[data-overlay="{name}"]').is_checked()
        page.keyboard.press(str(key))
        assert page.locator(f'input[data-overlay="{name}"]').is_checked() is not was
        assert _overlay_pixels(page) != before, f"toggling {name} changed nothing"
    # Arrows whose predicted standard error is above the limit the user sets are hidden (all, at a tiny limit).
    shown = _overlay_pixels(page)
    page.fill("#max-sigma", "0.0001")
    assert _overlay_pixels(page) != shown
    page.fill("#max-sigma", "")
    assert _overlay_pixels(page) == shown
    # Readout: hover the first feature of this frame
    x, y = page.evaluate("[S.current.ov.features.x[0], S.current.ov.features.y[0]]")
    box = page.locator("#view").bounding_box()
    sc = page.evaluate("S.scale") * box["width"] / page.evaluate("document.getElementById('view').width")
    page.mouse.move(box["x"] + x * sc, box["y"] + y * sc)
    text = page.locator("#readout").inner_text()
    assert "feature " in text and "quality" in text and "truth: " in text and " px" in text
    page.mouse.click(box["x"] + x * sc, box["y"] + y * sc)
    assert "pinned" in page.locator("#readout").inner_text()
    page.mouse.click(box["x"] + x * sc, box["y"] + y * sc)  # released
    # A pinned feature follows its track to the next frames, not whatever feature has its index there: pin one
    # whose track is at another index in frame 10.
    i = page.evaluate("""async () => {
        const next = await (await fetch(`api/s/${S.sid}/overlay/10?span=${S.span}`)).json();
        const f = S.current.ov.features;
        for (let i = 0; i < f.x.length; i++) {
            const j = next.features.track.indexOf(f.track[i]);
            if (f.track[i] >= 0 && j >= 0 && j !== i) return i;
        }
        return -1; }""")
    assert i >= 0
    track, x, y = page.evaluate(f"[S.current.ov.features.track[{i}], S.current.ov.features.x[{i}], S.current.ov.features.y[{i}]]")
    page.mouse.click(box["x"] + x * sc, box["y"] + y * sc)
    assert f"(track {track})" in page.locator("#readout").inner_text()
    for k in (10, 11):
        page.keyboard.press("ArrowRight")
        page.wait_for_function(f"S.k === {k}")
        text = page.locator("#readout").inner_text()
        i = page.evaluate(f"S.current.ov.features.track.indexOf({track})")
        if i >= 0:
            fx = page.evaluate(f"S.current.ov.features.x[{i}]")
            assert f"(track {track})" in text and f"x {fx:.2f} px" in text, text
        else:
            assert f"track {track}: not measured in this frame" in text, text
    # The analysis's notes on the whole clip stay in view; a span the clip cannot hold says so on every frame.
    notes = page.locator("#analysis-notes")
    assert notes.is_visible()
    assert "no strain over 20 frames: the 20-frame session has no frame pair" in notes.inner_text()
    page.select_option("#span", "20")
    page.wait_for_function(
        "S.span === 20 && document.getElementById('notes').textContent.includes('no strain over 20')")
    assert "the 20-frame session has no pair that far apart" in page.locator("#notes").inner_text()
    # The analysis plan is one click away: collapsed, then its rows.
    plan = page.locator("#analysis-plan")
    assert plan.is_visible() and not page.locator("#analysis-plan table").is_visible()
    page.click("#analysis-plan summary")
    assert "key-frame anchoring" in page.locator("#analysis-plan table").inner_text()
    page.select_option("#span", "1")
    page.wait_for_function("S.span === 1")
    page.screenshot(path=str(tmp_path / "viewer.png"))
    ms = [e["ms"] for e in page.evaluate("window.viewerStats.shown")]
    record_property("frame_display_ms_median", float(np.median(ms)))
    record_property("frame_display_ms_max", float(np.max(ms)))
    print(f"frame with overlays on screen: median {np.median(ms):.1f} ms, max {np.max(ms):.1f} ms over {len(ms)}")
    assert page.evaluate("window.viewerStats.errors") == []
    assert page.problems == []


def test_a_failed_self_check_is_in_the_banner(page, tmp_path):
    """A flow locked onto wrong ridges (two pyramid levels over a 19.7 px/mm print): the pairs a self-check doubted
    are named above the frame, in the warnings banner."""
    from skinstretch.drivers.camera_modes import CameraMode
    from skinstretch.drivers.session_file import write_session
    from skinstretch.experiments.analysis import analyze_session
    from skinstretch.experiments.viewer.server import start_server
    from skinstretch.experiments.viewer.session_data import find_view_target
    from skinstretch.processing.pixel_scale import Calibration
    from tests.print_clips import print_frame, print_image

    image = print_image()
    frames = np.stack([print_frame(image, k, px_per_mm=19.7, background=255.0, shape=(484, 640), contact=None)
                       for k in range(6)])
    trial = tmp_path / "000-flat-r1"
    trial.mkdir()
    path = write_session(trial / "session.h5", frames, timestamps=np.arange(6) / 60,
                         camera_mode=CameraMode("full", 640, 484, 60.0), calibration=Calibration(px_per_mm=19.7),
                         metadata={"surface": {"kind": "flat"}})
    analyze_session(path, trial / "analysis", method="flow",
                    params={"flow": {"pyramid_levels": 2}, "strain": {"spans": [1, 3]}})
    server = start_server(find_view_target(trial))
    try:
        page.goto(server.url)
        page.wait_for_function("window.viewerStats.shown.length > 0", timeout=30000)
        banner = page.locator("#analysis-warnings")
        assert banner.is_visible()
        assert "consecutive frame pairs failed a self-check" in banner.inner_text()
        assert page.problems == []
    finally:
        server.stop()


def test_a_page_without_the_token_gets_nothing(page, served):
    resp = page.goto(served.url.split("?")[0])
    assert resp.status == 403
    resp = page.goto(served.url.split("?")[0] + "static/viewer.js")
    assert resp.status == 403


def test_follows_a_live_recording(browser, tmp_path, sim_session, record_property):
    """``record --live``'s viewer process follows a trial while it is recorded at 60 fps and shows live strain."""
    from skinstretch.drivers.camera_modes import CAMERA_MODES
    from skinstretch.experiments.recorder import record_from_camera
    from skinstretch.experiments.viewer.live_check import latency_percentiles
    from skinstretch.experiments.viewer.live_launch import live_view
    from skinstretch.simulators.simulated_camera import SimulatedCamera

    s = sim_session
    data = tmp_path / "data"
    with live_view(data, open_browser=False) as viewer:
        assert viewer is not None
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        problems: list[str] = []
        page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        page.goto(viewer.url)
        page.wait_for_function("window.viewerStats !== undefined")
        mode = CAMERA_MODES["full"]
        camera = SimulatedCamera(s.frames.__getitem__, mode, n_frames=s.frames.shape[0], loop=True)
        (data / "trial").mkdir()
        out = {}
        # Recorded until the page has shown 10 live frames with their strain (about 2 s on an idle machine; the
        # live analysis only takes what the machine can spare, so a loaded one needs longer: up to 90 s).
        stop = threading.Event()
        thread = threading.Thread(target=lambda: out.update(count=record_from_camera(
            camera, data / "trial" / "session.h5", mode=mode, calibration=s.calibration, seconds=90.0, stop=stop)))
        thread.start()
        try:
            page.wait_for_function("document.getElementById('status').textContent.startsWith('recording')",
                                   timeout=30000)
            page.wait_for_function("window.viewerStats.live.length >= 10 && S.current && S.current.ov.mesh",
                                   timeout=90000)
            assert "live analysis" in page.locator("#source-label").inner_text()
        finally:
            stop.set()
            thread.join(30)
        page.wait_for_function("document.getElementById('status').textContent.startsWith('complete')",
                               timeout=30000)
        live = page.evaluate("window.viewerStats.live")
        received = page.evaluate("window.viewerStats.liveReceived")
        page.close()
    assert out["count"].dropped == 0
    frames = [e["frame"] for e in received]
    assert frames == sorted(frames) and len(set(frames)) == len(frames)
    p50, p95, _ = latency_percentiles(live)
    record_property("live_updates", len(live))
    record_property("live_latency_p95_ms", p95)
    print(f"live: {len(received)} analysed frames received, {len(live)} shown in {out['count'].seconds:.1f} s; "
          f"exposure to screen p50 {p50:.0f} ms, p95 {p95:.0f} ms")
    assert problems == []

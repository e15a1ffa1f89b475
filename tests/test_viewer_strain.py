"""The viewer's strain maps, gauge, exports and study overview (issue 40) in headless Chromium, on a data directory
of two analysed trials (features and flow: the ``analysed_study`` fixture)."""

from __future__ import annotations

import csv

import pytest

from skinstretch.experiments.viewer.browser import browser_unavailable_reason
from tests.test_viewer_browser import _overlay_pixels as _pixels
from tests.test_viewer_browser import browser  # noqa: F401 - the module's Chromium, a fixture

REASON = browser_unavailable_reason()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"no browser can be driven here: {REASON}")


@pytest.fixture(scope="module")
def served(analysed_study):
    from skinstretch.experiments.viewer.server import start_server
    from skinstretch.experiments.viewer.session_data import find_view_target

    server = start_server(find_view_target(analysed_study), live=False)
    yield server
    server.stop()


@pytest.fixture()
def page(browser, served):
    page = browser.new_page(viewport={"width": 1400, "height": 1100}, accept_downloads=True)
    problems: list[str] = []
    page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.goto(served.url)
    page.wait_for_function("window.viewerStats.shown.length > 0 && S.info.results", timeout=30000)
    page.problems = problems
    yield page
    page.close()


def _screen(page, x: float, y: float) -> tuple[float, float]:
    """Page coordinates of image pixel (x, y)."""
    box = page.locator("#view").bounding_box()
    sc = page.evaluate("S.scale") * box["width"] / page.evaluate("document.getElementById('view').width")
    return box["x"] + x * sc, box["y"] + y * sc


def _goto_frame(page, k: int) -> None:
    page.evaluate(f"setFollow(false); showFrame({k})")  # as stepping does: a followed directory stays put
    page.wait_for_function(f"S.k === {k} && !S.busy")


def test_maps_colour_range_and_arrow_magnification(page):
    _goto_frame(page, 10)
    quantities = page.eval_on_selector_all("#map-quantity option", "o => o.map(e => e.value)")
    assert quantities[:7] == ["area", "edge", "exx", "eyy", "exy", "e1", "e2"]
    drawn = {}
    for q in ("area", "edge", "exx", "e1"):
        page.select_option("#map-quantity", q)
        page.wait_for_function(f"S.quantity === '{q}'")
        drawn[q] = _pixels(page)
        title = page.locator("#map-title").inner_text()
        assert (q in title) or (q == "area" and "Area" in title) or (q == "edge" and "Edge" in title)
    assert len(set(drawn.values())) == 4, "every map draws something of its own"
    # One scale per quantity for the whole session, unless fixed by the user; a fixed one holds across frames.
    auto = float(page.locator("#colorbar").get_attribute("data-scale"))
    assert auto == page.evaluate("S.info.results.map_scales['1'].e1")
    page.check("#range-fixed")
    page.fill("#range-value", "0.25")
    page.dispatch_event("#range-value", "change")
    page.wait_for_function("S.fixedRange === 0.0025")
    _goto_frame(page, 12)
    assert float(page.locator("#colorbar").get_attribute("data-scale")) == pytest.approx(0.0025)
    page.uncheck("#range-fixed")
    page.wait_for_function("S.fixedRange === null")
    # Arrow magnification
    page.check('input[data-overlay="arrows"]')
    before = _pixels(page)
    page.fill("#arrow-gain-input", "25")
    page.dispatch_event("#arrow-gain-input", "change")
    page.wait_for_function("S.arrowGain === 25")
    assert _pixels(page) != before
    assert "×25" in page.locator("#legend-items").inner_text()
    # The cumulative strain, from the reference frame, as a span of its own.
    page.select_option("#span", "0")
    page.wait_for_function("S.span === 0 && S.current.ov.mesh && S.current.ov.mesh.span === 0")
    assert page.evaluate("S.current.ov.mesh.frame_a") == page.evaluate("S.info.results.reference_frame")
    assert page.problems == []


def test_gauge_extensometer_and_both_exports(page, tmp_path):
    _goto_frame(page, 8)
    cx, cy = page.evaluate("""() => { const xy = S.current.ov.mesh.xy; let sx = 0, sy = 0;
        for (const t of xy) { sx += (t[0] + t[2] + t[4]) / 3; sy += (t[1] + t[3] + t[5]) / 3; }
        return [sx / xy.length, sy / xy.length]; }""")
    page.check("#tool-gauge")
    page.fill("#gauge-radius", "1.5")
    page.mouse.click(*_screen(page, cx, cy))
    page.wait_for_function("S.gauge && S.gauge.kind === 'gauge'")
    assert page.locator("#gauge-panel").is_visible()
    cols = page.evaluate("S.gauge.columns")
    assert len(cols["frame"]) == 20 and sum(cols["ok"]) >= 15
    k = 8  # placed on frame 8: the gauge is where the click was in that frame
    assert abs(cols["x"][k] - cx) < 1.0 and abs(cols["y"][k] - cy) < 1.0
    assert "exx" in page.locator("#gauge-note").inner_text()
    assert page.evaluate("""() => { const c = document.getElementById('gauge-plot');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0; for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; }""") > 500
    with page.expect_download() as dl:
        page.click("#save-csv")
    path = tmp_path / "gauge.csv"
    dl.value.save_as(path)
    rows = list(csv.DictReader(path.read_text().splitlines()))
    assert len(rows) == 20 and {"frame", "x", "y", "dx", "dy", "exx", "eyy", "exy", "e1", "e2"} <= set(rows[0])
    assert float(rows[k]["x"]) == pytest.approx(cols["x"][k], abs=1e-3)
    with page.expect_download() as dl:
        page.click("#save-png")
    png = tmp_path / "view.png"
    dl.value.save_as(png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10000
    # Extensometer: drag between two points 3 mm apart.
    half = 1.5 * page.evaluate("S.info.px_per_mm")
    page.check("#tool-extensometer")
    page.mouse.move(*_screen(page, cx - half, cy))
    page.mouse.down()
    page.mouse.move(*_screen(page, cx, cy), steps=4)
    page.mouse.move(*_screen(page, cx + half, cy), steps=4)
    page.mouse.up()
    page.wait_for_function("S.gauge && S.gauge.kind === 'extensometer'")
    cols = page.evaluate("S.gauge.columns")
    assert abs(cols["length_px"][k] - 2 * half) < 1.0
    assert "length" in page.locator("#gauge-note").inner_text()
    page.screenshot(path=str(tmp_path / "viewer-gauge.png"))
    assert page.problems == []


def test_study_overview_lists_the_trials_and_opens_one(page, served):
    assert page.locator("#study-link").is_visible()
    shown_before = page.evaluate("S.info.trial_dir || S.info.path_name")
    page.click("#study-link")
    page.wait_for_function("document.querySelectorAll('#trials tbody tr').length === 2")
    text = page.locator("#trials").inner_text()
    for word in ("000-flat-r1", "001-ridge-r1", "s01", "demo", "flat", "ridge", "features", "flow"):
        assert word in text
    assert page.evaluate("""() => { const c = document.getElementById('profiles');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0; for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; }""") > 2000
    # Open the trial not shown (the newest, 001, is followed at first).
    row = page.locator("#trials tbody tr:not(.shown)").first
    name = row.locator("td").first.inner_text().split("/")[-1]
    row.click()
    page.wait_for_url(served.url.split("?")[0])
    page.wait_for_function("window.viewerStats && window.viewerStats.shown.length > 0 && S.info.results")
    assert name in page.locator("#title").inner_text()
    assert name not in str(shown_before)
    assert page.evaluate("S.follow") is False
    page.goto(served.url.split("?")[0] + "study")
    page.wait_for_function("document.querySelectorAll('#trials tbody tr').length === 2")
    assert name in page.locator("#trials tbody tr.shown").inner_text()
    page.click("#follow")  # back to following the newest trial
    page.wait_for_function("window.viewerStats && window.viewerStats.shown.length > 0")
    assert page.problems == []

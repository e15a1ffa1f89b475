"""The HTML report: one number from one computation (tables and figure titles agree), errors with their units,
strain maps in colour with a colorbar, the viewer command, and every kind of target (analysis output, session
file)."""

from __future__ import annotations

import json
import re
from html import escape as html_escape

import numpy as np
import pytest

from skinstretch.cli import main
from skinstretch.experiments import report as report_module
from skinstretch.experiments.playback import PlaybackResult


@pytest.fixture(scope="module")
def analysed(tmp_path_factory):
    from skinstretch.simulators.scene import simulate_to_file

    d = tmp_path_factory.mktemp("report")
    session = simulate_to_file("ridgeL", d / "ridge.h5", n_frames=14, seed=1)
    assert main(["analyze", str(session), "-o", str(d / "out"), "--min-track", "3", "--span", "1", "-q"]) == 0
    return session, d / "out"


def _text(html: str) -> str:
    return re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", re.sub(r'src="data:[^"]+"', "", html)))


def test_report_of_an_analysis_output_has_units_and_the_viewer_command(analysed):
    session, out = analysed
    assert main(["report", str(out), "-q"]) == 0
    html = (out / "report.html").read_text()
    text = _text(html)
    assert f"skinstretch view {out}" in text
    for header in ("displacement RMSE (px)", "displacement RMSE (um)", "wrong matches (%)",
                   "edge strain RMSE span 1 (%)"):
        assert header in text
    # the per-trial table and the summary show the same numbers, from one evaluation
    summary = re.search(r"displacement RMSE \(px\).*?ridge ([0-9.e-]+) ([0-9.e-]+)", text)
    detail = re.search(r"tracking: displacement rmse ([0-9.e-]+) px tracking: displacement rmse ([0-9.e-]+) um", text)
    assert summary and detail and summary.groups() == detail.groups()
    px, um = (float(v) for v in detail.groups())
    from skinstretch.drivers.session_file import open_session

    with open_session(session) as s:
        assert um == pytest.approx(px / s.calibration.px_per_mm * 1000, rel=0.01)
    assert re.search(r"strain: edge strain RMSE, span 1 [0-9.e-]+ %", text)
    assert html.count("data:image/png;base64") >= 3
    # the analysis's caveats come with its numbers (a 14-frame slide over a ridge leaves the shading in)
    notes = json.loads((out / "summary.json").read_text())["notes"]
    assert any("glass-fixed shading over the ridge was left in" in n for n in notes)
    for n in notes:
        assert _text(f"<li>{html_escape(n)}</li>").strip() in text
    assert "Analysis notes" in text
    # the plan it executed, with the parameter it did not apply as asked (no key frames over shading left in)
    assert "Analysis plan" in text and "key-frame anchoring off" in text
    assert "override: tracking.keyframe_interval_frames asked 5, used None" in text


def test_report_of_a_session_file_without_analysis(analysed, tmp_path):
    session, _ = analysed
    assert main(["report", str(session), "-o", str(tmp_path / "r.html"), "-q"]) == 0
    text = _text((tmp_path / "r.html").read_text())
    assert "No analysis results" in text and f"skinstretch view {session}" in text
    assert main(["report", str(tmp_path / "nothing"), "-q"]) == 2


def _playback(closed: bool, rng, offset_um: float) -> PlaybackResult:
    target = rng.normal(0, 10, (120, 10, 10))
    measured = target + rng.normal(0, offset_um, target.shape)
    measured[:20] += 5.0  # start-up: outside the error the playback reports
    return PlaybackResult(closed_loop=closed, frames_total=120, frames_played=120, target_um=target,
                          command_um=target, measured_um=measured, force_n=np.ones(120),
                          extra={"settle": 20, "rate_hz": 700.0})


def _rms_titles(monkeypatch, figure: str) -> list[str]:
    """The titles with "RMS" of every figure the report draws with ``fig6.<figure>`` (filled as it draws)."""
    titles: list[str] = []
    original = getattr(report_module.fig6, figure)

    def spy(*args, **kwargs):
        fig = original(*args, **kwargs)
        titles.extend(ax.get_title() for ax in fig.axes if "RMS" in ax.get_title())
        return fig

    monkeypatch.setattr(report_module.fig6, figure, spy)
    return titles


def test_playback_table_and_figure_titles_show_the_same_rms(rng, monkeypatch):
    """Issue 17: the table said 3.09 / 0.167 um and the figure 2.98 / 0.27 um for the same runs (the figure
    counted the start-up frames the table leaves out)."""
    runs = [_playback(False, rng, 3.0), _playback(True, rng, 0.2)]
    titles = _rms_titles(monkeypatch, "playback_figure")
    html = report_module._playback_section(runs)
    table = re.findall(r"<td>(?:open|closed) loop</td><td>120</td><td>120</td><td>20</td><td>([0-9.]+)</td>", html)
    assert [float(v) for v in table] == pytest.approx([p.rms_error_um for p in runs], rel=5e-3)
    assert [re.search(r"RMS ([0-9.]+) um", t).group(1) for t in titles] == table  # the same digits


def test_stretch_profile_titles_show_the_amplitude_of_the_table(analysed, monkeypatch, tmp_path):
    """The profile figure's title said RMS 0.076 % where the table's amplitude of the same ridge trial was 0.092 %
    (the title counted the profile's end strips, which the amplitude leaves out)."""
    session, out = analysed
    titles = _rms_titles(monkeypatch, "stretch_profile_figure")
    assert main(["report", str(out), "-o", str(tmp_path / "r.html"), "-q"]) == 0
    table = re.search(r"profile: amplitude ([0-9.e+-]+) %", _text((tmp_path / "r.html").read_text()))
    assert table and len(titles) == 1
    assert re.search(r"RMS ([0-9.e+-]+) %", titles[0]).group(1) == table.group(1)


@pytest.mark.parametrize("method", ["features", "flow"])
def test_report_of_an_imported_print_clip_draws_every_figure(tmp_path, method):
    """A user's clip (a real print at 19.7 px/mm on white, PNG frames, imported): every figure of its report is
    drawn; none is replaced by a note that it could not be (an IndexError once replaced one)."""
    import cv2

    from tests.print_clips import print_frame, print_image

    image = print_image()
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(16):
        cv2.imwrite(str(frames / f"f{k:03d}.png"),
                    np.clip(print_frame(image, k, px_per_mm=19.7, background=255.0), 0, 255).astype(np.uint8))
    session, out = tmp_path / "clip.h5", tmp_path / "out"
    assert main(["import", str(frames), "-o", str(session), "--px-per-mm", "19.7", "--fps", "60", "-q"]) == 0
    assert main(["analyze", str(session), "-o", str(out), "--method", method, "--span", "1,5", "--min-track", "5",
                 "--parallel", "serial", "-q"]) == 0
    assert main(["report", str(out), "-q"]) == 0
    text = _text((out / "report.html").read_text())
    assert "could not be drawn" not in text and "Error:" not in text
    assert (out / "report.html").read_text().count("data:image/png;base64") >= 3

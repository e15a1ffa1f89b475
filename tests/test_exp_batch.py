"""Batch analysis: every session analysed, a broken one reported without stopping the others, the summary
table and the per-surface Figure 94 written; profile averaging on a common grid."""

import json

import numpy as np
import pytest

from skinstretch.drivers.session_file import write_session
from skinstretch.experiments.batch import analyze_many, average_profiles, find_sessions
from skinstretch.processing.errors import InvalidInputError


@pytest.fixture
def batch_dir(tmp_path, rng):
    from skinstretch.drivers.camera_modes import CameraMode
    from skinstretch.processing.pixel_scale import Calibration

    d = tmp_path / "in"
    (d / "s01").mkdir(parents=True)
    md = {"subject": {"id": "s01"}, "surface": {"kind": "flat"}, "scene": "flatL"}
    write_session(d / "s01" / "a.h5", rng.integers(0, 255, (8, 48, 64), dtype=np.uint8),
                  timestamps=np.arange(8) / 60, camera_mode=CameraMode("tiny", 64, 48, 60.0),
                  calibration=Calibration(px_per_mm=62.0), metadata=md)
    (d / "s01" / "broken.h5").write_bytes(b"not a session")
    return d


def _fake_analyse_trial(session_path, outdir, method, params, overwrite=False):
    """Stands in for the (slow, JIT-compiled) analysis: a valid results file with a known profile."""
    import json
    from pathlib import Path

    from skinstretch.drivers.session_file import open_session
    from skinstretch.experiments.results_file import PAIR_DTYPE, MOTION_DTYPE, ResultsWriter
    from skinstretch.experiments.runner import TrialAnalysis

    try:
        with open_session(session_path) as s:  # a broken session fails here, as the real analysis would
            n, h, w = s.shape
            px = s.calibration.px_per_mm
    except Exception as exc:  # noqa: BLE001 - the real analyse_trial returns failures as values
        return TrialAnalysis(False, error=str(exc))
    x = np.arange(0, w, 16.0)
    Path(outdir).mkdir(parents=True, exist_ok=True)
    wr = ResultsWriter(Path(outdir) / "results.h5")
    wr.append("motion_pairs", np.zeros(0, PAIR_DTYPE))
    wr.append("motion", np.zeros(0, MOTION_DTYPE))
    wr.append("strain/span_1/pairs", np.zeros(0, PAIR_DTYPE))
    wr.file["strain/span_1"].attrs["span"] = 1
    wr.array("frame_flags", np.array([b""] * n, dtype="S128"))
    wr.array("fingertip/displacement", np.zeros((n - 1, 2)))
    wr.array("fingertip/n_points", np.zeros(n - 1, np.int64))
    wr.array("fingertip/valid", np.ones(n - 1, bool))
    wr.array("fingertip/position", np.zeros((n, 2)))
    wr.array("profile/position", x)
    wr.array("profile/change", 1e-4 * x)
    wr.array("profile/valid", np.ones(x.size, bool))
    wr.file["profile"].attrs["axis"] = "x"
    attrs = {"method": method, "session_path": str(session_path), "n_frames": n, "image_shape": [h, w],
             "px_per_mm": px, "coordinates": "image", "timing_json": "{}", "params_json": "{}", "versions_json": "{}",
             "window_json": json.dumps({"status": "none"}),
             "summary_json": json.dumps({"n_trajectories": 12, "min_track_frames": 4,
                                         "notes": ["a short clip", "no strain over 11 frames"],
                                         "density": {"warning": "too sparse"}})}
    r = wr.finish(attrs)
    return TrialAnalysis(True, str(r.path), 0.01)


def test_batch_reports_failures_and_summarises(batch_dir, tmp_path, monkeypatch, caplog, propagate_logs):
    import skinstretch.experiments.batch

    monkeypatch.setattr(skinstretch.experiments.batch, "analyse_trial", _fake_analyse_trial)
    with caplog.at_level("INFO", logger="skinstretch"):
        result = analyze_many([batch_dir], tmp_path / "out", scheduler="synchronous",
                              params={"strain": {"spans": [1]}}, progress=False)
    rows = {r.session.rsplit("/", 1)[-1]: r for r in result.rows}
    assert rows["broken.h5"].status == "failed" and "not an HDF5 file" in rows["broken.h5"].error
    good = rows["a.h5"]
    assert good.status == "ok", good.error
    assert good.subject == "s01" and good.surface == "flat" and good.n_frames == 8
    assert (tmp_path / "out" / "s01" / "a" / "results.h5").exists()
    table = json.loads(result.table_json.read_text())
    assert len(table) == 2 and {r["status"] for r in table} == {"ok", "failed"}
    assert result.table_csv.read_text().count("\n") == 3
    # What the analysis said about the clip reaches the table (a worker's log may not reach this console).
    assert (good.n_trajectories, good.min_track_frames) == (12, 4)
    assert good.notes == "a short clip | no strain over 11 frames | too sparse"
    assert "a short clip | no strain over 11 frames | too sparse" in result.table_csv.read_text()
    x, mean, _, n = result.profiles["flat"]
    np.testing.assert_allclose(mean, 1e-4 * x * good_px_per_mm(batch_dir), rtol=1e-6)
    assert result.figure is not None and result.figure.exists()
    assert "FAILED" in caplog.text
    # The same folder again: refused before anything is analysed, naming overwrite; replaced with it.
    from skinstretch.experiments.output_paths import OutputPathError

    with pytest.raises(OutputPathError, match=r"out: holds the results of an analysis already \(batch.json\); "
                                              r"pass overwrite=True to replace them"):
        analyze_many([batch_dir], tmp_path / "out", scheduler="synchronous", progress=False)
    again = analyze_many([batch_dir], tmp_path / "out", scheduler="synchronous", progress=False, overwrite=True)
    assert [r.status for r in again.rows] == [r.status for r in result.rows]


@pytest.fixture
def propagate_logs():
    """The command line stops skinstretch's log records at its own handler; let them reach caplog here."""
    import logging

    log = logging.getLogger("skinstretch")
    before = log.propagate
    log.propagate = True
    yield
    log.propagate = before


def test_batch_on_an_external_scheduler_shows_progress(batch_dir, tmp_path, capsys, caplog, propagate_logs):
    """Progress bar and per-session lines with a scheduler the batch did not start (issue 17 item 7)."""
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            caplog.at_level("INFO", logger="skinstretch"):
        result = analyze_many([batch_dir / "s01" / "broken.h5"], tmp_path / "ext", scheduler=cluster.scheduler_address,
                              progress=True)
    assert [r.status for r in result.rows] == ["failed"] and "not an HDF5 file" in result.rows[0].error
    assert "sessions:" in capsys.readouterr().err  # the progress bar
    assert "broken.h5: FAILED" in caplog.text  # and a line per session


def good_px_per_mm(batch_dir):
    from skinstretch.drivers.session_file import open_session

    with open_session(batch_dir / "s01" / "a.h5") as s:
        return s.calibration.px_per_mm


def test_average_profiles_on_common_grid():
    x1 = np.linspace(0, 4, 17)
    x2 = np.linspace(1, 5, 17)
    grid, mean, std, n = average_profiles([(x1, 0.01 * x1), (x2, 0.01 * x2 + 0.02)], step_mm=0.5)
    assert grid[0] == 0 and grid[-1] == 5
    inside = (grid >= 1) & (grid <= 4)
    np.testing.assert_allclose(mean[inside], 0.01 * grid[inside] + 0.01)
    assert np.all(n[inside] == 2) and n[0] == 1 and n[-1] == 1
    with pytest.raises(InvalidInputError, match="profiles"):
        average_profiles([])


def test_find_sessions_errors(tmp_path):
    with pytest.raises(InvalidInputError, match="does not exist"):
        find_sessions([tmp_path / "nope"])
    with pytest.raises(InvalidInputError, match="no session file"):
        find_sessions([tmp_path])


def test_batch_progress_counts_sessions_and_its_lines_stand_apart_from_the_bar(batch_dir, tmp_path, monkeypatch,
                                                                               capsys):
    """The command line's bar counts sessions (it said frame/s) and each session's line is written on a line of its
    own above it (it was appended to the bar's line)."""
    import skinstretch.experiments.batch
    from skinstretch.cli import main

    monkeypatch.setattr(skinstretch.experiments.batch, "analyse_trial", _fake_analyse_trial)
    assert main(["analyze", str(batch_dir), "-o", str(tmp_path / "out"), "--scheduler", "synchronous"]) == 1
    err = capsys.readouterr().err
    assert "sessions:" in err and ("session/s" in err or "s/session" in err)
    outcome_lines = [line.split("\r")[-1] for line in err.split("\n") if ".h5: ok" in line or ".h5: FAILED" in line]
    assert len(outcome_lines) == 2 and all(line.startswith("batch: ") for line in outcome_lines), err

"""The study overview of a data directory (issue 40) and the report's strain tensor maps."""

from __future__ import annotations

import math
import re
import shutil

import pytest

from skinstretch.cli import main


@pytest.fixture(scope="module")
def datadir(tmp_path_factory, analysed_study, sim_session):
    """The analysed study (000-flat-r1 features, 001-ridge-r1 flow) and a trial not analysed, 002-flat-r2."""
    from skinstretch.drivers.session_file import write_session

    root = tmp_path_factory.mktemp("data")
    shutil.copytree(analysed_study, root, dirs_exist_ok=True)
    s = sim_session
    trial = root / "s01" / "study" / "002-flat-r2"
    trial.mkdir(parents=True)
    md = {**s.metadata, "trial": "002-flat-r2", "subject": {"id": "s01"}, "protocol": "demo", "surface": {"kind": "flat"}}
    write_session(trial / "session.h5", s.frames, timestamps=s.timestamps, camera_mode=s.camera_mode,
                  calibration=s.calibration, metadata=md)
    return root


def test_study_overview_has_one_typed_row_per_trial(datadir):
    from skinstretch.experiments.study import study_overview

    rows = study_overview(datadir)
    assert [r.name for r in rows] == ["s01/study/000-flat-r1", "s01/study/001-ridge-r1", "s01/study/002-flat-r2"]
    a, b, c = rows
    assert (a.subject, a.protocol, a.surface, a.method) == ("s01", "demo", "flat", "features")
    assert (b.surface, b.method) == ("ridge", "flow")
    for r in (a, b):
        assert r.n_frames == 20 and r.status.startswith("complete")
        assert math.isfinite(r.edge_change_p5) and r.edge_change_p5 < r.edge_change_p95
        assert math.isfinite(r.cumulative_e1) and r.cumulative_e1 >= r.cumulative_e2
        assert r.profile is not None and r.travel_mm > 0
    assert c.method == "" and c.warnings == ["not analysed"] and c.profile is None
    assert c.to_json()["cumulative_e1"] is None  # JSON-safe, not NaN


def test_report_of_a_data_directory_has_the_study_and_the_tensor_maps(datadir):
    assert main(["report", str(datadir)]) == 0
    html = (datadir / "report.html").read_text()
    assert "<h2>Study overview</h2>" in html
    for name in ("s01/study/000-flat-r1", "s01/study/001-ridge-r1", "s01/study/002-flat-r2"):
        anchor = "trial-" + re.sub(r"[^A-Za-z0-9_-]", "-", name)
        assert f'href="#{anchor}"' in html and f'id="{anchor}"' in html
    assert "one colour per surface" in html
    assert html.count("<figcaption>Strain tensor maps (cumulative from frame 0)") == 2  # the two analysed trials
    assert "not analysed" in html
    assert "not available" not in html

"""Every file skinstretch writes explains itself in one vocabulary (skinstretch.drivers.file_vocabulary): a session
recorded on the simulated rig (frames, force, display state, the simulator's truth attached), a simulated session
and the log of a played movie here; analysis outputs of both methods in test_track_pipeline. And an output that
exists already is refused in one line naming --overwrite, or replaced with it (play, calibrate)."""

import numpy as np
import pytest

from skinstretch.cli import main
from skinstretch.drivers.file_vocabulary import AXES, UNITS, DatasetInfo, unit_words
from skinstretch.drivers.session_file import KNOWN_STREAMS, SESSION_DATASETS, open_session
from skinstretch.experiments.results_file import RESULTS_DATASETS
from tests.helpers import assert_file_explains_itself

PROTOCOL = """\
name: words
subject: {id: s01}
camera_mode: strip
trials:
  - {name: flat, duration_s: 0.05}
record: {frames: true, force: true, display: true}
analysis: {enabled: false}
"""


def test_the_schemas_speak_the_vocabulary():
    infos = [*SESSION_DATASETS.values(), *RESULTS_DATASETS.values(), *(s.info() for s in KNOWN_STREAMS.values())]
    for info in infos:
        assert set(unit_words(info.units)) <= UNITS and set(info.axes) <= set(AXES), info
    assert DatasetInfo('{"x": "px", "n": "1"}', ("row",), "t").column_units() == {"x": "px", "n": "1"}
    force = KNOWN_STREAMS["force"].info()
    assert force.column_units() == {"fx": "N", "fy": "N", "fz": "N", "tx": "N m", "ty": "N m", "tz": "N m"}


def test_a_recorded_a_simulated_session_and_a_playback_log_explain_themselves(tmp_path, capsys):
    proto = tmp_path / "p.yaml"
    proto.write_text(PROTOCOL)
    assert main(["record", str(proto), "-o", str(tmp_path / "data"), "--no-movie", "--quiet"]) == 0
    recorded = assert_file_explains_itself(tmp_path / "data" / "s01" / "words" / "000-flat-r1" / "session.h5")
    assert {"frames", "streams/force/data", "streams/display_state/data", "truth/strain"} <= set(recorded)
    assert recorded["frames"].axes == ("frame", "y", "x") and recorded["truth/strain"].units == "1"

    sim = tmp_path / "sim.h5"
    assert main(["simulate", "flatL", "-o", str(sim), "--frames", "2", "--quiet"]) == 0
    assert set(assert_file_explains_itself(sim)) >= {"truth/feature_kind", "truth/displacement"}

    movie = tmp_path / "m.npy"
    np.save(movie, 10.0 * np.sin(np.arange(70) / 10.0)[:, None, None] * np.ones((1, 10, 10)))
    log = tmp_path / "pb.h5"
    # 3: the movie was stopped (a host too loaded to feed the display twin in time): logged all the same
    assert main(["play", str(movie), "--movie-rate", "700", "-o", str(log), "--quiet"]) in (0, 3)
    played = assert_file_explains_itself(log)
    assert played["streams/display_measured/data"].axes == ("sample", "contactor_row", "contactor_column")
    assert played["streams/force/data"].columns == ("fx", "fy", "fz", "tx", "ty", "tz")

    # The log exists now: refused in one line naming --overwrite (untouched), replaced with it.
    capsys.readouterr()
    stamp = log.stat().st_mtime_ns
    assert main(["play", str(movie), "--movie-rate", "700", "-o", str(log)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"skinstretch play: error: {log}: exists already; pass --overwrite to replace it"]
    assert log.stat().st_mtime_ns == stamp
    assert main(["play", str(movie), "--movie-rate", "350", "-o", str(log), "--overwrite", "--quiet"]) in (0, 3)
    with open_session(log) as s:  # the movie resampled from 350 Hz: twice the frames of the first
        assert s.metadata["frames"] == 139 and s.status in ("complete", "failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "m.npy", "p.yaml", "pb.h5", "sim.h5"]


def test_calibrate_refuses_an_existing_output_before_fitting(tmp_path, capsys):
    out = tmp_path / "cal.json"
    out.write_text("{}")
    assert main(["calibrate", str(tmp_path / "no-grid.png"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{out}: exists already; pass --overwrite to replace it" in err[0]
    assert out.read_text() == "{}"
    assert main(["calibrate", str(tmp_path / "no-grid.png"), "-o", str(out), "--overwrite"]) == 2
    assert "no-grid.png" in capsys.readouterr().err  # with --overwrite it goes on, to the missing image


@pytest.mark.parametrize("name", ["session-v1-before-units.h5", "session-v1-simulated-before-units.h5"])
def test_a_session_written_before_is_described_in_the_same_words(name):
    from pathlib import Path

    with open_session(Path(__file__).parent / "data" / name) as s:
        for dataset in ("frames", "timestamps", "status") + (("truth/strain",) if s.has_truth else ()):
            info = s.dataset_info(dataset)
            assert set(unit_words(info.units)) <= UNITS and set(info.axes) <= set(AXES)

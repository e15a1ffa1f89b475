"""The analyze pipeline, results file and evaluate command on a short simulated session."""

import json

import numpy as np
import pytest

from skinstretch.cli import main
from skinstretch.experiments.analysis import analysis_params, analyze_frames, analyze_session
from skinstretch.experiments.analysis.derive import chain_flows
from skinstretch.experiments.output_paths import OutputPathError
from skinstretch.experiments.results_file import PairStatus, read_results
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.drivers.errors import SessionFileError
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.flow import DenseFlow
from skinstretch.processing.tracking import TrackingParams
from tests.helpers import assert_file_explains_itself
from tests.test_track_support import affine_field, render

scene = pytest.importorskip("skinstretch.simulators.scene")

N_FRAMES = 8


@pytest.fixture(scope="module")
def session_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("track") / "ridge.h5"
    scene.simulate_to_file("ridgeL", path, n_frames=N_FRAMES, seed=1)
    return path


@pytest.mark.parametrize("method", ["features", "flow"])
def test_analyze_and_evaluate_commands(session_file, tmp_path, method, capsys):
    out = tmp_path / method
    code = main(["analyze", str(session_file), "-o", str(out), "--method", method, "--span", "1,3",
                 "--min-track", "4", "--quiet"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == method and summary["n_frames"] == N_FRAMES
    r = read_results(out)
    assert set(r.strain) == {1, 3}
    assert r.strain[1].ok.all()
    assert r.summary["min_track_frames"] == (4 if method == "features" else None)
    assert r.tactile_positions_um.shape == (N_FRAMES, 10, 10)
    assert np.all(np.abs(r.tactile_positions_um) <= 50)
    assert np.all(np.isfinite(r.motion["dx"]))
    for span, strain in r.strain.items():  # streamed while the analysis ran: numpy's on the stored edges
        assert summary[f"strain_span_{span}"]["edge_change_p5_p95"] == np.percentile(strain.edges["change"],
                                                                                     [5, 95]).tolist()
    _every_dataset_has_units_and_codes(out / "results.h5")
    capsys.readouterr()
    assert main(["evaluate", str(out), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    for part in ("features", "tracking", "strain", "profile", "timing"):
        assert part in result
    assert result["tracking"]["displacement_rmse_px"] < 0.3
    assert result["strain"]["edge_rmse_1"] < 0.01
    if method == "features":
        assert result["tracking"]["wrong_match_rate"] <= 0.01
        assert result["features"]["pore"]["recall"] > 0.5
    else:
        assert result["tracking"]["wrong_match_rate"] is None
    # Results already in the folder: refused in one line naming --overwrite, untouched; replaced with it.
    stamp = (out / "results.h5").stat().st_mtime_ns
    assert main(["analyze", str(session_file), "-o", str(out), "--method", method]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{out}: holds the results of an analysis already" in err[0], err
    assert err[0].endswith("pass --overwrite to replace them") and (out / "results.h5").stat().st_mtime_ns == stamp
    if method == "flow":
        assert main(["analyze", str(session_file), "-o", str(out), "--method", method, "--span", "2",
                     "--overwrite", "--quiet"]) == 0
        assert set(read_results(out).strain) == {2} and json.loads((out / "summary.json").read_text())["n_frames"]


def _every_dataset_has_units_and_codes(path):
    import h5py

    infos = assert_file_explains_itself(path)
    with h5py.File(path, "r") as f:
        assert json.loads(f.attrs["status_codes"])["0"] == "ok" and json.loads(f.attrs["kind_codes"])["2"] == "pore"
        assert f["profile"].attrs["axis"] in ("x", "y")
    for name in ("motion", "strain/span_1/edges"):
        units = infos[name].column_units()
        assert units.get("x", units.get("xa")) == "px" and units.get("pair") == "1"
    assert infos["strain/span_1/edges"].column_units()["change"] == "1"  # a strain: a fraction
    assert read_results(path).dataset_info("fingertip/position") == infos["fingertip/position"]


def test_results_file_errors(tmp_path):
    with pytest.raises(SessionFileError, match="no such"):
        read_results(tmp_path / "missing.h5")
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5 at all")
    with pytest.raises(SessionFileError):
        read_results(bad)
    import h5py

    with h5py.File(tmp_path / "foreign.h5", "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(SessionFileError, match="not a skinstretch results"):
        read_results(tmp_path / "foreign.h5")


def test_pipeline_on_a_sequence_with_an_empty_frame_and_lost_contact(tmp_path):
    """Synthetic images: a blank frame mid-sequence and contact lost over part of the image give flags."""
    cal = Calibration(px_per_mm=62.0)
    frames = [render(affine_field(2.0 * k, 0.5 * k), shape=(240, 320), noise=1.0) for k in range(6)]
    frames[3] = np.full_like(frames[3], 235)  # no finger in this frame
    for f in frames[4:]:
        f[:, 240:] = 235  # contact lost on the right
    params = analysis_params({"strain": {"spans": [1, 2]}, "execution": {"kind": "serial"}})
    r = analyze_frames(frames, calibration=cal, method="flow", params=params)
    assert r.frame_flags[3] == "no contact"
    status = r.strain[1].pairs["status"]
    assert status[3] != PairStatus.OK and status[0] == PairStatus.OK
    assert not r.fingertip.valid[3]
    assert np.all(np.isfinite(r.fingertip.position))
    valid_after = r.flow.valid[4]
    assert not valid_after[:, r.flow.grid_x > 260].any()
    back = analyze_frames(frames, calibration=cal, method="flow", params=params, results_path=tmp_path / "r.h5")
    back = read_results(tmp_path / "r.h5")
    assert back.frame_flags == r.frame_flags
    np.testing.assert_array_equal(back.strain[2].edges, r.strain[2].edges)
    assert not (tmp_path / "r.h5.partial").exists()
    with pytest.raises(InsufficientDataError):
        analyze_frames(frames[:1], calibration=cal)
    with pytest.raises(InvalidInputError, match="method"):
        analyze_frames(frames, calibration=cal, method="magic")


def test_chained_flow_follows_skin_points():
    cal = Calibration(px_per_mm=62.0)
    frames = [render(affine_field(1.5 * k, -0.7 * k), shape=(200, 240)) for k in range(3)]
    flow = DenseFlow(calibration=cal)
    fields = [flow.compute(frames[0], frames[1], frame_a=0, frame_b=1),
              flow.compute(frames[1], frames[2], frame_a=1, frame_b=2)]
    m = chain_flows(fields, stride=2)
    assert (m.frame_a, m.frame_b) == (0, 2) and len(m) > 20
    assert np.abs(np.median(m.displacement, axis=0) - [3.0, -1.4]).max() < 0.05


def test_analyze_session_rejects_bad_method(session_file, tmp_path):
    with pytest.raises(InvalidInputError, match="method"):
        analyze_session(session_file, tmp_path, method="optical")
    with pytest.raises(InvalidInputError, match="strain.spans"):
        analysis_params({"strain": {"spans": [0]}})
    with pytest.raises(SessionFileError):
        analyze_session(tmp_path / "nope.h5", tmp_path)
    (tmp_path / "summary.json").write_text("{}")  # an earlier analysis' output: refused before any work
    with pytest.raises(OutputPathError, match=r"holds the results of an analysis already \(summary.json\); pass "
                                              r"overwrite=True to replace them"):
        analyze_session(session_file, tmp_path)
    (tmp_path / "r.h5").write_bytes(b"x")
    with pytest.raises(OutputPathError, match=r"r.h5: exists already; pass overwrite=True to replace it"):
        analyze_frames(np.zeros((3, 8, 8), np.uint8), calibration=Calibration(px_per_mm=62.0),
                       results_path=tmp_path / "r.h5")
    assert TrackingParams().min_length_frames is None  # the seed's 30, adapted by the analysis to short clips


def test_a_short_clip_adapts_the_minimum_trajectory_length_and_says_so(session_file, tmp_path, caplog):
    with caplog.at_level("WARNING"):
        r = analyze_session(session_file, tmp_path / "a", params={"execution": {"kind": "serial"}})
    assert "8-frame clip" in caplog.text and "at least 4 frames" in caplog.text
    assert r.params["tracking"]["min_length_frames"] == 4 and r.summary["n_trajectories"] > 10
    # The default spans are 1 and 11 frames: an 8-frame session has no 11-frame pair, and says so (log and summary).
    assert "no strain over 11 frames" in caplog.text and "--span up to 7" in caplog.text
    notes = r.summary["notes"]
    assert len(notes) == 3 and "no strain over 11 frames" in notes[1]
    # 8 frames over a ridge are too few to remove its glass-fixed shading: said as well.
    assert "shading over the ridge was left in" in notes[2] and "shading over the ridge was left in" in caplog.text
    assert r.strain[11].pairs.shape[0] == 0


def test_a_minimum_length_longer_than_the_clip_is_one_line(session_file, tmp_path, capsys):
    code = main(["analyze", str(session_file), "-o", str(tmp_path / "b"), "--min-track", "30", "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--min-track" in err[0] and "8-frame" in err[0]
    assert not (tmp_path / "b" / "results.h5").exists() and not (tmp_path / "b" / "results.h5.partial").exists()

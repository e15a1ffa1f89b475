"""The analyze pipeline, results file and evaluate command on a short simulated session."""

import json

import numpy as np
import pytest

from skinstretch.experiments.analysis import AnalysisParams, analyze_frames, analyze_session, chain_flows
from skinstretch.cli import main
from skinstretch.experiments.results_file import read_results, write_results
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.drivers.errors import SessionFileError
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.flow import DenseFlow
from skinstretch.processing.tracking import TrackingParams
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
    assert (r.strain[1].pairs["status"] == b"ok").all()
    assert r.tactile_positions_um.shape == (N_FRAMES, 10, 10)
    assert np.all(np.abs(r.tactile_positions_um) <= 50)
    assert np.all(np.isfinite(r.motion["dx"]))
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
    r = analyze_frames(frames, calibration=cal, method="flow", params=AnalysisParams(spans=(1, 2)))
    assert r.frame_flags[3] == "no contact"
    status = r.strain[1].pairs["status"]
    assert status[3] != b"ok" and status[0] == b"ok"
    assert not r.fingertip_valid[3]
    assert np.all(np.isfinite(r.fingertip_position))
    valid_after = r.flow_valid[4]
    assert not valid_after[:, r.flow_grid_x > 260].any()
    path = write_results(tmp_path / "results.h5", r)
    back = read_results(path)
    assert back.frame_flags == r.frame_flags
    np.testing.assert_array_equal(back.strain[2].edges, r.strain[2].edges)
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
    with pytest.raises(InvalidInputError):
        AnalysisParams(spans=(0,))
    with pytest.raises(SessionFileError):
        analyze_session(tmp_path / "nope.h5", tmp_path)
    assert TrackingParams().min_length_frames == 30

"""Analysis options are checked where they enter: a protocol at load (file, line, field), the command line, the
Python API; the recorder's analysis call reports a failure as a value with a one-line reason."""

import argparse

import pytest

from skinstretch.cli import main
from skinstretch.experiments.analysis import analysis_params
from skinstretch.experiments.protocol import load_protocol, parse_protocol
from skinstretch.experiments.runner import analyse_trial
from skinstretch.processing.errors import ConfigError, InvalidInputError
from skinstretch.processing.tracking import TrackingParams

PROTOCOL = """\
name: p1
subject: {id: s01}
trials:
  - name: flat
    duration_s: 1.0
analysis:
  method: features
  options: OPTIONS
"""


@pytest.mark.parametrize(
    "options, field",
    [
        ("{spanz: [1, 11]}", "analysis.options.spanz"),
        ("{tracking: {min_trak: 10}}", "analysis.options.tracking.min_trak"),
        ("{strain: {spans: [0, 11]}}", "analysis.options.strain.spans"),
        ("{flow: {window_px: 16}}", "analysis.options.flow.window_px"),
        ("{tracking: {min_length_frames: 0}}", "analysis.options.tracking.min_length_frames"),
        ("{extraction: {heal_broken_valleys: 1}}", "analysis.options.extraction.heal_broken_valleys"),
    ],
)
def test_a_bad_option_stops_the_protocol_at_load_with_file_line_and_field(tmp_path, options, field):
    path = tmp_path / "protocol.yaml"
    path.write_text(PROTOCOL.replace("OPTIONS", options))
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    message = str(info.value)
    assert message.startswith(f"{path}:8: {field}:") and "\n" not in message


def test_good_options_keep_the_analysis_defaults_of_fields_not_given():
    p = parse_protocol(PROTOCOL.replace("OPTIONS", "{tracking: {min_length_frames: 12}, flow: {window_mm: 0.5}}"))
    o = p.analysis.options
    assert o.tracking == TrackingParams(min_length_frames=12, smoothing_radius_frames=0, max_bridge_frames=None)
    assert o.flow.window_mm == 0.5 and o.strain.spans == (1, 11)


def test_the_python_api_and_the_command_line_name_the_field(tmp_path, capsys):
    with pytest.raises(InvalidInputError, match=r"analysis\.strain\.max_edge_mm"):
        analysis_params({"strain": {"max_edge_mm": -1}})
    with pytest.raises(InvalidInputError, match=r"TrackingParams\.search_radius_mm"):
        TrackingParams(search_radius_mm=float("nan"))
    code = main(["analyze", str(tmp_path / "s.h5"), "-o", str(tmp_path / "o"), "--flow-scale-px", "16", "-q",
                 "--method", "flow"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--flow-scale-px: " in err[0]  # the flag that set it, not the field
    assert main(["analyze", str(tmp_path / "s.h5"), "-o", str(tmp_path / "o"), "--flow-scale", "0.5", "-q"]) == 2
    assert "--method flow" in capsys.readouterr().err


def test_a_failed_analysis_is_a_value_with_one_line(tmp_path):
    out = analyse_trial(str(tmp_path / "missing.h5"), str(tmp_path / "o"), "features", {})
    assert not out.ok and "no such session file" in out.error and "\n" not in out.error
    out = analyse_trial(str(tmp_path / "missing.h5"), str(tmp_path / "o"), "features", {"tracking": {"x": 1}})
    assert not out.ok and "analysis.tracking.x" in out.error


@pytest.fixture(scope="module")
def small_flow_session(tmp_path_factory, sim_session):
    """Four frames of the shared simulated session (a 160 x 200 px crop, its calibration) in a session file."""
    import numpy as np

    from skinstretch.drivers.camera_modes import CameraMode
    from skinstretch.drivers.session_file import write_session

    s = sim_session
    frames = np.ascontiguousarray(s.frames[:4, 150:310, 220:420])
    path = tmp_path_factory.mktemp("knob") / "s.h5"
    write_session(path, frames, timestamps=np.arange(4) / 60, camera_mode=CameraMode("crop", 200, 160, 60.0),
                  calibration=s.calibration, metadata={"surface": {"kind": "flat"}})
    return path, s.calibration


def test_the_flow_window_knob_reaches_the_flow_from_the_cli_the_api_and_a_protocol(tmp_path, small_flow_session):
    """The knob sets the registration window the analysis uses: its grid (a quarter of the window) and the
    parameters recorded with the results, from ``analyze --flow-scale-px`` and a protocol's ``analysis.options``
    (whole analyses), and ``--flow-scale`` (mm) and the Python API (the parameters they make)."""
    import numpy as np

    from skinstretch.experiments.results_file import read_results
    from skinstretch.processing.flow import DenseFlow

    path, cal = small_flow_session

    def grid_step(out):
        r = read_results(out / "results.h5")
        steps = np.unique(np.diff(r.flow.grid_x))
        return (int(steps[0]) if steps.size == 1 else None), r.params["flow"]

    assert main(["analyze", str(path), "-o", str(tmp_path / "cli"), "--method", "flow", "--flow-scale-px", "31",
                 "--parallel", "serial", "-q"]) == 0
    assert grid_step(tmp_path / "cli") == (8, grid_step(tmp_path / "cli")[1])
    assert grid_step(tmp_path / "cli")[1]["window_px"] == 31
    p = parse_protocol(PROTOCOL.replace("features", "flow").replace(
        "OPTIONS", "{flow: {window_px: 39}, execution: {kind: serial}}"))
    out = analyse_trial(str(path), str(tmp_path / "protocol"), p.analysis.method, p.analysis.options)
    assert out.ok, out.error
    step, flow = grid_step(tmp_path / "protocol")
    assert step == 10 and flow["window_px"] == 39
    # --flow-scale in mm and the Python API's options give the analysis these flow parameters.
    from skinstretch.experiments.commands.analyze import options_from_args

    args = argparse.Namespace(flow_scale=0.35, flow_scale_px=None, method="flow", min_track=None, span="1,11",
                              workers=None, parallel=None)
    flow = DenseFlow(calibration=cal, params=analysis_params(options_from_args(args)).flow)
    assert flow.window_px == 23 and flow.grid_step_px == 6
    flow = DenseFlow(calibration=cal, params=analysis_params({"flow": {"window_px": 17}}).flow)
    assert flow.window_px == 17 and flow.grid_step_px == 4
    assert DenseFlow(calibration=cal, params=analysis_params().flow).grid_step_px == 12  # the default 0.8 mm

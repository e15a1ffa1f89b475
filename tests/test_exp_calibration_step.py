"""The calibration step of a protocol (seed 3.4): fitted once before the trials, stored in every trial's session."""

import json

import cv2
import numpy as np
import pytest

from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.skin_mapping_step import calibrate_source, mapping_for_frames
from skinstretch.experiments.protocol import Rig, load_protocol
from skinstretch.experiments.runner import CALIBRATION_FILE, read_events, run_protocol
from skinstretch.processing.errors import CalibrationError, ConfigError
from skinstretch.simulators.dot_grid_images import render_calibration_grid
from skinstretch.simulators.prism_optics import PrismOptics

PROTOCOL = """\
name: calib
subject: {{id: s04}}
camera_mode: strip
trials:
  - {{name: flat, duration_s: 0.05}}
analysis: {{enabled: false}}
calibration: {{source: {source}, max_frames: 1}}
"""


@pytest.fixture(scope="module")
def grid_png(tmp_path_factory):
    path = tmp_path_factory.mktemp("grid") / "grid.png"
    image = render_calibration_grid(PrismOptics(), missing_fraction=0.05, seed=3).image
    cv2.imwrite(str(path), image)
    return path


def test_protocol_calibrates_once_and_stores_the_window_in_each_trial(grid_png, tmp_path):
    proto_path = tmp_path / "protocol.yaml"
    proto_path.write_text(PROTOCOL.format(source=grid_png.name))  # relative to the protocol file
    (tmp_path / grid_png.name).write_bytes(grid_png.read_bytes())
    protocol = load_protocol(proto_path)
    run = run_protocol(protocol, Rig(), tmp_path / "data", progress=lambda _m: None, play_movie=False)
    saved = run.directory / CALIBRATION_FILE
    full = calibrate_source(saved)[0]
    assert (full.width, full.height) == (640, 484)
    trial = run.trials[0]
    with open_session(trial.path) as s:
        mapping = s.calibration.mapping
        assert mapping is not None and (mapping.width, mapping.height) == (640, 100)  # strip: central window
        assert s.calibration.px_per_mm == pytest.approx(mapping.px_per_mm)
    xy = np.array([[320.0, 50.0]])
    np.testing.assert_allclose(mapping.image_to_surface(xy), full.image_to_surface(xy + [0, 192]), atol=1e-9)
    names = [d.get("name") for n, d in read_events(run.directory / "events.jsonl") if n == "event"]
    assert "calibration" in names


def test_untrustworthy_grid_stops_the_session_before_any_trial(tmp_path):
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((484, 640), 200, np.uint8))
    proto_path = tmp_path / "protocol.yaml"
    proto_path.write_text(PROTOCOL.format(source="blank.png"))
    with pytest.raises(CalibrationError):
        run_protocol(load_protocol(proto_path), Rig(), tmp_path / "data", progress=lambda _m: None)
    assert not list((tmp_path / "data").rglob("session.h5"))


def test_bad_calibration_sources_are_named(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"not": "a calibration"}))
    with pytest.raises(CalibrationError, match="bad.json"):
        calibrate_source(bad)
    with pytest.raises(ConfigError, match="calibration"):
        from skinstretch.experiments.protocol import parse_protocol

        parse_protocol(PROTOCOL.format(source="''"), source="<t>")


def test_central_window_refuses_larger_frames(grid_png):
    mapping = calibrate_source(grid_png, max_frames=1)[0]
    assert mapping_for_frames(mapping, 640, 484) is mapping
    with pytest.raises(Exception, match="larger"):
        mapping_for_frames(mapping, 1280, 484)

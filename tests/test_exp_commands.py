"""The record and report commands from the command line, on the simulated rig (analysis off to stay fast)."""

import json

from skinstretch.cli import main

PROTOCOL = """\
name: cli
subject: {id: s03}
camera_mode: strip
trials:
  - {name: flat, duration_s: 0.05}
analysis: {enabled: false}
"""


def test_record_then_report(tmp_path, capsys):
    proto = tmp_path / "p.yaml"
    proto.write_text(PROTOCOL)
    rig = tmp_path / "rig.yaml"
    rig.write_text("name: camera-only\ncamera: {kind: sim}\nforce: {kind: none}\ndisplay: {kind: none}\n")
    assert main(["record", str(proto), "--rig", str(rig), "-o", str(tmp_path / "data")]) == 0
    out = capsys.readouterr()
    sdir = tmp_path / "data" / "s03" / "cli"
    assert f"session: {sdir}" in out.out and "000-flat-r1: complete" in out.out
    assert (sdir / "000-flat-r1" / "session.h5").exists() and (sdir / "protocol.yaml").read_text() == PROTOCOL
    assert "camera-only" in (sdir / "rig.yaml").read_text()
    # a second run without --resume refuses to overwrite; with it, nothing is redone
    assert main(["record", str(proto), "-o", str(tmp_path / "data")]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(["record", str(proto), "--rig", str(rig), "-o", str(tmp_path / "data"), "--resume"]) == 0
    assert "already complete, skipped" in capsys.readouterr().err  # a progress line: logged
    assert main(["report", str(sdir)]) == 0
    html = (sdir / "report.html").read_text()
    assert "000-flat-r1" in html and "No analysis results" in html and "<h2>Parameters and versions" in html


def test_bad_protocol_names_line(tmp_path, capsys):
    proto = tmp_path / "bad.yaml"
    proto.write_text(PROTOCOL.replace("duration_s: 0.05", "duration_s: 0"))
    assert main(["record", str(proto), "-o", str(tmp_path / "d")]) == 2
    assert "bad.yaml:5: trials[0].duration_s" in capsys.readouterr().err


def test_evaluate_refuses_to_score_rectified_motion_against_image_truth(tmp_path, capsys):
    import h5py
    import pytest

    scene = pytest.importorskip("skinstretch.simulators.scene")
    session = tmp_path / "flat.h5"
    scene.simulate_to_file("flatL", session, n_frames=4, seed=2)
    out = tmp_path / "res"
    assert main(["analyze", str(session), "-o", str(out), "--min-track", "2", "--span", "1", "--quiet"]) == 0
    capsys.readouterr()
    with h5py.File(out / "results.h5", "r+") as f:  # as if the session had carried a calibration mapping
        f.attrs["coordinates"] = "rectified"
    assert main(["evaluate", str(out), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["tracking"] is None and result["strain"] is None and result["profile"] is None
    assert "rectified" in result["not_evaluated"]
    assert result["features"]["pore"]["recall"] > 0.5  # features stay in image pixels: still scored


def test_a_bundled_protocol_is_found_past_a_folder_of_its_name(tmp_path, monkeypatch):
    """``skinstretch demo -o demo`` then ``skinstretch record demo``: the folder is not the protocol."""
    from skinstretch.experiments.commands.record import protocol_path
    from skinstretch.experiments.protocol import bundled_protocol

    monkeypatch.chdir(tmp_path)
    (tmp_path / "demo").mkdir()
    assert protocol_path("demo") == bundled_protocol("demo")
    (tmp_path / "mine.yaml").write_text("x")
    assert protocol_path("mine.yaml") == tmp_path.joinpath("mine.yaml").relative_to(tmp_path)

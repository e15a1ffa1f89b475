"""Protocol and rig YAML: the bundled files load, and every error names the file, line and field."""

import pytest

from skinstretch.experiments.protocol import Rig, bundled_protocol, load_protocol, load_rig, parse_protocol, parse_rig
from skinstretch.processing.errors import ConfigError

GOOD = """\
name: p1
subject: {id: s01}
trials:
  - name: flat
    duration_s: 1.0
    repetitions: 2
  - name: ridge
    duration_s: 0.5
    surface: {kind: ridge}
"""


def test_bundled_demo_protocol_loads_with_three_surfaces():
    p = load_protocol(bundled_protocol("demo"))
    plan = p.planned_trials()
    assert [t.surface.kind for t in plan] == ["flat", "ridge", "valley"]
    assert [t.surface.scene_name for t in plan] == ["flatL", "ridgeL", "valleyL"]
    assert p.movie is not None and p.movie.closed_loop


def test_planned_trials_expand_repetitions_with_stable_names():
    p = parse_protocol(GOOD)
    assert [t.dirname for t in p.planned_trials()] == ["000-flat-r1", "001-flat-r2", "002-ridge-r1"]
    assert p.planned_trials()[2].surface.kind == "ridge"
    assert p.session_name == "p1"


@pytest.mark.parametrize(
    "text, line, field",
    [
        (GOOD.replace("duration_s: 0.5", "duration_s: -2"), 8, "trials[1].duration_s"),
        (GOOD.replace("repetitions: 2", "repetitons: 2"), 6, "trials[0].repetitons"),
        (GOOD.replace("{kind: ridge}", "{kind: bump}"), 9, "trials[1].surface.kind"),
        (GOOD + "camera_mode: quarter\n", 10, "camera_mode"),
        (GOOD.replace("subject: {id: s01}\n", ""), 1, "subject"),
    ],
)
def test_errors_name_file_line_and_field(text, line, field):
    with pytest.raises(ConfigError) as err:
        parse_protocol(text, source="lab.yaml")
    assert f"lab.yaml:{line}: {field}:" in str(err.value)


def test_yaml_syntax_error_names_line(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\ntrials: [\n  {name: a\n")
    with pytest.raises(ConfigError, match=r"bad.yaml:\d+: not valid YAML"):
        load_protocol(path)


def test_missing_and_empty_files_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="no such protocol"):
        load_protocol(tmp_path / "nope.yaml")
    (tmp_path / "empty.yaml").write_text("")
    with pytest.raises(ConfigError, match="empty"):
        load_protocol(tmp_path / "empty.yaml")


def test_rig_defaults_to_everything_simulated():
    rig = load_rig(None)
    assert rig == Rig() and rig.all_simulated
    assert (rig.camera.kind, rig.force.kind, rig.display.kind) == ("sim", "sim", "sim")


def test_rig_errors_name_line():
    with pytest.raises(ConfigError, match=r"rig.yaml:1: .*camera.kind aravis needs camera.device"):
        parse_rig("camera: {kind: aravis}\n", source="rig.yaml")
    with pytest.raises(ConfigError, match=r"rig.yaml:2: display.rate: Extra inputs"):
        parse_rig("name: lab\ndisplay: {kind: sim, rate: 3}\n", source="rig.yaml")


def test_bundled_rigs_load():
    from pathlib import Path

    import skinstretch.experiments.protocol as mod

    folder = Path(mod.__file__).with_name("protocols")
    assert load_rig(folder / "rig-sim.yaml").all_simulated
    lab = load_rig(folder / "rig-lab.yaml")
    assert lab.camera.kind == "aravis" and not lab.all_simulated

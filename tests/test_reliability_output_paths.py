"""Every output-path problem is one line naming the path and what is wrong, found before any device is opened:
read-only file system, no permission, a file where a directory is expected, an output that exists already."""

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from skinstretch.experiments.output_paths import OutputPathError, check_output_dir, check_output_file, os_error_line
from skinstretch.processing.errors import Remedy

CLI = [sys.executable, "-m", "skinstretch.cli"]
PROTOCOL = """\
name: paths
subject: {id: s01}
camera_mode: strip
trials:
  - {name: a, duration_s: 0.1}
analysis: {enabled: false}
"""


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=120)


def _one_line(done: subprocess.CompletedProcess, *needles: str) -> None:
    assert done.returncode == 2, (done.returncode, done.stdout, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


@pytest.fixture
def unwritable(tmp_path):
    """A directory this process cannot write into: immutable (chattr +i, which binds root too) or mode 555."""
    d = tmp_path / "locked"
    d.mkdir()
    if os.geteuid() == 0:
        if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(d)], capture_output=True).returncode:
            pytest.skip("root ignores permission bits and chattr +i is not available here")
        try:
            yield d
        finally:
            subprocess.run(["chattr", "-i", str(d)], check=False)
    else:
        d.chmod(0o555)
        try:
            yield d
        finally:
            d.chmod(0o755)


@pytest.fixture
def read_only_fs(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("mounting a read-only file system needs root")
    mnt = tmp_path / "ro"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_the_checks_name_the_path_and_the_problem(tmp_path, unwritable):
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = [
        (lambda: check_output_dir(afile), f"{afile}: is a file, not a directory"),
        (lambda: check_output_dir(afile / "sub" / "dir"), f"{afile}: is a file, not a directory (on the way to"),
        (lambda: check_output_file(afile), f"{afile}: exists already"),
        (lambda: check_output_file(tmp_path), f"{tmp_path}: is a directory, not a file"),
        (lambda: check_output_dir(unwritable / "data"), f"{unwritable / 'data'}: no permission to write there"),
        (lambda: check_output_file(unwritable / "x.h5"), f"{unwritable / 'x.h5'}: no permission to write there"),
    ]
    for call, message in cases:
        with pytest.raises(OutputPathError) as info:
            call()
        assert str(info.value).startswith(message) and "\n" not in str(info.value)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(OutputPathError, match="is not empty; pass resume=True to go on"):
        check_output_dir(tmp_path / "full", must_be_empty=True, remedy=Remedy(("resume",), "to go on", True))
    assert check_output_dir(tmp_path / "new" / "deeper") == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()  # checking creates nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "full", "locked"]
    assert os_error_line(OSError(30, "Read-only file system", "/x")) == "/x: is on a read-only file system"


def test_record_refuses_every_bad_output_in_one_line_before_recording(tmp_path, unwritable, read_only_fs):
    proto = tmp_path / "p.yaml"
    proto.write_text(PROTOCOL)
    afile = tmp_path / "afile"
    afile.write_text("x")
    _one_line(_cli("record", str(proto), "-o", str(read_only_fs / "data")), "read-only file system",
              str(read_only_fs / "data" / "s01" / "paths"))
    _one_line(_cli("record", str(proto), "-o", str(unwritable)), "no permission", str(unwritable / "s01"))
    _one_line(_cli("record", str(proto), "-o", str(afile)), f"{afile}: is a file, not a directory")
    assert list(unwritable.iterdir()) == [] and list(read_only_fs.iterdir()) == []
    done = _cli("record", str(proto), "-o", str(tmp_path / "d"), "--no-movie")
    assert done.returncode == 0 and done.stdout.strip().splitlines()[-1] == "record: all 1 trials recorded"
    _one_line(_cli("record", str(proto), "-o", str(tmp_path / "d")), "is not empty", "--resume")


def test_play_checks_its_output_before_the_first_frame(tmp_path, unwritable):
    movie = tmp_path / "m.npy"
    np.save(movie, np.zeros((50, 10, 10)))
    existing = tmp_path / "done.h5"
    existing.write_bytes(b"a recording")
    _one_line(_cli("play", str(movie), "-o", str(existing)), f"{existing}: exists already")
    _one_line(_cli("play", str(movie), "--compare", "-o", str(unwritable / "p.h5")), "no permission",
              str(unwritable / "p-open.h5"))
    assert existing.read_bytes() == b"a recording"


def test_play_movie_refuses_an_existing_recording_before_the_display_moves(tmp_path):
    from skinstretch.drivers.display.stress import StressDisplay
    from skinstretch.drivers.display.transports import SerialTransport
    from skinstretch.experiments.playback import play_movie
    from skinstretch.simulators import stress_links

    stress_links.register_url_handler()
    link = stress_links.make_link(seed=0)
    display = StressDisplay(SerialTransport(stress_links.attach("paths", link)))
    existing = tmp_path / "p.h5"
    existing.write_bytes(b"x")
    try:
        with pytest.raises(OutputPathError, match="exists already"):
            play_movie(display, np.zeros((20, 10, 10)), path=existing)
        assert not display.armed and link.firmware.frames_received == 0
    finally:
        display.close()
        stress_links.detach("paths")


def test_fault_drills_from_the_command_line_and_finite_numbers_only(tmp_path):
    """play takes the twin's URL with its fault switches; NaN options and protocol values are named as such."""
    movie = tmp_path / "m.npy"
    np.save(movie, 20.0 * np.sin(np.arange(1400) / 70.0)[:, None, None] * np.ones((1, 10, 10)))
    out = tmp_path / "drill.h5"
    done = _cli("play", str(movie), "--movie-rate", "700", "--no-force", "-o", str(out),
                "--display", "stresssim://drill?faults=vanish_after:300&seed=1")
    assert done.returncode == 3 and "display link failed" in done.stdout, (done.stdout, done.stderr)
    from skinstretch.drivers.session_file import open_session

    with open_session(out) as s:
        assert s.status == "failed" and 0 < s.read_stream("display_target")[0].shape[0] < 1400
    bad = _cli("play", str(movie), "--gain", "nan")
    assert bad.returncode == 2 and "'nan' is not a finite number" in bad.stderr
    proto = tmp_path / "nan.yaml"
    proto.write_text("name: x\nsubject: {id: s}\ntrials:\n  - {name: a, duration_s: .nan}\n")
    _one_line(_cli("record", str(proto), "-o", str(tmp_path / "d")), "nan.yaml:4: trials[0].duration_s",
              "finite number")


@pytest.mark.parametrize("flag, value, says", [
    ("--rate", "0", "greater than or equal to 1"), ("--rate", "701", "less than or equal to 700"),
    ("--movie-rate", "0", "greater than 0"), ("--gain", "-1", "greater than 0"), ("--gain", "0", "greater than 0"),
    ("--peak-um", "-3", "greater than 0"), ("--force-ceiling", "0", "greater than 0"),
    ("--force-ceiling", "1000", "less than or equal to 50"), ("--gain", "inf", "not a finite number"),
])
def test_play_refuses_a_nonsensical_option_in_one_line_naming_it(tmp_path, capsys, flag, value, says):
    from skinstretch.cli import main

    movie = tmp_path / "m.npy"
    np.save(movie, np.zeros((50, 10, 10)))
    with pytest.raises(SystemExit) as info:
        main(["play", str(movie), flag, value])
    assert info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and f"argument {flag}: " in lines[0] and says in lines[0] and value in lines[0], lines


def test_a_protocol_movie_has_the_play_commands_limits():
    from skinstretch.experiments.protocol import parse_protocol
    from skinstretch.processing.errors import ConfigError

    base = "name: x\nsubject: {id: s}\ntrials:\n  - {name: a, duration_s: 1}\nmovie: {%s}\n"
    for bad in ("rate_hz: 800", "force_ceiling_n: 60", "gain: -1"):
        with pytest.raises(ConfigError, match=bad.split(":")[0]):
            parse_protocol(base % bad)
    assert parse_protocol(base % "rate_hz: 700").movie.rate_hz == 700


def test_simulate_checks_its_output_before_rendering(tmp_path, capsys, monkeypatch, unwritable):
    from skinstretch.cli import main
    from skinstretch.simulators import scene

    def never(*args, **kwargs):
        raise AssertionError("rendered although the output cannot be written")

    monkeypatch.setattr(scene, "simulate_to_file", never)
    existing = tmp_path / "s.h5"
    existing.write_bytes(b"a session")
    for target, says in ((existing, f"{existing}: exists already; pass --overwrite to replace it"),
                         (unwritable / "s.h5", f"{unwritable / 's.h5'}: no permission to write there"),
                         (existing / "s.h5", f"{existing}: is a file, not a directory")):
        assert main(["simulate", "flatL", "-o", str(target), "--frames", "2"]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and says in lines[0], lines
    assert existing.read_bytes() == b"a session" and list(unwritable.iterdir()) == []

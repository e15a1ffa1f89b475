"""Errors name what the caller can change: Python keywords in Python, flags on the command line (issue 17)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from skinstretch.cli import main
from skinstretch.processing.errors import InvalidInputError, Remedy


def test_a_remedy_is_spelled_for_each_caller():
    exc = InvalidInputError("out.h5 exists", remedy=Remedy(("overwrite",), "to replace it", True))
    assert str(exc) == "out.h5 exists; pass overwrite=True to replace it"
    flags = {"overwrite": "--overwrite", "px_per_mm": "--px-per-mm"}
    assert exc.message_for(lambda p: flags.get(p, p)) == "out.h5 exists; pass --overwrite to replace it"
    either = InvalidInputError("no scale", remedy=Remedy(("px_per_mm", "calibration"), "to give it"))
    assert str(either) == "no scale; pass px_per_mm=... or calibration=... to give it"
    assert either.message_for(lambda p: flags.get(p, p)) == "no scale; pass --px-per-mm or calibration=... to give it"
    assert pickle.loads(pickle.dumps(either)).remedy == either.remedy  # survives a worker process


def test_a_message_opening_with_a_parameter_opens_with_its_flag():
    flags = {"px_per_mm": "--px-per-mm"}
    name = lambda p: flags.get(p, p)  # noqa: E731
    assert InvalidInputError("px_per_mm must be positive, got 0").message_for(name) == "--px-per-mm must be positive, got 0"
    assert InvalidInputError("px_per_mmx must be positive").message_for(name) == "px_per_mmx must be positive"
    assert InvalidInputError("the px_per_mm must be").message_for(name) == "the px_per_mm must be"


@pytest.mark.parametrize("args,flag", [
    (["simulate", "flatL", "--frames", "2", "--workers", "0"], "--workers must be a positive integer"),
    (["simulate", "flatL", "--frames", "2", "--noise", "-1"], "--noise must be a non-negative number"),
    (["simulate", "flatL", "--frames", "2", "--texture", "afis_p1_2", "--dpi", "50"], "--dpi must be between 100"),
    (["calibrate", "grid.png", "--spacing-mm", "0"], "--spacing-mm must be positive"),
    (["analyze", "s.h5", "--workers", "0"], "--workers: Input should be greater than or equal to 1"),
    (["analyze", "s.h5", "--method", "flow", "--flow-scale", "-1"], "--flow-scale: Input should be greater than 0"),
    (["analyze", "s.h5", "--method", "flow", "--flow-scale-px", "8"], "--flow-scale-px: Value error, must be odd"),
    (["import", "clip.avi", "--px-per-mm", "62", "--crop", "600,0,100,100"], "--crop must lie inside the 32x24 frames"),
])
def test_commands_name_their_flags(tmp_path, capsys, args, flag):
    if args[0] == "import":
        from skinstretch.experiments.bench.import_video import write_video

        write_video(tmp_path / "clip.avi", np.zeros((3, 24, 32), np.uint8))
    args = [str(tmp_path / a) if a in ("s.h5", "clip.avi") else a for a in args]
    assert main([*args, "-o", str(tmp_path / "out"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and flag in err[0], err


@pytest.mark.parametrize("error,line", [
    (PermissionError(13, "Permission denied", "/data/s01/x.h5"), "/data/s01/x.h5: no permission to write there"),
    (OSError(28, "No space left on device"), "No space left on device"),
])
def test_an_os_error_nothing_caught_is_one_line_with_status_1(monkeypatch, capsys, error, line):
    import skinstretch.experiments.commands.analyze as analyze_command

    def refused(args):
        raise error

    monkeypatch.setattr(analyze_command, "run", refused)
    assert main(["analyze", "s.h5", "-o", "out", "-q"]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [f"skinstretch analyze: error: {line}"]


def test_logging_follows_the_current_standard_error(monkeypatch):
    """The CLI's log handler writes to sys.stderr as it is at each record, not to the stream it was set up with
    (a test capture that is closed afterwards used to make every later record print "Logging error")."""
    import io
    import logging

    from skinstretch.cli import configure_logging

    first, second = io.StringIO(), io.StringIO()
    monkeypatch.setattr("sys.stderr", first)
    configure_logging()
    first.close()
    monkeypatch.setattr("sys.stderr", second)
    logging.getLogger("skinstretch.test").warning("after the first stream closed")
    assert second.getvalue() == "after the first stream closed\n"

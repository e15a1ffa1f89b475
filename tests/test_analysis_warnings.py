"""The warning lines of an analysis' summary (experiments/analysis/pipeline.py ``_warnings``): displacements whose
windows do not match after their measured motion (no error bound) are warned about beyond a small fraction."""

from types import SimpleNamespace

from skinstretch.experiments.analysis.pipeline import MAX_UNBOUNDED_FRACTION, _warnings


class _NoDoubts:
    def describe(self, done, what):
        return None


def _lines(unbounded_fraction):
    motion = SimpleNamespace(doubted=_NoDoubts(), written=10)
    strain = SimpleNamespace(doubted={1: _NoDoubts()}, done={1: 10}, buffers={1: None})
    uncertainty = {"displacement_sigma_px": {"median": 0.02, "p95": 0.03, "unbounded": 1,
                                             "unbounded_fraction": unbounded_fraction}}
    return _warnings(motion, strain, uncertainty, {"too_sparse": False})


def test_many_unbounded_displacements_are_warned_about():
    assert _lines(MAX_UNBOUNDED_FRACTION / 10) == []
    (line,) = _lines(0.3)
    assert line.startswith("30 % of the displacements do not match after their measured motion")

"""Shared test configuration: fixed seeds, non-interactive plotting."""

import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def sim_session():
    """A small simulated session (scene flatL, 20 frames, seed 0) as a skinstretch.simulators.scene.RenderedSession.

    Shared by the whole test run: treat it as read-only.
    """
    from skinstretch.simulators.scene import render_session

    return render_session("flatL", n_frames=20, seed=0)


@pytest.fixture(scope="session")
def analysed_study(tmp_path_factory, sim_session):
    """A data directory of two analysed trials of :func:`sim_session`: ``s01/study/000-flat-r1`` (features, surface
    flat) and ``s01/study/001-ridge-r1`` (flow, surface ridge, the newer). Read-only: copy it to change it."""
    from skinstretch.drivers.session_file import write_session
    from skinstretch.experiments.analysis import AnalysisParams, analyze_session
    from skinstretch.processing.tracking import TrackingParams

    root = tmp_path_factory.mktemp("study")
    s = sim_session
    for name, surface, method in (("000-flat-r1", "flat", "features"), ("001-ridge-r1", "ridge", "flow")):
        trial = root / "s01" / "study" / name
        trial.mkdir(parents=True)
        md = {**s.metadata, "trial": name, "subject": {"id": "s01"}, "protocol": "demo", "surface": {"kind": surface}}
        path = write_session(trial / "session.h5", s.frames, timestamps=s.timestamps, camera_mode=s.camera_mode,
                             calibration=s.calibration, metadata=md)
        params = AnalysisParams(execution={"kind": "threads"}, strain={"spans": (1, 5)},
                                tracking=TrackingParams(min_length_frames=10))
        analyze_session(path, trial / "analysis", method=method, params=params)
    return root

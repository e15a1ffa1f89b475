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

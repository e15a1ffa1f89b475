"""Helpers shared by several test modules (not tests themselves)."""

import time

import numpy as np

from skinstretch.processing.feature_table import make_features


def wait_until(predicate, timeout_s: float = 5.0, poll_s: float = 0.005) -> None:
    """Poll ``predicate`` until it holds: a bounded wait on another thread; AssertionError after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not reached within {timeout_s} s")
        time.sleep(poll_s)


def y_shaped_skeleton() -> np.ndarray:
    """A one-pixel skeleton (60x60 uint8) shaped like a Y lying on its side: a stem along +x from (5, 30) to
    (29, 30) and two diagonal arms to the upper and lower right, i.e. one bifurcation near (29, 30) and three
    endings."""
    sk = np.zeros((60, 60), np.uint8)
    sk[30, 5:30] = 1
    for i in range(1, 22):
        sk[30 - i, 29 + i] = 1
        sk[30 + i, 29 + i] = 1
    return sk


def sliding_feature_grid(k: int, rng_seed: int = 0) -> np.ndarray:
    """A grid of features sliding 1.5 px per frame; a few vanish for 2 frames (re-linked) or for good."""
    rng = np.random.default_rng(rng_seed)
    gx, gy = np.meshgrid(np.arange(20.0, 300.0, 23.0), np.arange(20.0, 200.0, 21.0))
    x, y = gx.ravel() + 1.5 * k, gy.ravel() + 0.4 * k
    kind = rng.integers(0, 3, x.size)
    keep = np.ones(x.size, bool)
    keep[(np.arange(x.size) % 7 == k % 7)] = False  # each feature missing one frame in 7
    keep[5:9] = k < 25  # some end for good
    return make_features(x[keep], y[keep], kind[keep], frame=k)

"""Glass-fixed shading removal: a band of partial contact no longer pulls the measured motion towards zero."""

import cv2
import numpy as np
import pytest

from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.glass_shading import glass_shading, remove_glass_shading

H, W, N, STEP = 200, 160, 80, 0.5


def _frames():
    """A random texture sliding down STEP px per frame, seen through a glass-fixed band of lower gain and
    higher offset (a valley where the skin only partly touches)."""
    rng = np.random.default_rng(0)
    big = cv2.GaussianBlur(rng.normal(size=(H + 2 * N + 20, W)).astype(np.float32), (0, 0), 3)
    big /= big.std()
    y = np.arange(H, dtype=np.float32)[:, None]
    band = np.exp(-0.5 * ((y - 100) / 15) ** 2)
    gain, offset = 1 - 0.7 * band, 40 * band
    map_x = np.tile(np.arange(W, dtype=np.float32), (H, 1))
    out = []
    for k in range(N):
        map_y = np.repeat(y - STEP * k + 2 * N, W, axis=1).astype(np.float32)
        t = cv2.remap(big, map_x, map_y, cv2.INTER_CUBIC)
        out.append(np.clip(120 + offset + 40 * gain * t, 0, 255).round().astype(np.uint8))
    return out


def _shift(a, b, rows):
    """Least-squares vertical shift between two frames over some rows (gradient-based, as a flow would)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    gy = np.gradient((a + b) / 2, axis=0)[rows]
    return -np.sum(gy * (b - a)[rows]) / np.sum(gy * gy)


@pytest.mark.parametrize("smooth_px", [1.5, (8.0, 1.5)])
def test_removing_the_glass_shading_removes_the_motion_deficit_in_the_band(smooth_px):
    frames = _frames()
    g = glass_shading(frames, smooth_px=smooth_px)
    band, clear = np.s_[80:120], np.s_[10:50]
    fixed = [remove_glass_shading(f, g) for f in frames]

    def deficit(seq):
        pairs = range(10, 70)
        return np.mean([_shift(seq[k], seq[k + 1], clear) - _shift(seq[k], seq[k + 1], band) for k in pairs])

    assert deficit(frames) > 0.03  # the band reads ~10 % less motion than the clear rows
    assert abs(deficit(fixed)) < 0.01
    c = np.stack(fixed).astype(np.float64)
    assert c[:, 90:110].std() == pytest.approx(c[:, 10:40].std(), rel=0.1)  # same contrast in and out of the band


def test_a_still_finger_is_refused_and_bad_input_is_named():
    still = [_frames()[0]] * 20
    with pytest.raises(InsufficientDataError, match="moved too little"):
        glass_shading(still)
    with pytest.raises(InsufficientDataError):
        glass_shading(still[:1])
    with pytest.raises(InvalidInputError, match="uint8"):
        glass_shading([np.zeros((8, 8), np.float32)] * 3)
    with pytest.raises(InvalidInputError, match="smooth_px"):
        glass_shading(still, smooth_px=0)
    with pytest.raises(InvalidInputError, match="smooth_px"):
        glass_shading(still, smooth_px=(3.0, -1.0))
    g = glass_shading(_frames())
    with pytest.raises(InvalidInputError, match="shape"):
        remove_glass_shading(np.zeros((4, 4), np.uint8), g)


def test_statistics_of_an_array_a_list_and_a_chosen_subset_agree():
    """The compiled sums are exact: an (N, H, W) array, a list (stacked 64 frames at a time) and ``use`` give the
    statistics of the frames chosen, bit for bit."""
    frames = _frames()
    use = [k for k in range(N) if k % 5]  # e.g. without all-black frames
    a = glass_shading(np.stack(frames), use=use)
    b = glass_shading(frames, use=use)
    c = glass_shading([frames[k] for k in use])
    for g in (b, c):
        np.testing.assert_array_equal(g.offset, a.offset)
        np.testing.assert_array_equal(g.gain, a.gain)
    chosen = np.stack([frames[k] for k in use]).astype(np.float64)
    mean = cv2.GaussianBlur(chosen.mean(axis=0).astype(np.float32), (0, 0), 1.5)
    np.testing.assert_allclose(a.offset, mean, atol=1e-4)
    with pytest.raises(InvalidInputError, match="use holds"):
        glass_shading(frames, use=[0, N])
    with pytest.raises(InsufficientDataError, match="at least 2"):
        glass_shading(frames, use=[3])


@pytest.mark.parametrize("transpose", [False, True])
def test_the_shape_axis_is_found_when_the_print_ridges_run_along_the_slide(transpose):
    """Ridges that run along the slide stay where they are while the skin moves: a clip's mean keeps them, and
    their ghost varies across the image more steeply than the shape's band (the gradients of the mean, blurred,
    took the ridges' direction for the shape's). The band is still found on its axis, whichever image axis that
    is, so the maps are smoothed along it: the band's profile kept, the ridges gone."""
    rng = np.random.default_rng(1)
    n, size = 40, 240
    y = np.arange(size, dtype=np.float32)[:, None]
    x = np.arange(size, dtype=np.float32)[None, :]
    band = 30 * np.exp(-0.5 * ((y - 120) / 40) ** 2) * np.ones((1, size), np.float32)
    ridges = 30 * np.sin(2 * np.pi * (x / 60 + ((y - 120) / 100) ** 2))  # curving gently, mostly along y
    moving = cv2.GaussianBlur(rng.normal(size=(size + 2 * n, size)).astype(np.float32), (0, 0), 2)
    moving *= 12 / moving.std()
    frames = []
    for k in range(n):
        f = 110 + band + ridges + moving[2 * n - 2 * k: 2 * n - 2 * k + size]
        f = np.clip(f, 0, 255).round().astype(np.uint8)
        frames.append(np.ascontiguousarray(f.T) if transpose else f)
    g = glass_shading(frames, smooth_px=1.5, along_shape_px=60.0, min_motion_ratio=0.0)
    offset = g.offset.T if transpose else g.offset
    inner = offset[20:-20, 60:-60]
    profile = inner.mean(axis=1)
    expected = band[20:-20, 0] - band[20:-20, 0].mean() + profile.mean()
    assert np.abs(profile - expected).max() < 3.0  # the band kept (30 grey levels high)
    assert np.abs(inner - profile[:, None]).max() < 3.0  # the ridges (+-30) smoothed away along the band

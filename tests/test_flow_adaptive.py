"""Adaptive regularization and direct span registration of the dense flow."""

import cv2
import numpy as np
import pytest
from scipy import ndimage as ndi

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.flow import DenseFlow, FlowParams, compose_fields
from skinstretch.processing.pixel_scale import Calibration

CAL = Calibration(px_per_mm=62.0)


def _speckle(shape=(200, 260), seed=0):
    rng = np.random.default_rng(seed)
    a = cv2.GaussianBlur((rng.random((shape[0] * 4, shape[1] * 4)) * 255).astype(np.float32), (0, 0), 6.0)
    return cv2.normalize(a, None, 20, 235, cv2.NORM_MINMAX)  # 4x oversampled master


def _warped(master, v_of_y, seed):
    """A frame (1/4 of the master's resolution) whose content moved down by v(y) px (a field varying along y),
    plus noise of 1.5 grey levels."""
    h, w = master.shape[0] // 4, master.shape[1] // 4
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rows = y.copy()
    for _ in range(30):  # the point now at y came from Y with Y + v(Y) = y
        rows = y - v_of_y(rows)
    img = ndi.map_coordinates(master, [rows * 4 + 1.5, x * 4 + 1.5], order=3, mode="mirror")
    img = img + np.random.default_rng(seed).normal(0, 1.5, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _bump(amplitude, centre=100.0, sigma=12.0):
    return lambda y: amplitude * np.exp(-0.5 * ((y - centre) / sigma) ** 2)


def test_adaptive_regularization_resolves_a_narrow_bump_and_leaves_a_translation_alone():
    master = _speckle()
    a = _warped(master, lambda y: 0.0 * y, 1)
    b = _warped(master, _bump(0.6), 2)
    errors = {}
    for adaptive in (False, True):
        f = DenseFlow(calibration=CAL, params=FlowParams(window_px=31, adaptive=adaptive, texture_gate=False)).compute(a, b)
        m = f.motion()
        true_v = _bump(0.6)(m.points[:, 1])
        near = np.abs(m.points[:, 1] - 100) < 15
        errors[adaptive] = np.sqrt(np.mean((m.displacement[near, 1] - true_v[near]) ** 2))
    assert errors[True] < 0.5 * errors[False]
    # A uniform shift asks for no detail: the adaptive field is the smooth one, bit for bit.
    c = _warped(master, lambda y: 0.0 * y + 0.7, 3)
    smooth = DenseFlow(calibration=CAL, params=FlowParams(window_px=31, adaptive=False, texture_gate=False)).compute(a, c)
    adaptive = DenseFlow(calibration=CAL, params=FlowParams(window_px=31, texture_gate=False)).compute(a, c)
    np.testing.assert_array_equal(smooth.displacement, adaptive.displacement)


def test_compose_fields_follows_the_skin_points():
    master = _speckle()
    frames = [_warped(master, lambda y, s=s: 0.0 * y + 1.0 * s, 10 + s) for s in range(4)]  # whole px: no warp bias
    flow = DenseFlow(calibration=CAL, params=FlowParams(window_px=31, texture_gate=False))
    fields = flow.compute_sequence(frames, threads=1)
    composed = compose_fields(fields)
    assert (composed.frame_a, composed.frame_b) == (0, 3)
    d = composed.displacement[composed.valid]
    np.testing.assert_allclose(np.median(d, axis=0), [0.0, 3.0], atol=0.02)
    assert np.array_equal(np.isnan(composed.displacement[..., 0]), ~composed.valid)
    assert not composed.valid[-1].any()  # bottom nodes move out of the last grid: lost, not extrapolated
    with pytest.raises(InvalidInputError):
        compose_fields([])


def test_compute_spans_registers_the_span_directly():
    master = _speckle()
    # A steady slide of 1 px per frame: the direct span is at least as accurate as the composition of the steps and
    # keeps the nodes the composition loses (points next to an invalid node or beyond a grid on the way).
    frames = [_warped(master, lambda y, k=k: 0.0 * y + 1.0 * k, 30 + k) for k in range(8)]
    flow = DenseFlow(calibration=CAL, params=FlowParams(window_px=21, texture_gate=False))
    fields = flow.compute_sequence(frames, threads=1)
    spans = flow.compute_spans(frames, fields, span=7, threads=2)
    assert len(spans) == 1 and (spans[0].frame_a, spans[0].frame_b) == (0, 7)
    assert flow.compute_spans(frames, fields, span=1) == fields
    assert [(f.frame_a, f.frame_b) for f in flow.compute_spans(frames, fields, span=3)] == [(k, k + 3) for k in range(5)]

    def err(field):
        d = field.displacement[field.valid]
        return np.sqrt(np.mean((d - [0.0, 7.0]) ** 2))

    composed = compose_fields(fields)
    assert err(spans[0]) <= err(composed) and spans[0].valid.sum() > composed.valid.sum()
    (plain,) = flow.compute_spans(frames, fields, span=7, refine=False)  # the composition, as over a ridge
    np.testing.assert_array_equal(plain.displacement, composed.displacement)
    with pytest.raises(InvalidInputError, match="consecutive fields"):
        flow.compute_spans(frames, fields[:-1], span=2)

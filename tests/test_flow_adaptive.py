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
    # A slide has nothing but noise off the affine: the span's weaker membrane (flow._SPAN_SMOOTHNESS) lets a
    # little more of it through than the composition's steps, each under a pair's membrane.
    assert err(spans[0]) <= err(composed) + 0.005 and spans[0].valid.sum() > composed.valid.sum()
    (plain,) = flow.compute_spans(frames, fields, span=7, refine=False)  # the composition, as over a ridge
    np.testing.assert_array_equal(plain.displacement, composed.displacement)
    with pytest.raises(InvalidInputError, match="consecutive fields"):
        flow.compute_spans(frames, fields[:-1], span=2)


def test_a_span_with_motion_off_the_affine_is_registered_under_a_weaker_membrane(monkeypatch):
    import skinstretch.processing.flow as flow_module

    # A bump growing by 0.15 px a frame (1.05 px over the span): the membrane's pull towards the affine prior
    # flattens it in proportion to its size, ten times a pair's over an 11-frame span, while the noise is a pair's.
    master = _speckle()
    frames = [_warped(master, _bump(0.15 * k, sigma=18.0), 50 + k) for k in range(8)]
    flow = DenseFlow(calibration=CAL, params=FlowParams(window_px=31, texture_gate=False))
    fields = flow.compute_sequence(frames, threads=1)

    def err(field):
        m = field.motion()
        return np.sqrt(np.mean((m.displacement[:, 1] - _bump(1.05, sigma=18.0)(m.points[:, 1])) ** 2))

    (weak,) = flow.compute_spans(frames, fields, span=7, threads=1)
    monkeypatch.setattr(flow_module, "_SPAN_SMOOTHNESS", 1.0)
    (pair_like,) = flow.compute_spans(frames, fields, span=7, threads=1)
    assert err(weak) < 0.8 * err(pair_like)  # 0.020 against 0.029 px (the composition: 0.082 px)


def test_a_pair_under_the_local_prior_follows_a_smoothly_curved_field_the_affine_prior_flattens():
    # A field curving over the whole image (0.2 px in the middle, 1.4 px at the top and bottom rows), as a
    # fingertip's sides lag while it turns: the membrane tied to the affine pulls the curve towards a line, tied to
    # the affine plus the field's own smoothed deviation it smooths the noise only.
    master = _speckle()

    def v(y):
        return 0.2 + 1.2 * ((y - 100.0) / 100.0) ** 2

    a, b = _warped(master, lambda y: 0.0 * y, 1), _warped(master, v, 11)

    def err(local_prior):
        f = DenseFlow(calibration=CAL, params=FlowParams(window_px=31, texture_gate=False,
                                                         local_prior=local_prior)).compute(a, b)
        m = f.motion()
        assert m.points.shape[0] > 100
        return np.sqrt(np.mean((m.displacement[:, 1] - v(m.points[:, 1])) ** 2))

    assert err(True) < 0.85 * err(False)  # 0.027 against 0.035 px


def test_sor_tensor_reaches_the_minimum_of_the_anisotropic_energy_and_edge_weights_give_the_tensor_energy():
    from skinstretch.processing.flow_kernels import membrane_edge_weights, sor_tensor

    rng = np.random.default_rng(4)
    gy_n, gx_n = 6, 7
    g = rng.uniform(1.0, 3.0, (3, gy_n, gx_n))
    gxx, gyy, gxy = g[0], g[1], 0.3 * (g[2] - 2.0)
    rx, ry = rng.normal(size=(2, gy_n, gx_n))
    prior = 0.1 * rng.normal(size=(gy_n, gx_n, 2))
    contact = np.ones((gy_n, gx_n), bool)
    contact[0, 0] = contact[3, 4] = False
    weights = [rng.uniform(0.0, 2.0, (gy_n, gx_n)) for _ in range(4)]  # wx, wy, wd1, wd2
    u0 = np.zeros((gy_n, gx_n, 2))
    u = sor_tensor(u0, prior, gxx, gxy, gyy, rx, ry, contact, *weights, 3000, 1.5)
    # The minimum of sum_nodes (u^T G u - 2 r^T u) + sum_edges w (deviation_i - deviation_j)^2 (deviation = u -
    # prior), assembled and solved directly over the contact nodes.
    idx = -np.ones((gy_n, gx_n), int)
    idx[contact] = np.arange(contact.sum())
    n = int(contact.sum())
    a = np.zeros((2 * n, 2 * n))
    rhs = np.zeros(2 * n)
    for i, j in zip(*np.nonzero(contact)):
        p = idx[i, j]
        a[2 * p : 2 * p + 2, 2 * p : 2 * p + 2] += [[gxx[i, j], gxy[i, j]], [gxy[i, j], gyy[i, j]]]
        rhs[2 * p : 2 * p + 2] += [rx[i, j], ry[i, j]]
        for (di, dj), w in zip(((0, 1), (1, 0), (1, 1), (1, -1)), weights):
            ii, jj = i + di, j + dj
            if 0 <= ii < gy_n and 0 <= jj < gx_n and contact[ii, jj]:
                q, we = idx[ii, jj], 0.5 * (w[i, j] + w[ii, jj])
                for c in range(2):
                    a[2 * p + c, 2 * p + c] += we
                    a[2 * q + c, 2 * q + c] += we
                    a[2 * p + c, 2 * q + c] -= we
                    a[2 * q + c, 2 * p + c] -= we
                    d = prior[i, j, c] - prior[ii, jj, c]
                    rhs[2 * p + c] += we * d
                    rhs[2 * q + c] -= we * d
    exact = np.linalg.solve(a, rhs).reshape(n, 2)
    np.testing.assert_allclose(u[contact], exact, atol=1e-9)
    np.testing.assert_array_equal(u[~contact], u0[~contact])
    # The stencil's energy of a linear field is grad^T D grad, for any tensor with |Dxy| <= min(Dxx, Dyy).
    dxx, dxy, dyy = 2.0, -0.7, 1.1
    wx, wy, wd1, wd2 = (float(w) for w in membrane_edge_weights(np.array(dxx), np.array(dxy), np.array(dyy)))
    gx_, gy_ = 0.3, -0.8  # u = gx_ x + gy_ y: differences along x, y and the two diagonals
    energy = wx * gx_**2 + wy * gy_**2 + wd1 * (gx_ + gy_) ** 2 + wd2 * (gx_ - gy_) ** 2
    assert energy == pytest.approx(dxx * gx_**2 + 2 * dxy * gx_ * gy_ + dyy * gy_**2)


def test_adaptive_regularization_smooths_along_a_band_not_across_it(monkeypatch):
    """A band of motion along x (a slip front's shape): the adaptive field keeps the membrane along the band (less
    noise along x than weakening it alike in every direction) and resolves the band as well."""
    from skinstretch.processing import flow as flow_module

    master = _speckle((200, 320))
    a = _warped(master, lambda y: 0.0 * y, 5)
    b = _warped(master, _bump(0.6, sigma=10.0), 6)
    params = FlowParams(window_px=31, texture_gate=False)
    anisotropic = DenseFlow(calibration=CAL, params=params).compute(a, b)
    aniso_fn = flow_module._anisotropic_membrane

    def isotropic(deviation, weight, lam):
        dxx, dxy, dyy = aniso_fn(deviation, weight, lam)
        across = lam * (1.0 - weight) + flow_module._SHARP * lam * weight
        return across, 0.0 * dxy, across

    monkeypatch.setattr(flow_module, "_anisotropic_membrane", isotropic)
    iso = DenseFlow(calibration=CAL, params=params).compute(a, b)

    def scores(f):
        m = f.motion()
        near = np.abs(m.points[:, 1] - 100) < 20
        err = np.sqrt(np.mean((m.displacement[near, 1] - _bump(0.6, sigma=10.0)(m.points[near, 1])) ** 2))
        rows = np.abs(f.grid_y - 100) < 20
        v = f.displacement[rows][:, 2:-2, 1]  # nodes near the band, away from the side borders
        along = np.nanmean(np.nanstd(v, axis=1))  # the true v is constant along x
        return err, along

    err_a, along_a = scores(anisotropic)
    err_i, along_i = scores(iso)
    assert along_a < 0.8 * along_i and err_a < 1.05 * err_i  # seed 0: 0.012 vs 0.017 px; 0.064 vs 0.066 px

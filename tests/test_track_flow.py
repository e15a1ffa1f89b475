"""The dense method (skinstretch.processing.flow) on exact synthetic fingerprints."""

import numpy as np
import pytest

from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.flow import DenseFlow, FlowParams
from skinstretch.processing.flow_fields import grid_strain, sample_dense_flow
from skinstretch.processing.stretch import triangulation_strain
from tests.test_track_support import affine_field, render

CAL = Calibration(px_per_mm=62.0)
SHAPE = (240, 320)


@pytest.fixture(scope="module")
def strained_pair():
    f0 = render(affine_field(0, 0), shape=SHAPE, noise=2.0)
    field = affine_field(3.4, -1.2, exx=0.01, eyy=-0.005)
    f1 = render(field, shape=SHAPE, noise=2.0, rng=np.random.default_rng(3))
    return f0, f1, field


def test_flow_measures_displacement_and_strain(strained_pair):
    f0, f1, field = strained_pair
    flow = DenseFlow(calibration=CAL).compute(f0, f1, frame_a=4, frame_b=5)
    assert flow.status == "ok" and (flow.frame_a, flow.frame_b) == (4, 5)
    assert flow.valid.mean() > 0.8
    X, Y = np.meshgrid(flow.grid_x, flow.grid_y)
    u, v = field(X, Y)
    err = np.hypot(flow.displacement[..., 0] - u, flow.displacement[..., 1] - v)[flow.valid]
    assert np.sqrt(np.mean(err**2)) < 0.1
    assert np.all(np.isnan(flow.displacement[~flow.valid]))
    strain, ok = grid_strain(flow)
    assert np.median(strain[ok][:, 0]) == pytest.approx(0.01, abs=0.002)
    assert np.median(strain[ok][:, 1]) == pytest.approx(-0.005, abs=0.002)
    tri = triangulation_strain(flow.motion(stride=3))
    assert np.median(tri.area_change) == pytest.approx(1.01 * 0.995 - 1, abs=0.003)
    pts = np.array([[160.0, 120.0], [100.0, 80.0]])
    d, dok = flow.sample(pts)
    assert dok.all() and np.abs(d - np.column_stack(field(pts[:, 0], pts[:, 1]))).max() < 0.1


@pytest.mark.parametrize("shift, exx, eyy", [((0.3, 0.2), -0.02, 0.01), ((6.5, 8.2), 0.02, 0.0)])
def test_flow_measures_strong_uniform_strain(shift, exx, eyy):
    """2 % strain: the affine part along the ridges, which the windows barely see, must converge too."""
    f0 = render(affine_field(0, 0), shape=SHAPE, noise=2.0)
    field = affine_field(*shift, exx=exx, eyy=eyy)
    f1 = render(field, shape=SHAPE, noise=2.0, rng=np.random.default_rng(3))
    flow = DenseFlow(calibration=CAL).compute(f0, f1)
    X, Y = np.meshgrid(flow.grid_x, flow.grid_y)
    u, v = field(X, Y)
    err = np.hypot(flow.displacement[..., 0] - u, flow.displacement[..., 1] - v)[flow.valid]
    assert flow.valid.mean() > 0.8 and np.sqrt(np.mean(err**2)) < 0.06
    strain, ok = grid_strain(flow)
    assert np.median(strain[ok][:, 0]) == pytest.approx(exx, abs=0.001)
    assert np.median(strain[ok][:, 1]) == pytest.approx(eyy, abs=0.001)


def test_no_contact_and_partial_contact_are_flagged(strained_pair):
    f0, f1, _ = strained_pair
    flat = np.full(SHAPE, 230, np.uint8)
    none = DenseFlow(calibration=CAL).compute(flat, flat)
    assert none.status == "no contact" and not none.valid.any()
    assert len(none.motion()) == 0
    half0, half1 = f0.copy(), f1.copy()
    half0[:, 160:] = 230  # contact lost over the right half
    half1[:, 160:] = 230
    part = DenseFlow(calibration=CAL).compute(half0, half1)
    right = part.grid_x > 190
    assert not part.valid[:, right].any() and part.valid[:, part.grid_x < 130].mean() > 0.8


def test_dense_sampler_and_bad_inputs():
    flow = np.zeros((10, 12, 2), np.float32)
    flow[..., 0] = np.arange(12)[None, :]
    np.testing.assert_allclose(sample_dense_flow(flow, np.array([[2.5, 3.0]])), [[2.5, 0.0]])
    with pytest.raises(InvalidInputError, match="flow"):
        sample_dense_flow(np.zeros((3, 3)), np.zeros((1, 2)))
    with pytest.raises(InvalidInputError, match="grid_step_mm"):
        FlowParams(grid_step_mm=0)
    with pytest.raises(InvalidInputError, match="sor_omega"):
        FlowParams(sor_omega=2.0)
    with pytest.raises(InvalidInputError, match="prior_refits"):
        FlowParams(prior_refits=0)
    with pytest.raises(InvalidInputError, match="differ in shape"):
        DenseFlow(calibration=CAL).compute(np.zeros((50, 60), np.uint8), np.zeros((50, 61), np.uint8))


def test_sequence_equals_pairwise_compute(strained_pair):
    f0, f1, _ = strained_pair
    flat = np.full(SHAPE, 230, np.uint8)
    frames = [f0, f1, f0, flat, f1]  # a direction reversal and a frame out of contact in the middle
    flow = DenseFlow(calibration=CAL)
    seen = []
    for threads in (1, 2, 3):
        fields = flow.compute_sequence(frames, first_frame=10, threads=threads, on_field=seen.append)
        assert [(f.frame_a, f.frame_b) for f in fields] == [(10, 11), (11, 12), (12, 13), (13, 14)]
        for k, f in enumerate(fields):
            ref = flow.compute(frames[k], frames[k + 1], frame_a=10 + k, frame_b=11 + k)
            assert f.status == ref.status
            np.testing.assert_array_equal(f.valid, ref.valid)
            np.testing.assert_array_equal(f.displacement, ref.displacement)
    assert len(seen) == 12
    assert fields[3].status == "no contact" and not fields[3].valid.any()
    # forward then back: opposite displacements
    d01, d12 = fields[0].displacement, fields[1].displacement
    assert np.nanmedian(d01[..., 0]) == pytest.approx(-np.nanmedian(d12[..., 0]), abs=0.1)
    assert flow.compute_sequence([f0]) == []
    with pytest.raises(InvalidInputError, match="threads"):
        flow.compute_sequence(frames, threads=0)
    with pytest.raises(InvalidInputError, match="shape"):
        flow.compute_sequence([f0, f0[:, :300]])

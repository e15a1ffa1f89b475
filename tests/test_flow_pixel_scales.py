"""The dense method on a real print at the pixel scales a lab brings (15-100 px/mm), smaller than the frame on a
white or black background: its coarse levels keep the ridges resolvable (a 20 px/mm print was read tens of pixels
wrong when the pyramid halved the 8.5 px ridge period twice)."""

import numpy as np
import pytest

from skinstretch.processing.flow import DenseFlow
from skinstretch.processing.pixel_scale import Calibration
from tests.print_clips import print_frame, print_image, true_x

SHAPE = (240, 320)


@pytest.mark.parametrize("px_per_mm", [15.0, 19.7, 40.0, 100.0])
@pytest.mark.parametrize("background", [255.0, 0.0])
def test_flow_on_a_real_print_at_any_scale_and_background(px_per_mm, background):
    shape = SHAPE if px_per_mm < 62 else (484, 640)  # at 100 px/mm a 320 px frame holds 2 mm² of print: too little
    image = print_image()
    a, b = (print_frame(image, k, px_per_mm=px_per_mm, background=background, shape=shape) for k in (0, 1))
    flow = DenseFlow(calibration=Calibration(px_per_mm=px_per_mm)).compute(a, b)
    assert flow.status == "ok" and flow.valid.sum() > 50
    X, _ = np.meshgrid(flow.grid_x, flow.grid_y)
    true_dx = true_x(X, 1, width=shape[1], slide_px=0.5, stretch=0.0005) - X
    err = np.hypot(flow.displacement[..., 0] - true_dx, flow.displacement[..., 1])[flow.valid]
    assert np.sqrt(np.mean(err**2)) < 0.05


def test_reductions_keep_the_ridge_period_resolvable():
    for px_per_mm in (15.0, 19.7, 30.0, 62.0, 100.0, 200.0):
        cal = Calibration(px_per_mm=px_per_mm)
        period = cal.px(0.43)
        assert period / 2 ** cal.resolvable_halvings(5) >= 6.0
        assert period / cal.resolvable_reduction(4) >= 6.0
    assert Calibration(px_per_mm=62.0).resolvable_halvings(5) == 2  # the rig's scale keeps its two levels

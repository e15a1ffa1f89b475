"""The strain tensor of triangles, the cumulative strain and the virtual gauge (issue 40): the pure computation
against closed forms, and the whole analysis on a real print moved by a known affine map (both methods)."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from skinstretch.cli import main
from skinstretch.experiments.bench.affine import PX_PER_MM, affine_clip, gauge_errors, triangle_errors, true_tensor
from skinstretch.processing.strain_tensor import (
    TENSOR_DEGENERATE, TENSOR_NOT_FINITE, TENSOR_OK, green_lagrange, local_affine_fit, triangle_strain_tensors,
)


def _rotation(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


@pytest.mark.parametrize("deg", [0.0, 7.0, -30.0, 90.0])
def test_a_rigid_motion_has_no_strain(deg):
    t = green_lagrange(_rotation(deg))
    for c in ("exx", "eyy", "exy", "e1", "e2"):
        assert abs(float(getattr(t, c))) < 1e-12


def test_principal_strains_of_a_rotated_stretch():
    # 2 % along a direction 30 deg from +x towards +y, -1 % across it.
    r = _rotation(30.0)
    F = r @ np.diag([1.02, 0.99]) @ r.T
    t = green_lagrange(F)
    assert float(t.e1) == pytest.approx(0.5 * (1.02**2 - 1), abs=1e-12)
    assert float(t.e2) == pytest.approx(0.5 * (0.99**2 - 1), abs=1e-12)
    assert float(t.angle_deg) == pytest.approx(30.0, abs=1e-9)
    assert float(t.exx + t.eyy) == pytest.approx(float(t.e1 + t.e2), abs=1e-12)  # the trace is invariant


def test_simple_shear_gives_half_the_engineering_shear():
    g = 0.004
    t = green_lagrange(np.array([[1.0, g], [0.0, 1.0]]))
    assert float(t.exy) == pytest.approx(g / 2, abs=1e-15)
    assert float(t.exx) == 0.0 and float(t.eyy) == pytest.approx(g * g / 2)


def test_triangles_degenerate_or_not_finite_are_flagged_never_nan():
    a = np.array([[[0, 0], [10, 0], [0, 10]], [[0, 0], [5, 5], [10, 10]], [[0, 0], [10, 0], [0, 10]]], float)
    b = a * [1.01, 0.98]
    b[2, 1, 0] = np.nan
    t = triangle_strain_tensors(a, b)
    assert t.status.tolist() == [TENSOR_OK, TENSOR_DEGENERATE, TENSOR_NOT_FINITE]
    for c in ("exx", "eyy", "exy", "e1", "e2", "angle_deg"):
        v = getattr(t, c)
        assert np.all(np.isfinite(v)) and np.all(v[1:] == 0)
    assert t.exx[0] == pytest.approx(0.5 * (1.01**2 - 1)) and t.eyy[0] == pytest.approx(0.5 * (0.98**2 - 1))


def test_local_affine_fit_recovers_the_map_and_refuses_too_few_or_collinear_points(rng):
    pa = rng.uniform(0, 100, (200, 2))
    F = np.array([[1.01, 0.003], [-0.002, 0.995]])
    pb = (pa - 50) @ F.T + 50 + [3.0, -1.0]
    fit = local_affine_fit(pa, pb, center=(40.0, 60.0), radius_px=15.0)
    assert fit.ok and fit.n_points > 10
    np.testing.assert_allclose(fit.F, F, atol=1e-12)
    np.testing.assert_allclose(fit.position_b, (np.array([40.0, 60.0]) - 50) @ F.T + 50 + [3.0, -1.0], atol=1e-9)
    assert fit.residual_rms_px < 1e-9 and np.all(fit.F_sigma < 1e-9)  # exact: no residual
    noisy = local_affine_fit(pa, pb + rng.normal(0, 0.05, pb.shape), center=(40.0, 60.0), radius_px=15.0)
    assert 0.03 < noisy.residual_rms_px < 0.07 and np.all(noisy.F_sigma > 0)
    assert np.all(np.abs(noisy.F - F) < 5 * noisy.F_sigma)
    few = local_affine_fit(pa, pb, center=(40.0, 60.0), radius_px=0.5)
    assert not few.ok and "need 3" in few.reason and float(few.strain.exx) == 0.0
    line = np.column_stack([np.arange(10.0), np.arange(10.0)])
    flat = local_affine_fit(line, line * 1.01, center=(5.0, 5.0), radius_px=20.0)
    assert not flat.ok and "collinear" in flat.reason


@pytest.fixture(scope="module")
def affine_results(tmp_path_factory):
    """Both methods' results on a real print moved by a known affine map (files, so the CLI can probe them)."""
    from skinstretch.experiments.analysis import analysis_params, analyze_frames
    from skinstretch.processing.pixel_scale import Calibration

    clip = affine_clip(n_frames=10, seed=3)
    params = analysis_params({"strain": {"spans": [1, 5]}, "execution": {"kind": "serial"}})
    out = {}
    for method in ("features", "flow"):
        path = tmp_path_factory.mktemp(method) / "results.h5"
        out[method] = analyze_frames(clip.frames, calibration=Calibration(px_per_mm=PX_PER_MM), method=method,
                                     params=params, results_path=path)
    return clip, out


@pytest.mark.parametrize("method", ["features", "flow"])
def test_triangle_tensors_match_a_known_affine_within_0_05_percent(affine_results, method):
    clip, results = affine_results
    r = results[method]
    for span, st in r.strain.items():
        e = triangle_errors(st.triangles, st.pairs, clip)
        assert e.pairs >= 10 - span - 1 and e.triangles > 100 * e.pairs
        assert e.max < 5e-4, (span, e.worst)
    c = r.cumulative
    assert c.reference_frame == 0 and c.pairs.size == 9
    e = triangle_errors(c.triangles, c.pairs, clip)
    assert e.pairs == 9 and e.max < 5e-4, e.worst


@pytest.mark.parametrize("method", ["features", "flow"])
def test_the_gauge_follows_the_cumulative_strain_within_0_1_percent(affine_results, method):
    clip, results = affine_results
    tensor_err, extensometer_err, n_points = gauge_errors(results[method], clip)
    assert n_points >= 6
    assert tensor_err < 1e-3 and extensometer_err < 1e-3
    truth = true_tensor(clip.gradient(0, 9))
    assert truth["exx"] > 0.01  # the strain measured is ten times the bar
    from skinstretch.experiments.probe import probe

    last = probe(results[method], at=tuple(clip.center), radius_mm=1.5).rows[-1]
    for c in ("exx", "eyy", "exy"):  # the gauge's standard errors are of the size of its errors
        sigma = getattr(last, f"{c}_sigma")
        assert 0 < sigma < 1e-3 and abs(getattr(last, c) - truth[c]) < 4 * sigma + 1e-5, (c, sigma)
    assert 0 < last.residual_px < 0.1


def test_the_tensor_columns_have_units_and_come_with_the_dataframe(affine_results):
    _, results = affine_results
    r = results["features"]
    df = r.to_dataframe("triangles", span=1)
    for c in ("exx", "eyy", "exy", "e1", "e2", "angle_deg", "tensor_status", "frame_a", "frame_b"):
        assert c in df.columns
    assert np.isfinite(df[["exx", "eyy", "exy", "e1", "e2"]].to_numpy()).all()
    assert (df["e1"] >= df["e2"]).all()
    info = r.dataset_info("strain/span_1/triangles")
    units = info.column_units()
    assert units["exx"] == "1" and units["angle_deg"] == "deg"
    assert "tensor_status" in info.column_codes
    cum = r.to_dataframe("cumulative")
    assert set(cum["frame_a"]) == {0} and cum["frame_b"].max() == 9


def test_probe_command_writes_a_gauge_and_an_extensometer(affine_results, tmp_path):
    clip, results = affine_results
    outdir = results["flow"].path.parent
    x, y = clip.center
    gauge = tmp_path / "gauge.csv"
    assert main(["probe", str(outdir), "--at", f"{x},{y}", "--radius-mm", "1.5", "-o", str(gauge)]) == 0
    rows = list(csv.DictReader(gauge.read_text().splitlines()))
    assert len(rows) == 10 and rows[0]["exx"] == "0" and rows[-1]["ok"] == "1"
    assert float(rows[-1]["exx"]) == pytest.approx(true_tensor(clip.gradient(0, 9))["exx"], abs=1e-3)
    moved = clip.position(9, clip.center)
    assert float(rows[-1]["x"]) == pytest.approx(moved[0], abs=0.05)
    ext = tmp_path / "ext.csv"
    assert main(["probe", str(outdir), "--at", f"{x - 30},{y}", "--to", f"{x + 30},{y}", "-o", str(ext)]) == 0
    rows = list(csv.DictReader(ext.read_text().splitlines()))
    assert {"x1", "y1", "x2", "y2", "length_px", "length_change"} <= set(rows[0])
    assert main(["probe", str(outdir), "--at", f"{x},{y}", "-o", str(gauge)]) == 2  # exists: --overwrite
    assert main(["probe", str(outdir), "--at", "9999,1", "-o", str(tmp_path / "x.csv")]) == 2


def test_probe_in_python_gives_a_dataframe(affine_results):
    import skinstretch as ss

    clip, results = affine_results
    series = ss.probe(results["features"].path.parent, at=tuple(clip.center), radius_mm=1.5)
    df = series.to_dataframe()
    assert list(df.columns[:3]) == ["frame", "x", "y"] and len(df) == 10 and df["ok"].all()


def test_the_flows_cumulative_strain_carries_on_across_a_refused_frame():
    """A black frame mid-clip: the flow refuses it, and the skin points are registered from the reference frame
    again after it (the gauge has no value on that frame only)."""
    from skinstretch.experiments.analysis import analysis_params, analyze_frames
    from skinstretch.experiments.probe import probe
    from skinstretch.processing.pixel_scale import Calibration

    clip = affine_clip(n_frames=10, seed=4)
    frames = clip.frames.copy()
    frames[5] = 0
    r = analyze_frames(frames, calibration=Calibration(px_per_mm=PX_PER_MM), method="flow",
                       params=analysis_params({"strain": {"spans": [1]}, "execution": {"kind": "serial"}}))
    assert r.frame_flags[5] == "all_black"
    c = r.cumulative
    assert c.pairs["frame_b"].tolist() == [1, 2, 3, 4, 6, 7, 8, 9]
    assert len(set(c.pairs["n_points"].tolist())) == 1  # no skin point lost
    e = triangle_errors(c.triangles, c.pairs, clip)
    assert e.pairs == 8 and e.max < 5e-4, e.worst
    rows = probe(r, at=tuple(clip.center), radius_mm=1.5).rows
    assert [row.ok for row in rows] == [True] * 5 + [False] + [True] * 4
    assert "no motion measured" in rows[5].reason

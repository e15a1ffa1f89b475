"""The texture gate: real prints always pass, noise / blank / black / saturated / out-of-focus frames never do, and
both motion methods report no motion from a frame it refuses."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.extraction import extract_features
from skinstretch.processing.flow import DenseFlow
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.texture_gate import (
    PLAUSIBLE_RIDGE_PERIOD_MM,
    TextureGateParams,
    ridge_period_mm,
    texture_verdict,
)

SCENES = ("flat1", "flat2", "flatL", "flatS", "ridgeL", "ridgeS", "valleyL", "valleyS")
PX_PER_MM = 640 / 10.3
SHAPE = (484, 640)


@pytest.fixture(scope="module")
def scene_frames():
    """First, middle and last frame of every bundled scene, two prints (seeds) each."""
    from skinstretch.simulators.scene import SceneRenderer, load_scene

    out = []
    for name in SCENES:
        for seed in (0, 1):
            r = SceneRenderer(load_scene(name), seed=seed)
            for k in (0, r.n_frames // 2, r.n_frames - 1):
                out.append((f"{name} seed {seed} frame {k}", r.render_frame(k), r.calibration.px_per_mm))
    return out


def _noise(kind: int, rng: np.random.Generator) -> np.ndarray:
    if kind == 0:  # white, uniform
        return rng.integers(0, 256, SHAPE).astype(np.uint8)
    if kind == 1:  # white, Gaussian, any contrast
        return np.clip(rng.normal(128, rng.uniform(3, 60), SHAPE), 0, 255).astype(np.uint8)
    if kind == 2:  # smooth noise, correlation length 0.5-6 px
        g = cv2.GaussianBlur(rng.normal(0, 1, SHAPE).astype(np.float32), (0, 0), rng.uniform(0.5, 6))
        return np.clip(128 + g / g.std() * 40, 0, 255).astype(np.uint8)
    return np.clip(rng.normal(200, 20, SHAPE) * (rng.random(SHAPE) > 0.5), 0, 255).astype(np.uint8)  # speckle


def test_every_real_frame_of_every_scene_passes(scene_frames):
    for label, frame, px_per_mm in scene_frames:
        v = texture_verdict(frame, px_per_mm=px_per_mm)
        assert v.ok, f"{label}: {v}"
        assert v.textured_mm2 >= 20.0, f"{label}: only {v.textured_mm2:.1f} mm^2 textured"  # 5x the threshold


def test_every_scene_frame_has_a_fingertips_ridge_period_at_its_scale_and_no_other(scene_frames):
    lo, hi = PLAUSIBLE_RIDGE_PERIOD_MM
    for label, frame, px_per_mm in scene_frames:
        period = ridge_period_mm(frame, px_per_mm=px_per_mm)
        assert lo <= period <= hi, f"{label}: {period:.3f} mm"
        # The same frame read at twice or half the pixel scale (a wrong calibration) has ridges no finger has.
        assert not lo <= ridge_period_mm(frame, px_per_mm=2 * px_per_mm) <= hi, label
        assert not lo <= ridge_period_mm(frame, px_per_mm=px_per_mm / 2) <= hi, label
    assert np.isnan(ridge_period_mm(np.full(SHAPE, 200, np.uint8), px_per_mm=62.0))  # flat: no period


@settings(max_examples=60, deadline=None, derandomize=True)
@given(kind=st.integers(0, 3), seed=st.integers(0, 2**32 - 1))
def test_noise_never_passes(kind, seed):
    v = texture_verdict(_noise(kind, np.random.default_rng(seed)), px_per_mm=PX_PER_MM)
    assert v.reason in ("no_texture", "out_of_focus") and v.textured_blocks <= 1


@pytest.mark.parametrize("value, reason", [(0, "all_black"), (19, "all_black"), (128, "no_texture"),
                                           (230, "no_texture"), (255, "saturated")])
def test_uniform_frames_are_refused_with_their_reason(value, reason):
    assert texture_verdict(np.full(SHAPE, value, np.uint8), px_per_mm=PX_PER_MM).reason == reason


def test_a_print_out_of_focus_is_refused_as_such():
    """Defocus blurs the print before the sensor adds its noise: render noiseless, blur, then add the noise."""
    from skinstretch.simulators.scene import SceneRenderer, load_scene

    rng = np.random.default_rng(3)
    for name in SCENES:
        r = SceneRenderer(load_scene(name), seed=2, noise=0)
        sharp, px_per_mm = r.render_frame(0).astype(np.float32), r.calibration.px_per_mm
        for sigma_mm, passes in ((0.1, True), (0.2, False), (0.3, False), (0.5, False)):
            blurred = cv2.GaussianBlur(sharp, (0, 0), sigma_mm * px_per_mm) + rng.normal(0, 2.0, sharp.shape)
            v = texture_verdict(np.clip(blurred, 0, 255).astype(np.uint8), px_per_mm=px_per_mm)
            assert v.ok if passes else v.reason == "out_of_focus", (name, sigma_mm, v)


def test_a_saturated_print_is_refused(scene_frames):
    _, frame, px_per_mm = scene_frames[12]  # flatL, seed 0
    over = np.clip(frame.astype(np.int32) * 3, 0, 255).astype(np.uint8)
    assert texture_verdict(over, px_per_mm=px_per_mm).reason == "saturated"


def test_both_methods_refuse_noise_and_measure_nothing():
    cal = Calibration(px_per_mm=PX_PER_MM)
    rng = np.random.default_rng(5)
    noise = [_noise(0, rng) for _ in range(2)]
    res = extract_features(noise[0], calibration=cal)
    assert not res.ok and res.flags == {"no_texture"} and res.features.size == 0
    field = DenseFlow(calibration=cal).compute(noise[0], noise[1])
    assert field.status == "no_texture" and field.frame_flags == ("no_texture", "no_texture")
    assert not field.valid.any() and len(field.motion()) == 0
    black = np.zeros(SHAPE, np.uint8)
    field = DenseFlow(calibration=cal).compute(black, noise[1])
    assert field.frame_flags == ("all_black", "no_texture") and field.status == "all_black"


def test_sessions_without_a_print_give_no_ok_pair_and_flag_every_frame():
    from skinstretch.experiments.analysis import analysis_params, analyze_frames
    from skinstretch.experiments.results_file import PairStatus

    cal = Calibration(px_per_mm=PX_PER_MM)
    rng = np.random.default_rng(11)
    sessions = {"noise": [_noise(0, rng) for _ in range(8)], "blank": [np.full(SHAPE, 128, np.uint8)] * 8,
                "saturated": [np.full(SHAPE, 255, np.uint8)] * 8}
    for name, frames in sessions.items():
        for method in ("flow", "features"):
            r = analyze_frames(frames, calibration=cal, method=method, params=analysis_params({"execution": {"kind": "threads"}}))
            assert all(r.frame_flags), (name, method, r.frame_flags)
            for span in r.strain.values():
                assert not np.any(span.pairs["status"] == PairStatus.OK), (name, method)
            assert not np.any(r.fingertip_valid), (name, method)


def test_bad_arguments_are_named():
    with pytest.raises(InvalidInputError, match="min_coherence"):
        TextureGateParams(min_coherence=1.5)
    with pytest.raises(InvalidInputError, match="black_level"):
        TextureGateParams(black_level=float("nan"))
    with pytest.raises(InvalidInputError, match="px_per_mm"):
        texture_verdict(np.zeros((64, 64), np.uint8) + 100, px_per_mm=0)
    with pytest.raises(InvalidInputError, match="2-D uint8"):
        texture_verdict(np.zeros((64, 64, 3), np.uint8), px_per_mm=62.0)
    with pytest.raises(InvalidInputError, match="smaller than one gate block"):
        texture_verdict(np.full((40, 40), 100, np.uint8), px_per_mm=62.0)

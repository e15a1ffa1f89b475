"""Trajectories anchored to key frames (``KeyframeAnchoring``): a chain of steps that all err the same way drifts;
a direct registration from a reference key frame measures that drift, and the corrections, spread between key
frames, take it out. The analysis uses it wherever the skin slides on glass or a shape's shading was removed."""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from skinstretch.processing.displacement_refinement import SubpixelRefiner
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.trajectory_anchoring import KeyframeAnchoring, KeyframeCorrections

CAL = Calibration(px_per_mm=62.0)
H, W = 200, 240
STEP = np.array([0.23, -0.11])  # true motion per frame, px
DRIFT = np.array([0.02, 0.015])  # what every chained step adds to it, px (a lossy copy's bias)


def _frames(n):
    """A blotchy texture moving by STEP a frame (quintic splines: OpenCV's warps round shifts to 1/32 px), 0.8 grey
    of noise."""
    rng = np.random.default_rng(4)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 2.5)
    tex = (tex - tex.mean()) * (60 / tex.std()) + 128
    out = []
    for k in range(n):
        moved = ndimage.shift(tex, (STEP[1] * k, STEP[0] * k), order=5, mode="reflect")
        out.append(np.clip(moved + rng.normal(0, 0.8, tex.shape), 0, 255).astype(np.uint8))
    return out


def test_key_frames_take_out_the_drift_of_a_chain_that_errs_one_way():
    """Key frames 0, 5, .., 20 and the clip's last frame, 23: the drift is taken out at every frame, the last ones
    too."""
    n, every = 24, 5
    frames = _frames(n)
    p0 = np.array([[x, y] for x in (70.0, 100.5, 130.2, 160.0) for y in (60.0, 95.5, 130.0)])
    m = p0.shape[0]
    late = np.arange(m, m + 3)  # three more runs that start at frame 10
    p10 = p0[:3] + 10 * STEP + np.array([3.0, 4.0])
    anchoring = KeyframeAnchoring(SubpixelRefiner(calibration=CAL), frames.__getitem__, interval=every,
                                  reference_span=40)
    chained = {}
    for k in [*range(0, n, every), n - 1]:
        xy = p0 + k * (STEP + DRIFT)
        group = np.arange(m)
        if k >= 10:
            xy = np.vstack([xy, p10 + (k - 10) * (STEP + DRIFT)])
            group = np.r_[group, late]
        chained[k] = xy
        anchoring.add(k, group, xy, final=k == n - 1)
    c = anchoring.corrections()
    for k in range(n):  # every frame, key frame or not
        xy = p0 + k * (STEP + DRIFT)
        fixed = xy + c.at(np.arange(m), np.full(m, k))
        true = p0 + k * STEP
        assert np.abs(fixed - true).max() < 0.015, (k, np.abs(fixed - true).max())
        # uncorrected, frame 23 is 0.5 px off
    assert np.abs(chained[23][:m] - (p0 + 23 * STEP)).max() > 0.35
    assert c.frame.max() == 23
    # A run's first key frame is its reference: no correction there, and its drift is measured from it.
    assert np.allclose(c.at(late, np.full(3, 10)), 0.0)
    late_20 = chained[20][m:] + c.at(late, np.full(3, 20))
    assert np.abs(late_20 - (p10 + 10 * STEP)).max() < 0.015


def test_a_point_the_registration_cannot_measure_keeps_its_chained_positions():
    frames = _frames(11)
    p = np.array([[3.0, 100.0], [120.0, 100.0]])  # the first one's window leaves the image
    anchoring = KeyframeAnchoring(SubpixelRefiner(calibration=CAL), frames.__getitem__, interval=5, reference_span=40)
    for k in (0, 5, 10):
        anchoring.add(k, np.array([0, 1]), p + k * (STEP + DRIFT))
    c = anchoring.corrections()
    assert np.allclose(c.at(np.array([0, 0]), np.array([5, 10])), 0.0)
    assert np.all(np.isfinite(c.dx)) and np.abs(c.at(np.array([1]), np.array([10]))[0] + 10 * DRIFT).max() < 0.015


def test_a_black_key_frame_is_chained_over_and_the_next_is_registered_past_it():
    frames = _frames(21)
    frames[10] = np.zeros_like(frames[10])
    p = np.array([[x, 100.0] for x in (80.0, 120.0, 160.0)])
    anchoring = KeyframeAnchoring(SubpixelRefiner(calibration=CAL), frames.__getitem__, interval=5, reference_span=40)
    raw = {}
    for k in (0, 5, 10, 15, 20):
        anchoring.add(k, np.arange(3), p + k * (STEP + DRIFT))
        raw[k] = anchoring._rows[-1][2]
    assert np.allclose(raw[10], raw[5])  # nothing to register against: chained on from key frame 5
    for k in (15, 20):
        assert np.abs(raw[k] + k * DRIFT).max() < 0.015, k


def test_each_anchored_position_carries_its_registrations_variance():
    """0 at a run's first key frame; a registration's predicted variance at the next ones (covering the anchored
    position's error); the reference's own variance added once the reference has moved on; inf at a black key
    frame (nothing registered), finite again past it."""
    n = 24
    frames = _frames(n)
    frames[15] = np.zeros_like(frames[15])
    p0 = np.array([[x, y] for x in (70.0, 100.5, 130.2, 160.0) for y in (60.0, 95.5, 130.0)])
    m = p0.shape[0]
    anchoring = KeyframeAnchoring(SubpixelRefiner(calibration=CAL), frames.__getitem__, interval=5, reference_span=10)
    var = {}
    for k in (0, 5, 10, 15, 20, 23):
        anchoring.add(k, np.arange(m), p0 + k * (STEP + DRIFT), final=k == 23)
        var[k] = anchoring._rows[-1][3]
        if k in (5, 10, 20):  # registered: the anchored position's error within its 95 % interval
            anchored = p0 + k * (STEP + DRIFT) + anchoring._rows[-1][2]
            err = np.hypot(*(anchored - (p0 + k * STEP)).T)
            assert np.all(err <= 2.45 * np.sqrt(var[k])), (k, err, np.sqrt(var[k]))
    assert np.all(var[0] == 0.0)
    assert np.all((var[5] > 0.0) & (np.sqrt(var[5]) < 0.05)) and np.all(var[10] < 2 * var[5])
    assert np.all(np.isinf(var[15]))  # black: chained on, from reference 10
    assert np.all(var[20] > var[10]) and np.all(np.isfinite(var[20]))  # registered from 10, which carries its own
    c = anchoring.corrections()
    v = c.variance_at(np.zeros(4, np.int64), np.array([0, 5, 12, 22]))
    assert v[0] == 0.0 and v[1] == pytest.approx(var[5][0]) and np.isinf(v[2]) and np.isfinite(v[3])


def test_corrections_are_linear_between_key_frames_and_held_beyond():
    c = KeyframeCorrections(group=np.array([0, 0, 1]), frame=np.array([0, 10, 5]), dx=np.array([0.0, 1.0, 2.0]),
                            dy=np.array([0.0, -1.0, 0.5]))
    got = c.at(np.array([0, 0, 0, 1, 1, 7]), np.array([5, 12, 0, 0, 9, 3]))
    assert got.tolist() == [[0.5, -0.5], [1.0, -1.0], [0.0, 0.0], [2.0, 0.5], [2.0, 0.5], [0.0, 0.0]]


def test_a_session_with_one_key_frame_or_none_has_no_corrections():
    """Too short a clip (or no kept trajectory) gives no correction, and the positions stay chained."""
    a = KeyframeAnchoring(SubpixelRefiner(calibration=CAL), _frames(1).__getitem__, interval=5, reference_span=40)
    assert a.corrections().group.size == 0
    a.add(0, np.zeros(0, np.int64), np.zeros((0, 2)))  # key frames with no run present
    assert a.corrections().group.size == 0
    a = KeyframeAnchoring(SubpixelRefiner(calibration=CAL), _frames(1).__getitem__, interval=5, reference_span=40)
    a.add(0, np.array([3]), np.array([[50.0, 60.0]]))
    c = a.corrections()
    assert c.group.tolist() == [3] and c.dx.tolist() == [0.0] and c.at(np.array([3, 4]), np.array([2, 2])).tolist() == [
        [0.0, 0.0], [0.0, 0.0]]
    a.add(5, np.zeros(0, np.int64), np.zeros((0, 2)))  # no run present at a key frame
    assert a.corrections().group.size == 1


def test_key_frames_must_come_in_order_and_make_sense():
    r = SubpixelRefiner(calibration=CAL)
    with pytest.raises(InvalidInputError, match="interval >= 2"):
        KeyframeAnchoring(r, lambda k: None, interval=1, reference_span=40)
    with pytest.raises(InvalidInputError, match="reference span >= it"):
        KeyframeAnchoring(r, lambda k: None, interval=10, reference_span=5)
    a = KeyframeAnchoring(r, lambda k: np.zeros((50, 50), np.uint8), interval=5, reference_span=20)
    with pytest.raises(InvalidInputError, match="increasing multiples of 5, then the last frame"):
        a.add(3, np.array([0]), np.array([[10.0, 10.0]]))
    a.add(0, np.array([0]), np.array([[10.0, 10.0]]))
    a.add(3, np.array([0]), np.array([[10.0, 10.0]]), final=True)
    with pytest.raises(InvalidInputError, match="got 5 after 3"):  # nothing after the last frame
        a.add(5, np.array([0]), np.array([[10.0, 10.0]]))


def test_the_feature_analysis_anchors_its_trajectories(sim_session, monkeypatch):
    """flatL: the positions' drift against the truth from each trajectory's start is smaller with key frames than
    without, frame-to-frame motion as good; the key frames are every 5th frame and the last."""
    from skinstretch.experiments.analysis import analysis_params, analyze_frames
    from skinstretch.experiments.evaluation.tracking import evaluate_tracking
    from skinstretch.experiments.evaluation.trajectories import evaluate_trajectories

    keys = []
    original = KeyframeAnchoring.add
    monkeypatch.setattr(KeyframeAnchoring, "add", lambda self, k, *a, final=False: keys.append((k, final)) or
                        original(self, k, *a, final=final))
    s = sim_session
    out = {}
    for every in (5, None):
        r = analyze_frames(s.frames, calibration=s.calibration, method="features", surface="flat",
                           params=analysis_params({"tracking": {"keyframe_interval_frames": every}}))
        out[every] = (evaluate_trajectories(r, s.truth), evaluate_tracking(r, s.truth))
    n = len(s.frames)
    assert n % 5 != 1 and keys == [(k, False) for k in range(0, n, 5)] + [(n - 1, True)]
    on, off = out[5], out[None]
    assert on[0]["drift_rmse_px"] < off[0]["drift_rmse_px"]
    assert on[1]["tracking"]["displacement_rmse_px"] < 1.05 * off[1]["tracking"]["displacement_rmse_px"]


def test_the_analysis_anchors_where_the_shading_is_known(sim_session, monkeypatch):
    """On plain glass the corrections follow the drift over 3 key frames; over a ridge whose glass-fixed shading was
    removed, each registration also carries what that step leaves, and a line over 9 key frames (a reference's
    span) is fitted instead; the drift against the truth is smaller than chained there too. Over a ridge whose
    shading stayed (the skin slid too little) the registrations would follow the shading itself: chained."""
    from skinstretch.experiments.analysis import analysis_params, analyze_frames
    from skinstretch.experiments.analysis.trajectories import TrajectoryStore
    from skinstretch.experiments.evaluation.trajectories import evaluate_trajectories
    from skinstretch.simulators.scene import load_scene, render_session

    calls = []
    original = TrajectoryStore.anchor
    monkeypatch.setattr(TrajectoryStore, "anchor", lambda self, a: calls.append(a.smoothing) or original(self, a))
    s = sim_session
    analyze_frames(s.frames, calibration=s.calibration, method="features", params=analysis_params(), surface="flat")
    assert calls == [3]
    calls.clear()
    ridge = render_session(load_scene("ridgeL"), n_frames=40, seed=1)
    drift = {}
    for every in (5, None):
        r = analyze_frames(ridge.frames, calibration=ridge.calibration, method="features", surface="ridge",
                           params=analysis_params({"tracking": {"keyframe_interval_frames": every}}))
        assert r.params["glass_shading_status"].startswith("applied")
        drift[every] = evaluate_trajectories(r, ridge.truth)["drift_rmse_px"]
    assert calls == [9]  # with key frames only
    assert drift[5] < drift[None]
    calls.clear()
    short = render_session(load_scene("ridgeL"), n_frames=24, seed=0)
    r = analyze_frames(short.frames, calibration=short.calibration, method="features", surface="ridge",
                       params=analysis_params({"tracking": {"min_length_frames": 12}}))
    assert r.params["glass_shading_status"].startswith("not applied") and calls == []


class _SlidingRefiner(SubpixelRefiner):
    """A refiner whose span registration of point ``slide`` lands 0.5 px along x from where the texture is (a
    window sliding along its ridges)."""

    slide = 3

    def register_span(self, prev_image, curr_image, points, displacement, **kwargs):
        fit = super().register_span(prev_image, curr_image, points, displacement, **kwargs)
        d = fit.displacement.copy()
        if len(d) > self.slide:
            d[self.slide, 0] += 0.5
        return fit._replace(displacement=d)


@pytest.mark.parametrize("astray", ["chain", "registration"])
def test_a_jump_is_taken_where_the_chain_went_astray_and_not_where_the_registration_did(astray):
    """12 points, one of them off by 0.5 px at key frame 5: where its chained steps read short (a codec's copy),
    the registration fits its window far better than the chained guess and is taken; where the registration slid,
    the chained guess fits better and the point is chained on."""
    frames = _frames(6)
    p0 = np.array([[x, y] for x in (70.0, 100.5, 130.2, 160.0) for y in (60.0, 95.5, 130.0)])
    chained = p0 + 5 * STEP
    refiner = SubpixelRefiner(calibration=CAL)
    if astray == "chain":
        chained[3, 0] -= 0.5
    else:
        refiner = _SlidingRefiner(calibration=CAL)
    anchoring = KeyframeAnchoring(refiner, frames.__getitem__, interval=5, reference_span=40)
    anchoring.add(0, np.arange(12), p0)
    anchoring.add(5, np.arange(12), chained)
    raw = anchoring._rows[-1][2]
    fixed = chained + raw
    assert np.abs(fixed - (p0 + 5 * STEP)).max() < 0.02
    if astray == "registration":
        assert np.allclose(raw[3], 0.0)


def test_a_registration_that_jumps_from_the_chained_guess_is_not_taken():
    """Between key frames the drift changes little: a point whose registration moves it tenths of a pixel from its
    chained guess (a window sliding along its ridges) is chained on; the others' steps, and a step the same
    everywhere, are taken."""
    from skinstretch.processing.trajectory_anchoring import _jumped

    rng = np.random.default_rng(2)
    step = rng.normal(0.0, 0.02, (40, 2)) + [0.03, -0.01]
    step[17] = [0.5, 0.3]
    ok = np.ones(40, bool)
    ok[3] = False
    step[3] = [5.0, 5.0]  # not registered: not judged
    assert np.flatnonzero(_jumped(step, ok)).tolist() == [17]
    assert not _jumped(np.tile([0.4, 0.1], (40, 1)), ok).any()
    assert not _jumped(step[:7], ok[:7]).any()  # too few to judge


@pytest.mark.parametrize("window", [3, 9])
def test_the_corrections_line_keeps_a_steady_drift_and_averages_noise(window):
    """A run's corrections along a straight line come back exactly whatever the window (a steady drift is kept);
    over 3 key frames an inner one is its mean with its neighbours' and the last the three-point line's end; noise
    is averaged, more over 9 key frames than over 3."""
    from skinstretch.processing.trajectory_anchoring import _line_fits

    group = np.repeat([4, 7, 9], [12, 2, 1])
    time = np.arange(group.size) + np.r_[np.zeros(11), -0.4, np.zeros(3)]  # the first run's last key frame: the clip's
    line = np.column_stack([0.03 * time, -0.01 * time])                     # last frame, 0.4 of an interval early
    assert np.allclose(_line_fits(group, time, line, window), line)
    time = np.arange(group.size, dtype=float)
    noise = np.random.default_rng(1).normal(0.0, 0.05, (group.size, 2))
    fit = _line_fits(group, time, noise, window)
    if window == 3:
        assert np.allclose(fit[5], noise[4:7].mean(axis=0))
        assert np.allclose(fit[11], (5 * noise[11] + 2 * noise[10] - noise[9]) / 6)
    assert np.allclose(fit[12:14], noise[12:14]) and np.allclose(fit[14], noise[14])  # two key frames, one
    assert np.std(fit[:12]) < (0.6 if window == 3 else 0.45) * 0.05  # the noise's 0.05 px


def test_a_point_near_the_edge_is_registered_with_a_smaller_window():
    """18 px from the image edge the 0.8 mm span window (51 px) leaves the image: unregistered as a span's point,
    registered with the largest window that fits (at least 0.4 mm) as a key frame's, at the true displacement."""
    frames = _frames(6)
    refiner = SubpixelRefiner(calibration=CAL)
    prev, curr = refiner.prepare(frames[0]), refiner.prepare(frames[5])
    points = np.array([[18.0, 100.0], [120.0, 18.5], [120.0, 100.0], [5.0, 100.0]])
    guess = np.tile(5 * STEP + [0.1, -0.1], (4, 1))
    plain = refiner.register_span(prev, curr, points, guess)
    assert plain.ok.tolist() == [False, False, True, False]
    near = refiner.register_span(prev, curr, points, guess, min_window_mm=0.4)
    assert near.ok.tolist() == [True, True, True, False]  # 5 px from the edge: no window of 0.4 mm fits
    assert np.abs(near.displacement[:3] - 5 * STEP).max() < 0.02
    assert np.array_equal(near.displacement[2], plain.displacement[2])
    assert np.array_equal(near.displacement[3], guess[3])

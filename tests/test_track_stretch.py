"""Skin stretch (seed 5.3), fingertip motion (5.2) and the tactile display mapping (5.4)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.display_mapping import DisplayMappingParams, HorizontalMapping, tactile_movie
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.fingertip import fingertip_motion, visibility_window
from skinstretch.processing.stretch import (
    horizontal_stretch_profile,
    local_movement,
    mean_profile,
    patch_area_change,
    triangulation_strain,
)
from skinstretch.processing.tracking import MotionSample

CAL = Calibration(px_per_mm=20.0)


def _points(n=40, seed=0):
    return np.random.default_rng(seed).uniform(0, 200, (n, 2))


def _sample(p, d, a=0, b=1):
    return MotionSample(a, b, p, d, np.arange(len(p)))


@settings(max_examples=30, deadline=None)
@given(
    tx=st.floats(-50, 50), ty=st.floats(-50, 50), theta=st.floats(-np.pi, np.pi), seed=st.integers(0, 1000)
)
def test_rigid_motion_gives_zero_strain(tx, ty, theta, seed):
    p = _points(seed=seed)
    c, s = np.cos(theta), np.sin(theta)
    q = p @ np.array([[c, -s], [s, c]]).T + [tx, ty]
    r = triangulation_strain(_sample(p, q - p))
    assert np.abs(r.edge_change).max() < 1e-9
    assert np.abs(r.area_change).max() < 1e-9
    assert not r.flipped.any()


@settings(max_examples=20, deadline=None)
@given(exx=st.floats(-0.2, 0.2), eyy=st.floats(-0.2, 0.2), seed=st.integers(0, 1000))
def test_uniform_stretch_is_measured_exactly(exx, eyy, seed):
    p = _points(seed=seed)
    d = p * [exx, eyy]
    r = triangulation_strain(_sample(p, d))
    np.testing.assert_allclose(r.area_change, (1 + exx) * (1 + eyy) - 1, atol=1e-9)
    horizontal = np.abs(p[r.edges[:, 0], 1] - p[r.edges[:, 1], 1]) < 1e-12
    np.testing.assert_allclose(r.edge_change[horizontal], exx, atol=1e-9)


def test_degenerate_inputs_raise_or_are_flagged():
    with pytest.raises(InsufficientDataError, match="need at least 3"):
        triangulation_strain(_sample(np.array([[0.0, 0.0], [1.0, 1.0]]), np.zeros((2, 2))))
    line = np.column_stack([np.arange(10.0), 2 * np.arange(10.0)])
    with pytest.raises(InsufficientDataError, match="collinear"):
        triangulation_strain(_sample(line, np.zeros((10, 2))))
    dup = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [5.0, 5.0]])
    with pytest.raises(InsufficientDataError):
        triangulation_strain(_sample(dup, np.zeros((4, 2))))
    # duplicates are dropped, not triangulated
    p = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [0.0, 10.0]])
    r = triangulation_strain(_sample(p, np.zeros((4, 2))))
    assert r.n_dropped == 1 and r.triangles.shape == (1, 3)
    # a triangle whose vertex crosses the opposite edge flips: flagged, area change below -1
    flip = np.zeros((3, 2))
    flip[2] = [0.0, -20.0]
    r = triangulation_strain(_sample(p[:3], flip))
    assert r.flipped.all() and (r.area_change < -1).all()
    # NaN positions never reach the triangulation
    pn = _points(10)
    dn = np.zeros_like(pn)
    dn[0] = np.nan
    assert 0 not in triangulation_strain(_sample(pn, dn)).ids


def test_local_movement_patch_area_and_profile_of_a_linear_stretch():
    rng = np.random.default_rng(1)
    p = rng.uniform(0, 400, (3000, 2))
    e = 0.02
    d = np.column_stack([e * (p[:, 0] - 200) + 3.0, np.full(len(p), -1.0)])  # 2 % along x, plus sliding
    s = _sample(p, d)
    ft = d.mean(axis=0)
    gx, gy = np.meshgrid(np.arange(100.0, 301, 50), np.arange(100.0, 301, 50))
    centers = np.stack([gx, gy], -1)
    lm = local_movement(s, fingertip_displacement=ft, centers=centers, radius_px=20.0)
    assert lm.valid.all() and lm.movement.shape == (5, 5, 2)
    np.testing.assert_allclose(lm.movement[..., 1], 0.0, atol=1e-12)
    change, ok = patch_area_change(centers, lm.movement, lm.valid)
    assert ok.all() and np.abs(change - e).max() < 0.004
    prof = horizontal_stretch_profile(
        s, fingertip_displacement=ft, x_positions=np.arange(60.0, 341, 20), strip_width_px=40.0
    )
    assert prof.valid.all() and np.abs(prof.change - e).max() < 0.002
    empty = local_movement(_sample(p[:0], d[:0]), fingertip_displacement=ft, centers=centers, radius_px=5.0)
    assert not empty.valid.any() and np.isnan(empty.movement).all()
    avg = mean_profile([prof, prof])
    np.testing.assert_allclose(avg.change, prof.change)
    with pytest.raises(InvalidInputError, match="radius_px"):
        local_movement(s, fingertip_displacement=ft, centers=centers, radius_px=0)


def test_fingertip_motion_and_visibility_window():
    p = _points(50)
    steps = [np.array([3.0, 0.0])] * 5 + [np.array([-2.0, 1.0])] * 5
    samples = [_sample(p, np.tile(s, (50, 1)), k, k + 1) for k, s in enumerate(steps)]
    samples[7] = _sample(p[:2], np.tile(steps[7], (2, 1)), 7, 8)  # too few features: flagged, holds still
    ft = fingertip_motion(samples, n_frames=11)
    assert not ft.valid[7] and ft.valid.sum() == 9
    np.testing.assert_allclose(ft.position[5], [15.0, 0.0])
    np.testing.assert_allclose(ft.position[-1], [15.0 - 8.0, 4.0])
    win = visibility_window(ft, image_shape=(100, 200))
    assert (win.x0, win.y0) == (0.0, 0.0) and win.x1 == pytest.approx(199 - 15.0) and win.y1 == pytest.approx(99 - 4.0)
    np.testing.assert_allclose(win.centers[5] - win.centers[0], [15.0, 0.0])
    far = fingertip_motion([_sample(p, np.tile([250.0, 0], (50, 1)))], n_frames=2)
    with pytest.raises(InsufficientDataError, match="stays in view"):
        visibility_window(far, image_shape=(100, 200))
    with pytest.raises(InvalidInputError):
        fingertip_motion(samples, n_frames=5)


def _movie_inputs(step_px, n=4, size=400, stretch=0.0):
    g = np.stack(np.meshgrid(np.arange(10.0, size - 10, 4), np.arange(10.0, size - 10, 4)), -1).reshape(-1, 2)
    samples = []
    for k in range(n - 1):
        d = np.tile(step_px, (len(g), 1)).astype(float)
        d[:, 0] += stretch * (g[:, 0] - size / 2)
        samples.append(MotionSample(k, k + 1, g, d, np.arange(len(g))))
    ft = fingertip_motion(samples, n_frames=n)
    return samples, ft, visibility_window(ft, image_shape=(size, size))


def test_tactile_movie_cumulates_resets_and_clips():
    samples, ft, win = _movie_inputs([0.0, 0.0], stretch=0.01)
    movie = tactile_movie(samples, fingertip=ft, window=win, calibration=CAL, image_shape=(400, 400))
    assert movie.positions_um.shape == (4, 10, 10) and movie.positions_um.dtype == np.float32
    np.testing.assert_array_equal(movie.positions_um[0], 0)
    # 1 % stretch per frame: contactor at +4.5 mm moves 45 um per frame -> clipped at 50 um from frame 2 on
    assert movie.positions_um[1, 0, -1] == pytest.approx(45.0, abs=1.5)  # relative to the mean motion
    assert movie.positions_um[2, 0, -1] == 50.0 and movie.clipped[2, 0, -1]
    assert np.all(np.abs(movie.positions_um) <= 50.0)
    assert np.all(movie.stretch_change[1] > 0)  # expansion everywhere
    # a square without features is reset
    holes = [MotionSample(s.frame_a, s.frame_b, s.points[s.points[:, 0] > 125], s.displacement[s.points[:, 0] > 125],
                          s.ids[s.points[:, 0] > 125]) for s in samples]
    m2 = tactile_movie(holes, fingertip=ft, window=win, calibration=CAL, image_shape=(400, 400))
    assert m2.reset[1, :, 0].all() and (m2.positions_um[1:, :, 0] == 0).all()
    # rotation mapping keeps the vector's length
    rot = tactile_movie(samples, fingertip=ft, window=win, calibration=CAL, image_shape=(400, 400),
                        params=DisplayMappingParams(horizontal=HorizontalMapping.ROTATION, range_um=1e6))
    assert np.all(np.abs(rot.positions_um) >= np.abs(movie.positions_um) - 1e-3)
    with pytest.raises(InvalidInputError, match="range_um"):
        DisplayMappingParams(range_um=0)


def test_tactile_movie_follows_a_vertical_sliding_axis():
    # The same 1 % stretch field, but along image y: with motion_axis=1 the movie must be the transpose of the
    # x case (columns along the sliding axis), not a field of zeros from projecting on x.
    samples, ft, win = _movie_inputs([0.0, 0.0], stretch=0.01)
    along_x = tactile_movie(samples, fingertip=ft, window=win, calibration=CAL, image_shape=(400, 400))
    swapped = [MotionSample(s.frame_a, s.frame_b, s.points[:, ::-1].copy(), s.displacement[:, ::-1].copy(), s.ids)
               for s in samples]
    ft_y = fingertip_motion(swapped, n_frames=len(swapped) + 1)
    win_y = visibility_window(ft_y, image_shape=(400, 400))
    along_y = tactile_movie(swapped, fingertip=ft_y, window=win_y, calibration=CAL, image_shape=(400, 400),
                            motion_axis=1)
    assert along_y.motion_axis == 1
    np.testing.assert_allclose(along_y.positions_um, along_x.positions_um, atol=1e-3)
    np.testing.assert_allclose(along_y.stretch_change, along_x.stretch_change, atol=1e-6)
    np.testing.assert_array_equal(along_y.reset, along_x.reset)
    projected_on_x = tactile_movie(swapped, fingertip=ft_y, window=win_y, calibration=CAL, image_shape=(400, 400))
    assert np.abs(projected_on_x.positions_um).max() < 1e-3  # the wrong axis sees nothing
    with pytest.raises(InvalidInputError, match="motion_axis"):
        tactile_movie(samples, fingertip=ft, window=win, calibration=CAL, image_shape=(400, 400), motion_axis=2)


def test_tactile_movie_resets_contactors_out_of_view():
    samples, ft, win = _movie_inputs([6.0, 0.0], n=6, size=400)
    # the 10 mm display (200 px here) fits; drag the window towards the edge by hand
    win2 = type(win)(win.x0, win.y0, win.x1, win.y1, win.centers + [130.0, 0.0])
    movie = tactile_movie(samples, fingertip=ft, window=win2, calibration=CAL, image_shape=(400, 400))
    assert movie.reset[1:, :, -1].all()  # right-hand column beyond the image
    assert not movie.reset[1:, :, 0].any()


def test_a_batch_gives_each_pair_what_triangulation_strain_gives():
    from skinstretch.processing.stretch import COLLINEAR, STRAIN_OK, TOO_FEW_POINTS, triangulation_strains

    rng = np.random.default_rng(3)
    good = [_sample(_points(60, seed=k), rng.normal(0, 0.5, (60, 2)), a=k, b=k + 1) for k in range(4)]
    line = np.column_stack([np.arange(10.0), 2 * np.arange(10.0)])
    samples = [good[0], _sample(line, np.zeros((10, 2)), a=7, b=8), good[1],
               _sample(np.zeros((0, 2)), np.zeros((0, 2)), a=9, b=10), good[2], good[3]]
    b = triangulation_strains(samples, max_edge_px=80.0)
    assert b.status.tolist() == [STRAIN_OK, COLLINEAR, STRAIN_OK, TOO_FEW_POINTS, STRAIN_OK, STRAIN_OK]
    assert b.failure(1) == "frames 7->8: the 10 matched points are collinear"
    assert b.failure(3) == "frames 9->10: 0 distinct matched points, need at least 3"
    for i, s in enumerate(samples):
        if b.status[i] != STRAIN_OK:
            continue
        one = triangulation_strain(s, max_edge_px=80.0)
        e = slice(b.edge_offsets[i], b.edge_offsets[i + 1])
        t = slice(b.triangle_offsets[i], b.triangle_offsets[i + 1])
        np.testing.assert_array_equal(b.ids[b.edges[e]], one.ids[one.edges])
        np.testing.assert_array_equal(b.points[b.triangles[t]], one.points[one.triangles])
        np.testing.assert_array_equal(b.edge_change[e], one.edge_change)
        np.testing.assert_array_equal(b.area_change[t], one.area_change)
        np.testing.assert_array_equal(b.flipped[t], one.flipped)
    with pytest.raises(InvalidInputError, match="disagree"):
        triangulation_strains([MotionSample(0, 1, np.zeros((3, 2)), np.zeros((2, 2)), np.arange(3))])

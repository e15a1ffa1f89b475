"""Feature tracking in chunks on worker processes gives exactly the sequential result (skinstretch.experiments.analysis_pool)."""

import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from skinstretch.experiments import analysis_pool
from skinstretch.experiments.analysis import AnalysisParams, analyze_frames
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import make_features
from skinstretch.processing.tracking import FeatureTracker, TrackingParams

scene = pytest.importorskip("skinstretch.simulators.scene")
ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("n, workers", [(32, 2), (40, 3), (180, 2), (1000, 2)])
def test_chunk_plan_covers_every_frame_with_the_overlap(n, workers):
    overlap = 5
    plan = analysis_pool.chunk_plan(n, workers=workers, overlap=overlap)
    assert plan[0][0] == 0 and plan[-1][1] == n - 1
    assert len(plan) >= workers
    for (_, last), (first, _) in zip(plan, plan[1:]):
        assert first == last - overlap
    sizes = [b - a + 1 for a, b in plan]
    assert min(sizes) >= 2 * overlap + 2
    assert max(sizes) - min(sizes) <= 2  # balanced, overlaps included
    assert max(sizes) <= analysis_pool.MAX_CHUNK_FRAMES + 1


def test_chunk_plan_declines_short_sequences_and_one_worker():
    assert analysis_pool.chunk_plan(analysis_pool.MIN_FRAMES - 1, workers=2, overlap=5) is None
    assert analysis_pool.chunk_plan(40, workers=2, overlap=20) is None  # chunks too short for their overlap
    assert analysis_pool.chunk_plan(500, workers=1, overlap=5) is None


def _moving_features(k, rng_seed=0):
    """A grid of features sliding 1.5 px per frame; a few vanish for 2 frames (re-linked) or for good."""
    rng = np.random.default_rng(rng_seed)
    gx, gy = np.meshgrid(np.arange(20.0, 300.0, 23.0), np.arange(20.0, 200.0, 21.0))
    x, y = gx.ravel() + 1.5 * k, gy.ravel() + 0.4 * k
    kind = rng.integers(0, 3, x.size)
    keep = np.ones(x.size, bool)
    keep[(np.arange(x.size) % 7 == k % 7)] = False  # each feature missing one frame in 7
    keep[5:9] = k < 25  # some end for good
    return make_features(x[keep], y[keep], kind[keep], frame=k)


def _tracker():
    return FeatureTracker(calibration=Calibration(px_per_mm=62.0),
                          params=TrackingParams(min_length_frames=3, max_gap_frames=3, smoothing_radius_frames=0))


def test_continue_with_gives_the_sequential_trajectories():
    n, b, overlap = 40, 22, 5
    seq = _tracker()
    for k in range(n):
        seq.add_frame(_moving_features(k))
    a, c = _tracker(), _tracker()
    for k in range(b + 1):
        a.add_frame(_moving_features(k))
    for k in range(b - overlap, n):
        c.add_frame(_moving_features(k))
    assert a.continue_with(c, overlap=overlap)
    ta, ts = a.finish(), seq.finish()
    for name in ("x", "y", "present", "feature_index", "linked", "kind"):
        np.testing.assert_array_equal(getattr(ta, name), getattr(ts, name), err_msg=name)


def test_continue_with_refuses_disagreeing_trackers_and_changes_nothing():
    b, overlap = 22, 5
    a, c = _tracker(), _tracker()
    for k in range(b + 1):
        a.add_frame(_moving_features(k))
    for k in range(b - overlap, 40):
        feats = _moving_features(k)
        c.add_frame(feats[1:] if k == b - 1 else feats)  # one feature missing in an overlapped frame
    before = (a.n_frames, len(a._frames), a._n_tracks)
    assert not a.continue_with(c, overlap=overlap)
    assert (a.n_frames, len(a._frames), a._n_tracks) == before
    with pytest.raises(InvalidInputError, match="overlap"):
        a.continue_with(c, overlap=2)  # shorter than max_gap_frames + 2


@pytest.fixture(scope="module")
def ridge_session():
    return scene.render_session("ridgeL", n_frames=40, seed=1)


def _params(workers, processes):
    p = AnalysisParams(workers=workers, processes=processes)
    return replace(p, tracking=replace(p.tracking, min_length_frames=5))


def _assert_same_results(a, b):
    for name in b.trajectories:
        np.testing.assert_array_equal(a.trajectories[name], b.trajectories[name], err_msg=name)
    for f in b.motion.dtype.names:
        np.testing.assert_array_equal(a.motion[f], b.motion[f], err_msg=f)
    for f in b.features.dtype.names:
        np.testing.assert_array_equal(a.features[f], b.features[f], err_msg=f)
    for span in b.strain:
        for table in ("pairs", "edges", "triangles"):
            np.testing.assert_array_equal(getattr(a.strain[span], table), getattr(b.strain[span], table))
    np.testing.assert_array_equal(a.tactile_positions_um, b.tactile_positions_um)


def test_processes_give_exactly_the_threads_result(ridge_session):
    s = ridge_session
    kw = dict(calibration=s.calibration, surface="ridge")
    threads = analyze_frames(s.frames, params=_params(3, False), **kw)
    procs = analyze_frames(s.frames, params=_params(3, True), **kw)
    assert threads.params["parallel"].startswith("threads")
    assert procs.params["parallel"].startswith("processes (3): 3 chunks")
    _assert_same_results(procs, threads)


def test_a_join_that_disagrees_is_tracked_here_with_the_same_result(ridge_session, monkeypatch):
    s = ridge_session
    kw = dict(calibration=s.calibration, surface="ridge")
    threads = analyze_frames(s.frames, params=_params(2, False), **kw)
    monkeypatch.setattr(FeatureTracker, "continue_with", lambda self, other, overlap: False)
    procs = analyze_frames(s.frames, params=_params(2, True), **kw)
    assert "1 re-tracked" in procs.params["parallel"]
    _assert_same_results(procs, threads)


def test_failed_worker_processes_fall_back_to_threads(ridge_session, monkeypatch):
    def fail(*args, **kwargs):
        raise analysis_pool.ProcessPoolFailed("could not start 2 worker processes: test")

    monkeypatch.setattr(analysis_pool, "track_in_processes", fail)
    s = ridge_session
    r = analyze_frames(s.frames, calibration=s.calibration, params=_params(2, True), surface="ridge")
    assert r.params["parallel"].startswith("threads (2): worker processes failed")
    assert r.trajectories["present"].any()


def test_a_script_without_a_main_guard_runs_once(tmp_path):
    """Workers never re-run the caller's script (it would analyse again in each of them)."""
    script = tmp_path / "lab_script.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from dataclasses import replace
        from skinstretch.experiments.analysis import AnalysisParams, analyze_frames
        from skinstretch.simulators.scene import render_session
        s = render_session("flatL", n_frames=32, seed=0)
        p = AnalysisParams(workers=2)
        p = replace(p, tracking=replace(p.tracking, min_length_frames=4))
        r = analyze_frames(s.frames, calibration=s.calibration, params=p)
        print("RAN", r.params["parallel"])
    """))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = [line for line in out.stdout.splitlines() if line.startswith("RAN")]
    assert len(lines) == 1 and "processes (2)" in lines[0], out.stdout + out.stderr[-2000:]


def test_a_worker_process_keeps_to_threads(monkeypatch):
    """The runner analyses trials in a worker process while recording: no nested pool there."""
    monkeypatch.setattr(analysis_pool.mp, "parent_process", lambda: object())
    assert analysis_pool.chunk_plan(500, workers=2, overlap=5) is None


def test_frame_blocks_are_reused_by_the_next_analysis_and_freed_at_shutdown(ridge_session):
    s = ridge_session
    kw = dict(calibration=s.calibration, surface="ridge", params=_params(2, True))
    analysis_pool.shutdown()
    first = analyze_frames(s.frames, **kw)
    kept = {b.name for b in analysis_pool._kept_blocks}
    assert len(kept) == 2  # one per chunk, written once
    again = analyze_frames(s.frames, **kw)
    assert {b.name for b in analysis_pool._kept_blocks} == kept  # the same blocks served the second analysis
    _assert_same_results(again, first)
    analysis_pool.shutdown()
    assert analysis_pool._kept_blocks == []
    for name in kept:  # unlinked: nothing left in /dev/shm
        with pytest.raises(FileNotFoundError):
            analysis_pool.shared_memory.SharedMemory(name=name)


def test_a_full_dev_shm_falls_back_to_threads_before_writing(ridge_session, monkeypatch):
    """Writing past a small /dev/shm (containers mount 64 MB) would kill the process with SIGBUS."""
    analysis_pool.shutdown()
    monkeypatch.setattr(analysis_pool, "_shm_room", lambda: 20 * 2**20)
    s = ridge_session
    r = analyze_frames(s.frames, calibration=s.calibration, params=_params(2, True), surface="ridge")
    assert r.params["parallel"].startswith("threads (2): worker processes failed (/dev/shm has 20 MB free")
    assert r.trajectories["present"].any()
    assert analysis_pool._kept_blocks == []


def test_a_worker_that_cannot_open_its_frames_falls_back_to_threads(ridge_session, monkeypatch):
    """An OS error in a worker (its frame block gone) is the pool's failure, not the analysis': threads take over."""
    real = analysis_pool._take_block

    def gone(nbytes):
        block = real(nbytes)
        block.unlink()  # the worker will not find it by name
        return block

    monkeypatch.setattr(analysis_pool, "_take_block", gone)
    s = ridge_session
    r = analyze_frames(s.frames, calibration=s.calibration, params=_params(2, True), surface="ridge")
    assert r.params["parallel"].startswith("threads (2): worker processes failed (a worker process could not track")
    assert r.trajectories["present"].any()
    analysis_pool.shutdown()

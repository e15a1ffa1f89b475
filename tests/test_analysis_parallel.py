"""The analysis in chunks on any executor gives exactly the sequential result; worker processes die with their
parent, whatever kills it (skinstretch.experiments.analysis.measure, .executor)."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import numpy as np
import psutil
import pytest

from skinstretch.experiments.analysis import analysis_params, analyze_frames, make_executor
from skinstretch.experiments.analysis import executor as executor_module
from skinstretch.experiments.analysis.executor import InlineExecutor, WorkerProcesses
from skinstretch.experiments.analysis.measure import MAX_CHUNK_FRAMES, MIN_FRAMES, chunk_plan
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.tracking import FeatureTracker, TrackingParams
from tests.helpers import sliding_feature_grid

scene = pytest.importorskip("skinstretch.simulators.scene")
ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("n, width", [(32, 2), (40, 3), (180, 2), (1000, 2)])
def test_chunk_plan_covers_every_frame_with_the_overlap(n, width):
    overlap = 5
    plan = chunk_plan(n, width=width, overlap=overlap)
    assert plan[0][0] == 0 and plan[-1][1] == n - 1
    assert len(plan) >= width
    for (_, last), (first, _) in zip(plan, plan[1:]):
        assert first == last - overlap
    sizes = [b - a + 1 for a, b in plan]
    assert min(sizes) >= 2 * overlap + 2
    assert max(sizes) - min(sizes) <= 2  # balanced, overlaps included
    assert max(sizes) <= MAX_CHUNK_FRAMES + 1


def test_chunk_plan_keeps_short_sequences_whole():
    assert chunk_plan(MIN_FRAMES - 1, width=2, overlap=5) == [(0, MIN_FRAMES - 2)]
    assert chunk_plan(40, width=2, overlap=20) == [(0, 39)]  # chunks too short for their overlap
    assert len(chunk_plan(500, width=1, overlap=5)) == 3  # bounded chunks even on one worker


def _tracker(smoothing=0):
    return FeatureTracker(calibration=Calibration(px_per_mm=62.0),
                          params=TrackingParams(min_length_frames=3, smoothing_radius_frames=smoothing))


def test_continue_with_gives_the_sequential_trajectories():
    n, b, overlap = 40, 22, 5
    seq = _tracker()
    for k in range(n):
        seq.add_frame(sliding_feature_grid(k))
    a, c = _tracker(), _tracker()
    for k in range(b + 1):
        a.add_frame(sliding_feature_grid(k))
    for k in range(b - overlap, n):
        c.add_frame(sliding_feature_grid(k))
    assert a.continue_with(c, overlap=overlap)
    ta, ts = a.finish(), seq.finish(release=True)
    for name in ts.rows.dtype.names:
        np.testing.assert_array_equal(ta.rows[name], ts.rows[name], err_msg=name)
    with pytest.raises(InvalidInputError, match="released"):
        seq.add_frame(sliding_feature_grid(n))


def test_continue_with_refuses_disagreeing_trackers_and_changes_nothing():
    b, overlap = 22, 5
    a, c = _tracker(), _tracker()
    for k in range(b + 1):
        a.add_frame(sliding_feature_grid(k))
    for k in range(b - overlap, 40):
        feats = sliding_feature_grid(k)
        c.add_frame(feats[1:] if k == b - 1 else feats)  # one feature missing in an overlapped frame
    before = (a.n_frames, len(a._frames), a._n_tracks)
    assert not a.continue_with(c, overlap=overlap)
    assert (a.n_frames, len(a._frames), a._n_tracks) == before
    with pytest.raises(InvalidInputError, match="overlap"):
        a.continue_with(c, overlap=1)  # shorter than join_overlap_frames


def test_the_long_trajectory_table_has_the_dense_smoothing_to_the_bit():
    """Chaining and smoothing per track (the long table) give the numbers of smooth_positions on dense arrays."""
    from skinstretch.processing.tracking import smooth_positions

    t0, t1 = _tracker(smoothing=0), _tracker(smoothing=2)
    for k in range(40):
        t0.add_frame(sliding_feature_grid(k))
        t1.add_frame(sliding_feature_grid(k))
    d0, d1 = t0.finish().dense(), t1.finish().dense()
    pos = np.stack([d0.x, d0.y], axis=-1)
    dense = smooth_positions(pos, d0.present, d0.linked, radius_frames=2, sigma_frames=1.0)
    np.testing.assert_array_equal(np.stack([d1.x, d1.y], axis=-1), dense)


@pytest.fixture(scope="module")
def ridge_session():
    return scene.render_session("ridgeL", n_frames=40, seed=1)


def _params(kind, workers=2, **tracking):
    return analysis_params({"tracking": {"min_length_frames": 5, **tracking},
                            "execution": {"kind": kind, "workers": workers}})


def _assert_same_results(a, b):
    for name in b.trajectories.rows.dtype.names:
        np.testing.assert_array_equal(a.trajectories.rows[name], b.trajectories.rows[name], err_msg=name)
    for f in b.motion.dtype.names:
        np.testing.assert_array_equal(a.motion[f], b.motion[f], err_msg=f)
    for f in b.features.dtype.names:
        np.testing.assert_array_equal(a.features[f], b.features[f], err_msg=f)
    for span in b.strain:
        for table in ("pairs", "edges", "triangles"):
            np.testing.assert_array_equal(getattr(a.strain[span], table), getattr(b.strain[span], table))
    np.testing.assert_array_equal(a.movie.positions_um, b.movie.positions_um)


@pytest.mark.parametrize("method", ["features", "flow"])
def test_processes_threads_and_serial_give_the_same_results(ridge_session, method):
    s = ridge_session
    kw = dict(calibration=s.calibration, surface="ridge", method=method)
    serial = analyze_frames(s.frames, params=_params("serial"), **kw)
    threads = analyze_frames(s.frames, params=_params("threads", 3), **kw)
    procs = analyze_frames(s.frames, params=_params("processes", 2), **kw)
    assert serial.params["parallel"].startswith("serial: 1 chunk")
    if method == "features":  # points bridged without end (the default): the workers extract, this process tracks
        assert threads.params["parallel"].startswith("threads (3): features extracted in 2 chunks, tracked in this")
        assert procs.params["parallel"].startswith("processes (2): features extracted in 2 chunks, tracked in this")
    else:
        assert threads.params["parallel"].startswith("threads (3): 3 chunks")
        assert procs.params["parallel"].startswith("processes (2): 2 chunks")
    if method == "features":
        _assert_same_results(procs, serial)
        _assert_same_results(threads, serial)
    else:
        np.testing.assert_array_equal(procs.flow.displacement, serial.flow.displacement)
        np.testing.assert_array_equal(threads.motion, serial.motion)


def test_chunks_tracked_apart_join_when_bridging_is_bounded(ridge_session):
    s = ridge_session
    kw = dict(calibration=s.calibration, surface="ridge")
    serial = analyze_frames(s.frames, params=_params("serial", max_bridge_frames=2), **kw)
    threads = analyze_frames(s.frames, params=_params("threads", 3, max_bridge_frames=2), **kw)
    assert threads.params["parallel"].startswith("threads (3): 3 chunks")
    _assert_same_results(threads, serial)


def test_a_join_that_disagrees_is_tracked_here_with_the_same_result(ridge_session, monkeypatch):
    s = ridge_session
    kw = dict(calibration=s.calibration, surface="ridge")
    serial = analyze_frames(s.frames, params=_params("serial", max_bridge_frames=2), **kw)
    monkeypatch.setattr(FeatureTracker, "continue_with", lambda self, other, overlap: False)
    threads = analyze_frames(s.frames, params=_params("threads", max_bridge_frames=2), **kw)
    assert "1 re-tracked" in threads.params["parallel"]
    _assert_same_results(threads, serial)


class _DeadWorkers(ThreadPoolExecutor):
    """An executor whose workers have died."""

    def submit(self, fn, /, *args, **kwargs):
        f = Future()
        f.set_exception(BrokenProcessPool("a worker died"))
        return f


def test_dead_worker_processes_leave_the_analysis_to_this_process(ridge_session, caplog):
    s = ridge_session
    serial = analyze_frames(s.frames, calibration=s.calibration, params=_params("serial"), surface="ridge")
    with _DeadWorkers(2) as dead, caplog.at_level("WARNING"):
        r = analyze_frames(s.frames, calibration=s.calibration, params=_params("threads"), surface="ridge",
                           executor=dead)
    assert "carries on in this process" in caplog.text
    _assert_same_results(r, serial)


def test_a_worker_process_keeps_to_threads(monkeypatch):
    """The recorder analyses trials in a worker process, Dask in its workers: no nested pool there."""
    monkeypatch.setattr(executor_module.mp, "parent_process", lambda: object())
    with make_executor(_params("processes").execution) as ex:
        assert isinstance(ex, ThreadPoolExecutor)
    assert isinstance(make_executor(_params("serial").execution), InlineExecutor)


def test_a_script_without_a_main_guard_runs_once(tmp_path):
    """Workers never re-run the caller's script (it would analyse again in each of them)."""
    script = tmp_path / "lab_script.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from skinstretch.experiments.analysis import analysis_params, analyze_frames
        from skinstretch.simulators.scene import render_session
        s = render_session("flatL", n_frames=32, seed=0)
        p = analysis_params({{"tracking": {{"min_length_frames": 4}}}})
        r = analyze_frames(s.frames, calibration=s.calibration, params=p)
        print("RAN", r.params["parallel"])
    """))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = [line for line in out.stdout.splitlines() if line.startswith("RAN")]
    assert len(lines) == 1 and "processes (2)" in lines[0], out.stdout + out.stderr[-2000:]


def test_worker_processes_die_with_a_sigkilled_parent(tmp_path):
    """SIGKILL of the analysing process: its workers (and their forkserver) are gone within 2 s."""
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(ROOT)!r})
        from skinstretch.experiments.analysis.executor import WorkerProcesses
        ex = WorkerProcesses(2)
        ex.submit(int, 0).result()
        print(" ".join(map(str, ex.pids())), flush=True)
        time.sleep(600)
    """))
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                              text=True, cwd=tmp_path)
    try:
        pids = [int(p) for p in parent.stdout.readline().split()]
        assert len(pids) == 2 and all(psutil.pid_exists(p) for p in pids)
        tree = [p.pid for p in psutil.Process(parent.pid).children(recursive=True)]
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(timeout=10)
        killed = time.monotonic()
        while time.monotonic() - killed < 2.0 and any(_alive(p) for p in tree):
            time.sleep(0.05)
        assert not [p for p in tree if _alive(p)], "processes outlived their SIGKILLed parent by 2 s"
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait(timeout=10)
        parent.stdout.close()


def _alive(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def test_worker_processes_start_on_first_use_and_stop_at_shutdown():
    ex = WorkerProcesses(2)
    assert ex.pids() == []
    assert ex.submit(os.getpid).result() != os.getpid()
    pids = ex.pids()
    ex.shutdown()
    assert len(pids) == 2 and not [p for p in pids if _alive(p)]

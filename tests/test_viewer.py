"""The session viewer without a browser: what it reads from results (the adapter), what it serves and refuses
(token, path traversal, other files, foreign hosts), and the live analysis against the simulator's truth."""

from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinstretch.drivers.errors import SessionFileError
from skinstretch.drivers.session_file import SessionWriter, write_session
from skinstretch.experiments.results_file import read_results
from skinstretch.experiments.viewer.live_analysis import LiveAnalyzer, _SyntheticPrint, warm_up
from skinstretch.experiments.viewer.live_check import live_accuracy
from skinstretch.experiments.viewer.server import TOKEN_COOKIE, ViewerState, create_app
from skinstretch.experiments.viewer.session_data import (
    SessionSource,
    ViewTarget,
    empty_overlays,
    find_view_target,
    load_results_index,
    nice_scale,
)

TOKEN = "test-token-0123456789"


@pytest.fixture(scope="module")
def analysed(tmp_path_factory, sim_session):
    """A 20-frame flatL session in the runner's layout (trial/session.h5 + trial/analysis/results.h5)."""
    from skinstretch.experiments.analysis import AnalysisParams, analyze_session
    from skinstretch.processing.tracking import TrackingParams

    root = tmp_path_factory.mktemp("viewer")
    trial = root / "subject" / "sess" / "000-flat-r1"
    trial.mkdir(parents=True)
    s = sim_session
    path = write_session(trial / "session.h5", s.frames, timestamps=s.timestamps, camera_mode=s.camera_mode,
                         calibration=s.calibration, metadata=s.metadata, truth=s.truth)
    results = analyze_session(path, trial / "analysis", params=AnalysisParams(
        execution={"kind": "threads"}, strain={"spans": (1, 5)},
        tracking=TrackingParams(smoothing_radius_frames=0, min_length_frames=10))).path
    other = write_session(root / "other.h5", 255 - s.frames[:3], timestamps=s.timestamps[:3],
                          camera_mode=s.camera_mode, calibration=s.calibration)  # frames unlike this session's
    return root, trial, path, results, other


def test_view_target_from_every_kind_of_path(analysed):
    root, trial, session, results, _ = analysed
    for given_path in (session, results, results.parent, trial):
        t = find_view_target(given_path)
        assert (t.session.resolve(), t.results.resolve(), t.directory) == (session.resolve(), results.resolve(), None)
    t = find_view_target(root)
    assert t.follows_directory and t.session is None
    (root / "notes.h5").write_bytes(b"not hdf5 at all")
    with pytest.raises(SessionFileError, match="notes.h5"):
        find_view_target(root / "notes.h5")
    with pytest.raises(SessionFileError, match="no such"):
        find_view_target(root / "missing")


def test_overlays_are_the_results_of_that_frame(analysed):
    _, _, session, results_path, _ = analysed
    r = read_results(results_path)
    idx = load_results_index(results_path)
    tr = vars(r.trajectories.dense())
    for k in (0, 1, 7, 19):
        for span in (1, 5):
            ov = idx.overlays(k, span=span)
            rows = r.features["frame"] == k
            assert sorted(ov.features.id.tolist()) == sorted(r.features["id"][rows].tolist())
            tracked = ov.features.track >= 0
            assert tracked.sum() > 0.5 * tracked.size
            # A feature's track passes through it: the track's extracted position in frame k is the feature's.
            np.testing.assert_allclose(tr["raw_x"][k, ov.features.track[tracked]], ov.features.x[tracked])
            motion = r.motion[r.motion["pair"] == k - 1] if k else r.motion[:0]
            assert ov.arrows.shape[0] == motion.size
            np.testing.assert_allclose(ov.arrows[:, 2:], np.column_stack([motion["dx"], motion["dy"]]))
            s = r.strain[span]
            tris = s.triangles[s.triangles["pair"] == k - span] if k >= span else s.triangles[:0]
            if tris.size:
                assert ov.mesh is not None and ov.mesh.drawn_at == "frame_b"
                np.testing.assert_array_equal(ov.mesh.change, tris["change"])
                # Vertices drawn where their tracks are in frame k.
                np.testing.assert_allclose(ov.mesh.xy[:, 0], tr["x"][k, tris["id_a"]])
                np.testing.assert_allclose(ov.mesh.xy[:, 5], tr["y"][k, tris["id_c"]])
            else:
                assert ov.mesh is None and ov.notes
    assert idx.overlays(19, span=1).tactile_um.shape == (10, 10)
    json.dumps(idx.overlays(3).to_json(), allow_nan=False)  # JSON-able, no NaN


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-0.5, 0.5, allow_nan=False), min_size=1, max_size=200))
def test_strain_colour_scale_is_round_and_covers_the_data(values):
    scale = nice_scale(np.asarray(values))
    top = max(float(np.percentile(np.abs(values), 98)), 0.001)
    mantissa = scale / 10 ** np.floor(np.log10(scale) + 1e-12)
    assert min(abs(mantissa - m) for m in (1, 2, 5, 10)) < 1e-6
    assert top <= scale * (1 + 1e-9) <= 2.5 * top + 1e-12


@pytest.fixture()
def client(analysed):
    from starlette.testclient import TestClient

    _, trial, _, _, _ = analysed
    state = ViewerState(find_view_target(trial))
    app = create_app(state, token=TOKEN, allowed_hosts=["127.0.0.1", "localhost", "testserver"])
    with TestClient(app, base_url="http://127.0.0.1") as c:
        yield c


def test_every_route_needs_the_token(client):
    for url in ("/", "/api/info", "/static/viewer.js", "/api/s/1/frame/0.bmp", "/api/s/1/overlay/0", "/api/events"):
        assert client.get(url).status_code == 403, url
        assert client.get(url + ("&" if "?" in url else "?") + "token=wrong").status_code == 403, url
    page = client.get(f"/?token={TOKEN}")
    assert page.status_code == 200 and "skinstretch viewer" in page.text
    assert page.cookies.get(TOKEN_COOKIE) == TOKEN
    assert client.get("/static/viewer.js").status_code == 200  # the page's cookie carries the token


def test_serves_this_sessions_frames_losslessly(client, sim_session):
    info = client.get(f"/api/info?token={TOKEN}").json()
    assert info["n_frames"] == 20 and info["has_truth"] and info["results"]["method"] == "features"
    image = client.get(f"/api/s/{info['sid']}/frame/7.bmp?token={TOKEN}")
    assert image.status_code == 200 and image.headers["content-type"] == "image/bmp"
    # Compared with the frames written (a second handle on a file this process holds open in SWMR mode reads
    # wrong chunks with this HDF5: the viewer opens each session once).
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(image.content, np.uint8), cv2.IMREAD_UNCHANGED),
                                  sim_session.frames[7])
    ov = client.get(f"/api/s/{info['sid']}/overlay/7?span=5&token={TOKEN}").json()
    assert ov["source"] == "results" and ov["mesh"]["span"] == 5 and ov["truth"] is not None
    assert client.get(f"/api/s/{info['sid']}/frame/20.bmp?token={TOKEN}").status_code == 404
    assert client.get(f"/api/s/{info['sid'] + 1}/frame/0.bmp?token={TOKEN}").status_code == 404


@pytest.mark.parametrize("url", [
    "/static/../session.h5", "/static/%2e%2e/%2e%2e/session.h5", "/static/..%2f..%2fsession.h5",
    "/static//etc/passwd", "/static/%2fetc%2fpasswd", "/api/s/1/frame/..%2f..%2fsession.h5",
    "/session.h5", "/analysis/results.h5", "/api/s/1/frame/-1.bmp", "/api/s/1/overlay/../../other.h5",
])
def test_path_traversal_and_other_files_are_refused(client, url):
    r = client.get(url + ("&" if "?" in url else "?") + f"token={TOKEN}")
    assert r.status_code in (400, 404), (url, r.status_code)
    assert b"HDF" not in r.content and b"root:" not in r.content


def test_other_sessions_cannot_be_asked_for(client, analysed, sim_session):
    _, _, _, _, other = analysed
    # No route takes a path: a path in the query is ignored and this session's data come back.
    info = client.get(f"/api/info?token={TOKEN}&path={other}&session={other}").json()
    assert info["n_frames"] == 20 and info["path_name"] == "session.h5"
    for query in (f"session={other}", f"path={other}", f"file={other}"):
        r = client.get(f"/api/s/{info['sid']}/frame/0.bmp?token={TOKEN}&{query}")
        assert r.status_code == 200
        frame = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(frame, sim_session.frames[0])  # this session's frame, not the other's


def _raw_get(port: int, target: str, host: str = "127.0.0.1") -> tuple[int, bytes]:
    """GET ``target`` byte for byte (an HTTP client library would resolve ``..`` before sending it)."""
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.sendall(f"GET {target} HTTP/1.1\r\nHost: {host}:{port}\r\nConnection: close\r\n\r\n".encode())
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    return int(data.split(b" ", 2)[1]), data


def test_a_real_server_binds_loopback_and_refuses_traversal_to_files_that_exist(analysed):
    """Against the served app over a socket, with the ``..`` segments sent as they are: files that do exist beside
    the page's static folder (the server's source) and beside the session are not served."""
    from skinstretch.experiments.viewer.server import start_server

    _, trial, _, _, _ = analysed
    running = start_server(find_view_target(trial))
    try:
        assert running._server.servers[0].sockets[0].getsockname()[0] == "127.0.0.1"
        token = f"token={running.token}"
        assert _raw_get(running.port, f"/static/viewer.js?{token}")[0] == 200  # the harness reaches files
        assert _raw_get(running.port, "/static/viewer.js")[0] == 403
        for target in ("/static/../server.py", "/static/%2e%2e/server.py", "/static/..%2fserver.py",
                       "/static/%2e%2e%2fserver.py", "/static/..%5cserver.py", "/static/../../viewer/server.py",
                       "/static/../../../../../../etc/passwd", "/../session.h5", "/static/../../../session.h5",
                       "/api/s/1/frame/..%2f..%2fsession.h5", "/api/s/1/overlay/..%2f..%2fanalysis%2fresults.h5"):
            status, body = _raw_get(running.port, f"{target}?{token}")
            assert status in (400, 404), (target, status)
            assert b"import " not in body and b"root:" not in body and b"HDF" not in body, target
    finally:
        running.stop()


def test_a_port_in_use_gets_one_line_naming_the_flag(analysed, capsys):
    from skinstretch.cli import main
    from skinstretch.experiments.viewer.server import start_server

    _, trial, _, _, _ = analysed
    running = start_server(find_view_target(trial))
    capsys.readouterr()  # the first server's own start-up line (logged when an earlier test left the CLI's handler)
    try:
        assert main(["view", str(trial), "--port", str(running.port), "--no-browser"]) == 2
    finally:
        running.stop()
    assert capsys.readouterr().err.splitlines() == [
        f"skinstretch view: error: port {running.port} on 127.0.0.1 is in use; pass --port to choose another "
        "(0: any free port)"]


def test_foreign_host_header_is_refused(client):
    r = client.get(f"/api/info?token={TOKEN}", headers={"host": "attacker.example"})
    assert r.status_code == 400


def test_live_analysis_of_a_recording_matches_the_truth(tmp_path, sim_session):
    """A session written frame by frame in SWMR mode: the live analysis reads it as it grows and measures the
    motion and strain of every second frame within 0.1 px and 0.5 % of the truth."""
    s = sim_session
    path = tmp_path / "live.h5"
    writer = SessionWriter(path, camera_mode=s.camera_mode, calibration=s.calibration)
    source = None
    overlays = []
    try:
        for k in range(s.frames.shape[0]):
            writer.append_frame(s.frames[k], timestamp=float(s.timestamps[k]), frame_id=k)
            writer.flush()
            if source is None:
                source = SessionSource(path)
                analyzer = LiveAnalyzer(source)
                assert source.status() == "recording"
            assert source.n_frames() == k + 1
            if k % 2 == 0:
                overlays.append(analyzer.analyse_frame(k))
    finally:
        writer.close()
    assert source.status() == "complete"
    source.close()
    assert overlays[0].mesh is None and all(o.mesh is not None for o in overlays[1:])
    acc = live_accuracy([o.to_json() for o in overlays], s.truth, np.arange(s.frames.shape[0]),
                        px_per_mm=s.calibration.px_per_mm)
    assert acc.pairs == len(overlays) - 1 and acc.displacements > 100 * acc.pairs
    assert acc.displacement_rmse_px < 0.1
    assert acc.area_change_rmse < 0.005
    assert all(o.tails for o in overlays[2:])


def test_the_live_event_names_the_frame_and_its_overlays_are_fetched(tmp_path, sim_session):
    """Each live event is the analysed frame's index and times (the page draws fewer frames than are analysed
    and fetches the overlays of those it draws); the overlay route serves them as the live analysis' own."""
    s = sim_session
    path = tmp_path / "live.h5"
    writer = SessionWriter(path, camera_mode=s.camera_mode, calibration=s.calibration)
    state = None
    try:
        for k in range(4):
            writer.append_frame(s.frames[k], timestamp=float(s.timestamps[k]), frame_id=k)
        writer.flush()
        state = ViewerState(ViewTarget(path, None, None))
        assert state.analyzer is not None
        deadline = time.monotonic() + 60
        while state.analyzer.stats().analysed == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        version, event = state.live_update(-1)
        assert event is not None and state.live_update(version) == (version, None)
        ev = json.loads(event)
        assert set(ev) == {"frame", "exposure_time", "analysed_time"} and len(event) < 200
        assert ev["exposure_time"] == pytest.approx(float(s.timestamps[ev["frame"]]))
        ov = json.loads(state.overlays(state.sid, ev["frame"], 1))
        assert ov["source"] == "live" and ov["frame"] == ev["frame"] and len(ov["features"]["x"]) > 10
        assert state.snapshot()["live"] is True
    finally:
        if state is not None:
            state.close()
        writer.close()


def test_the_live_analysis_takes_frames_in_order_unless_it_falls_behind():
    """Frames appear a few at a time (at each of the recorder's flushes): analysed in order while within
    MAX_LAG_FRAMES of the newest, so none is skipped that there is time for; beyond, the newest."""
    from skinstretch.experiments.viewer.live_analysis import MAX_LAG_FRAMES, _next_frame

    assert _next_frame(-1, 40) == 40  # attached late: the newest first
    assert _next_frame(10, 10) is None and _next_frame(10, 9) is None
    assert _next_frame(10, 11) == 11 and _next_frame(10, 12) == 11
    assert _next_frame(10, 11 + MAX_LAG_FRAMES) == 11
    assert _next_frame(10, 12 + MAX_LAG_FRAMES) == 12 + MAX_LAG_FRAMES


def test_tails_are_rounded_at_once_as_one_by_one():
    """The page's JSON of many polylines: rounded together, the same as each on its own (NaN as 0)."""
    rng = np.random.default_rng(3)
    tails = [rng.uniform(0, 500, (int(n), 2)) for n in rng.integers(2, 13, 300)]
    tails[5][1, 0] = np.nan
    ov = empty_overlays(0, "test")
    ov.tails = tails
    got = ov.to_json()["tails"]
    want = [np.where(np.isfinite(t), np.round(t, 1), 0.0).tolist() for t in tails]
    assert got == want


def test_the_warm_up_runs_the_whole_live_analysis_on_a_made_up_print():
    """The warm-up (loading the compiled kernels before a recording's first frame) goes through extraction,
    matching, refinement and the strain mesh, and the flat glass around its contact leaves no NaN."""
    analyzer = LiveAnalyzer(_SyntheticPrint())
    first, second = analyzer.analyse_frame(0), analyzer.analyse_frame(1)
    assert len(first.features.x) >= 10 and first.mesh is None
    assert second.mesh is not None and len(second.mesh.change) >= 10
    assert np.isfinite(second.mesh.change).all() and np.isfinite(second.arrows).all()
    assert warm_up(frames=2) > 0


def test_state_follows_the_newest_trial_and_picks_up_results(tmp_path, analysed, sim_session):
    root, trial, session, results, _ = analysed
    data = tmp_path / "data"
    first = data / "a"
    first.mkdir(parents=True)
    state = ViewerState(ViewTarget(None, None, data))
    try:
        assert state.source is None and "waiting" in state.info()
        s = sim_session
        write_session(first / "session.h5", s.frames[:4], timestamps=s.timestamps[:4], camera_mode=s.camera_mode,
                      calibration=s.calibration)
        state.update()
        assert state.info()["n_frames"] == 4 and state.results is None
        assert "no analysis results" in json.loads(state.overlays(state.sid, 0, 1))["notes"][0]
        (first / "analysis").mkdir()
        (first / "analysis" / "results.h5").write_bytes(results.read_bytes())
        state.update()
        assert state.results is not None
    finally:
        state.close()


def test_view_command_refuses_a_bad_target(tmp_path, capsys):
    from skinstretch.cli import main

    assert main(["view", str(tmp_path / "nothing.h5"), "--no-browser"]) == 2
    assert "no such file" in capsys.readouterr().err

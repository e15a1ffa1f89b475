"""The viewer's web server: a small Starlette app served by uvicorn, with server-sent events (sse-starlette) for
a session that is still being recorded.

Privacy: subject data never leave the machine unless asked. The server binds 127.0.0.1 unless ``host`` says
otherwise, and every request must carry the random token of this run (``?token=`` in the URL the command prints;
the page then keeps it in a same-site cookie), so another user of the machine, or a web page in the browser, cannot
read the session. Routes take frame numbers, never paths: the server serves this session's frames and results
and the page's own files, nothing else. Requests for another Host than the bound one are refused (DNS rebinding).

Routes (``sid`` numbers the session shown: it changes when a followed data directory starts a new trial)::

    GET /                                 the page
    GET /static/...                       its script and style sheet
    GET /api/info                         what is shown: size, frames, status, results, live analysis
    GET /api/s/{sid}/frame/{k}.bmp        frame k (lossless BMP)
    GET /api/s/{sid}/overlay/{k}?span=s   frame k's overlays (JSON, see session_data.FrameOverlays)
    GET /api/events                       server-sent events: "state" on a change, "live" per analysed frame (index)
    GET /api/s/{sid}/gauge?frame=k&x=&y=[&x2=&y2=][&radius_mm=]
                                          a virtual gauge (extensometer) placed on frame k: JSON of every frame
    GET /api/s/{sid}/gauge.csv?...        the same as CSV (what skinstretch probe writes)
    GET /study                            the study overview page (a data directory)
    GET /api/study                        its trials (JSON, see skinstretch.experiments.study)
    POST /api/study/open/{i}              show trial i (no longer following the newest)
    POST /api/study/follow                follow the newest trial again
"""

from __future__ import annotations

import errno
import json
import logging
import os
import secrets
import socket
import threading
import time
import webbrowser
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import anyio
import cv2
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import HTTPConnection, Request
from starlette.responses import FileResponse, JSONResponse, PlainTextResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Receive, Scope, Send

from skinstretch.drivers.errors import SessionFileError
from skinstretch.experiments.viewer.live_analysis import LiveAnalyzer, warm_up
from skinstretch.experiments.viewer.session_data import (
    ResultsIndex,
    SessionSource,
    ViewTarget,
    _results_beside,
    empty_overlays,
    load_results_index,
    newest_trial_session,
)
from skinstretch.processing.errors import InvalidInputError, Remedy, SkinstretchError
from skinstretch.processing.feature_table import KIND_NAMES

log = logging.getLogger(__name__)

__all__ = ["ViewerState", "create_app", "RunningServer", "start_server", "serve"]

STATIC_DIR = Path(__file__).parent / "static"
TOKEN_COOKIE = "skinstretch_viewer_token"
WATCH_INTERVAL_S = 0.2  # how often the state looks for new frames, results and trials
EVENT_INTERVAL_S = 0.01  # how often the event stream looks for changes


class ViewerState:
    """The session shown (and the results or live analysis of it); followed as it is recorded.

    Parameters
    ----------
    target : ViewTarget
        A session (with results if any) or a data directory whose newest trial is followed.
    live : bool
        Run the live analysis on a session that is still being recorded.
    """

    def __init__(self, target: ViewTarget, *, live: bool = True) -> None:
        self.target = target
        self.live = bool(live)
        self._lock = threading.RLock()
        self.sid = 0
        self.source: SessionSource | None = None
        self.results: ResultsIndex | None = None
        self.analyzer: LiveAnalyzer | None = None
        self._status = "waiting"
        self._n_frames = 0
        self._results_error = ""
        self._chosen: Path | None = None  # a trial opened from the study overview (then not following the newest)
        if target.session is not None:
            self._switch(target.session, target.results)
        self.update()
        if live and (target.directory is not None or self._status == "recording"):
            # The live analysis runs two threads of its own on a machine the recorder and the browser share: OpenCV
            # spreading each call over more threads only adds contention (interleaved live runs, tuning log).
            cv2.setNumThreads(1)
            # The live analysis' kernels load while the recorder starts, not on its first frames.
            threading.Thread(target=_warm_up_live, name="live-warm-up", daemon=True).start()

    # -- following
    def _switch(self, session: Path, results: Path | None) -> None:
        with self._lock:
            self._close_current()
            self.source = SessionSource(session)
            self.sid += 1
            self._results_error = ""
            self.results = self._load_results(results)
            log.info("viewer: showing %s", session)

    def _load_results(self, path: Path | None) -> ResultsIndex | None:
        if path is None:
            return None
        try:
            return load_results_index(path)
        except SessionFileError as exc:
            self._results_error = str(exc)
            log.warning("viewer: results not shown: %s", exc)
            return None

    def update(self) -> None:
        """Look for a newer trial (data directory), new frames, the end of the recording and new results."""
        with self._lock:
            if self.target.directory is not None and self._chosen is None:
                newest = newest_trial_session(self.target.directory)
                if newest is not None and (self.source is None or newest.resolve() != self.source.path.resolve()):
                    try:
                        self._switch(newest, _results_beside(newest))
                    except SessionFileError as exc:  # created but not yet readable: try again next round
                        log.debug("viewer: %s not readable yet (%s)", newest, exc)
            if self.source is None:
                return
            self._n_frames = self.source.n_frames()
            status = self.source.status()
            if status == "recording" and self.results is None and self.live and self.analyzer is None:
                self.analyzer = LiveAnalyzer(self.source).start()
            if status != "recording" and self.source.reopen_if_changed():  # closed, then its truth attached
                status = self.source.status()
            self._status = status
            if self.results is None and not self._results_error:
                found = _results_beside(self.source.path)
                if found is not None and status != "recording":
                    self.results = self._load_results(found)

    def _close_current(self) -> None:
        if self.analyzer is not None:
            self.analyzer.stop()
            self.analyzer = None
        if self.source is not None:
            self.source.close()
            self.source = None

    def close(self) -> None:
        with self._lock:
            self._close_current()

    # -- what the page asks for
    def snapshot(self) -> dict[str, Any]:
        """Small state compared by the event stream: any change is sent to the page (and redraws part of it: the
        live rate in whole frames/s, not the frame analysed, which has an event of its own)."""
        with self._lock:
            live = self.analyzer.stats() if self.analyzer is not None else None
            return {
                "sid": self.sid,
                "n_frames": self._n_frames,
                "status": self._status,
                "has_results": self.results is not None,
                "live": bool(live and live.last_frame >= 0),
                "live_fps": round(live.frames_per_s) if live else 0,
                "live_error": live.error if live else "",
            }

    def info(self) -> dict[str, Any]:
        with self._lock:
            base: dict[str, Any] = {
                "sid": self.sid,
                "follows_directory": self.target.follows_directory and self._chosen is None,
                "study_available": self.target.follows_directory,
                "kinds": {str(k): v.replace("_", " ") for k, v in KIND_NAMES.items()},
                "results_error": self._results_error,
                **self.snapshot(),
            }
            if self.source is None:
                return {**base, "waiting": "no trial recorded in this directory yet"}
            truth = self.source.truth() if self._status != "recording" else None
            return {
                **base,
                **self.source.describe(),
                "has_truth": truth is not None,
                "results": self.results.describe() if self.results is not None else None,
                "live": self.analyzer is not None,
            }

    def frame_image(self, sid: int, k: int) -> bytes | None:
        """Frame ``k`` as a BMP file: lossless and ~60x cheaper to encode than PNG (0.2 against 14 ms for 640x484),
        which the live view pays on every update; the larger file costs nothing on the local loopback."""
        with self._lock:
            if sid != self.sid or self.source is None or not 0 <= k < self.source.n_frames():
                return None
            image = self.source.frame(k)
        ok, buf = cv2.imencode(".bmp", image)
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
            raise InvalidInputError(f"frame {k} could not be encoded")
        return buf.tobytes()

    def overlays(self, sid: int, k: int, span: int) -> bytes | None:
        """Frame ``k``'s overlays as the page's JSON (bytes), None when there is no such frame."""
        with self._lock:
            if sid != self.sid or self.source is None or not 0 <= k < self.source.n_frames():
                return None
            if self.results is not None:
                return self.results.overlays(k, span=span, truth=self.source.truth()).to_json_bytes()
            if self.analyzer is not None:
                ov = self.analyzer.overlays(k)
                if ov is not None:
                    return ov.to_json_bytes()
                note = "not analysed live: the live analysis takes the newest frame and skips the others"
            elif self._results_error:
                note = f"results not shown: {self._results_error}"
            else:
                note = "no analysis results yet: run skinstretch analyze on this session"
            return empty_overlays(k, note).to_json_bytes()

    def gauge(self, sid: int, query: dict[str, str]):
        """The gauge of ``query`` (frame, x, y[, x2, y2][, radius_mm]) as a GaugeSeries, or None without results."""
        def number(name: str) -> float | None:
            if name not in query or query[name] == "":
                return None
            try:
                return float(query[name])
            except ValueError:
                raise InvalidInputError(f"{name} must be a number, got {query[name]!r}") from None

        with self._lock:
            if sid != self.sid or self.results is None:
                return None
            x, y, frame = number("x"), number("y"), number("frame")
            if x is None or y is None:
                raise InvalidInputError("a gauge needs x and y")
            return self.results.gauge(frame=int(frame or 0), x=x, y=y, x2=number("x2"), y2=number("y2"),
                                      radius_mm=number("radius_mm"))

    def study(self) -> dict[str, Any]:
        """The study overview of the data directory shown (``{"available": False}`` for a single trial)."""
        from skinstretch.experiments.study import study_overview  # noqa: PLC0415

        directory = self.target.directory
        if directory is None:
            return {"available": False, "reason": "the viewer shows one trial: run skinstretch view DATADIR"}
        with self._lock:
            shown = self.source.path.resolve() if self.source is not None else None
            following = self._chosen is None
        trials = study_overview(directory)
        return {"available": True, "directory": directory.name, "following": following,
                "trials": [{**t.to_json(), "shown": shown is not None and t.session.resolve() == shown}
                           for t in trials]}

    def open_trial(self, index: int) -> bool:
        """Show trial ``index`` of the study overview (and stop following the newest); False if there is none."""
        from skinstretch.experiments.study import study_sessions  # noqa: PLC0415

        if self.target.directory is None:
            return False
        sessions = study_sessions(self.target.directory)
        if not 0 <= index < len(sessions):
            return False
        with self._lock:
            self._chosen = sessions[index]
            self._switch(sessions[index], _results_beside(sessions[index]))
        self.update()
        return True

    def follow_newest(self) -> None:
        with self._lock:
            self._chosen = None
        self.update()

    def live_update(self, seen_version: int) -> tuple[int, bytes | None]:
        """(version, JSON of the newest live frame: its index and times) when a frame was analysed live since
        ``seen_version``. The page fetches the overlays of the frames it draws: it draws fewer than are analysed."""
        with self._lock:
            a = self.analyzer
            if a is None or a.version == seen_version:
                return seen_version, None
            ov = a.latest()
            if ov is None:
                return a.version, None
            return a.version, json.dumps({"frame": ov.frame, "exposure_time": ov.exposure_time,
                                          "analysed_time": ov.analysed_time}).encode()


# ------------------------------------------------------------------------------------------- security


class TokenGate:
    """ASGI middleware: every request carries this run's token (query ``token`` or the cookie set with the page)."""

    def __init__(self, app: ASGIApp, *, token: str) -> None:
        self.app = app
        self.token = token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        conn = HTTPConnection(scope)
        given = conn.query_params.get("token") or conn.cookies.get(TOKEN_COOKIE) or ""
        if not secrets.compare_digest(given.encode(), self.token.encode()):
            await PlainTextResponse("this viewer needs the token from the URL it printed", status_code=403)(
                scope, receive, send)
            return

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                headers += [(b"x-content-type-options", b"nosniff"), (b"referrer-policy", b"no-referrer"),
                            (b"x-frame-options", b"DENY")]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


# ------------------------------------------------------------------------------------------------ app


def create_app(state: ViewerState, *, token: str, allowed_hosts: list[str] | None = None) -> Starlette:
    """The viewer's ASGI app for ``state``; every request must carry ``token``."""

    async def index(request: Request) -> Response:
        resp = FileResponse(STATIC_DIR / "index.html", headers={"cache-control": "no-store"})
        resp.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="strict")
        return resp

    async def info(request: Request) -> Response:
        data = await anyio.to_thread.run_sync(state.info)
        return JSONResponse(data, headers={"cache-control": "no-store"})

    async def frame(request: Request) -> Response:
        sid, k = request.path_params["sid"], request.path_params["k"]
        data = await anyio.to_thread.run_sync(state.frame_image, sid, k)
        if data is None:
            return PlainTextResponse(f"no frame {k} in session {sid}", status_code=404)
        return Response(data, media_type="image/bmp", headers={"cache-control": "private, max-age=3600"})

    async def overlay(request: Request) -> Response:
        sid, k = request.path_params["sid"], request.path_params["k"]
        try:
            span = int(request.query_params.get("span", "1"))
        except ValueError:
            return PlainTextResponse("span must be an integer", status_code=400)
        data = await anyio.to_thread.run_sync(state.overlays, sid, k, span)
        if data is None:
            return PlainTextResponse(f"no frame {k} in session {sid}", status_code=404)
        return Response(data, media_type="application/json", headers={"cache-control": "no-store"})

    async def gauge(request: Request) -> Response:
        sid = request.path_params["sid"]
        try:
            series = await anyio.to_thread.run_sync(state.gauge, sid, dict(request.query_params))
        except SkinstretchError as exc:
            return PlainTextResponse(str(exc), status_code=400)
        if series is None:
            return PlainTextResponse(f"no analysis results for session {sid}", status_code=404)
        if request.url.path.endswith(".csv"):
            return Response(series.csv_text().encode(), media_type="text/csv", headers={
                "cache-control": "no-store", "content-disposition": f'attachment; filename="{series.kind}.csv"'})
        return JSONResponse(series.to_json(), headers={"cache-control": "no-store"})

    async def study_page(request: Request) -> Response:
        return FileResponse(STATIC_DIR / "study.html", headers={"cache-control": "no-store"})

    async def study(request: Request) -> Response:
        data = await anyio.to_thread.run_sync(state.study)
        return JSONResponse(data, headers={"cache-control": "no-store"})

    async def open_trial(request: Request) -> Response:
        ok = await anyio.to_thread.run_sync(state.open_trial, request.path_params["i"])
        if not ok:
            return PlainTextResponse(f"no trial {request.path_params['i']} in this study", status_code=404)
        return JSONResponse({"sid": state.sid})

    async def follow(request: Request) -> Response:
        await anyio.to_thread.run_sync(state.follow_newest)
        return JSONResponse({"sid": state.sid})

    async def events(request: Request) -> Response:
        from sse_starlette.sse import EventSourceResponse  # noqa: PLC0415

        async def stream():
            last: dict[str, Any] | None = None
            version = -1
            while True:
                snap = state.snapshot()
                if snap != last:
                    last = snap
                    yield {"event": "state", "data": json.dumps(snap)}
                version, live = state.live_update(version)
                if live is not None:
                    yield {"event": "live", "data": live.decode()}
                await anyio.sleep(EVENT_INTERVAL_S)

        return EventSourceResponse(stream(), ping=10, headers={"cache-control": "no-store"})

    @asynccontextmanager
    async def lifespan(app):
        stop = threading.Event()

        def watch():
            while not stop.wait(WATCH_INTERVAL_S):
                try:
                    state.update()
                except (SessionFileError, OSError) as exc:
                    log.warning("viewer: %s", exc)

        watcher = threading.Thread(target=watch, name="viewer-watch", daemon=True)
        watcher.start()
        try:
            yield
        finally:
            stop.set()
            watcher.join(2.0)
            state.close()

    routes = [
        Route("/", index),
        Route("/api/info", info),
        Route("/api/s/{sid:int}/frame/{k:int}.bmp", frame),
        Route("/api/s/{sid:int}/overlay/{k:int}", overlay),
        Route("/api/events", events),
        Route("/api/s/{sid:int}/gauge", gauge),
        Route("/api/s/{sid:int}/gauge.csv", gauge),
        Route("/study", study_page),
        Route("/api/study", study),
        Route("/api/study/open/{i:int}", open_trial, methods=["POST"]),
        Route("/api/study/follow", follow, methods=["POST"]),
        Mount("/static", app=StaticFiles(directory=STATIC_DIR), name="static"),
    ]
    middleware = [Middleware(TokenGate, token=token)]
    if allowed_hosts:
        middleware.insert(0, Middleware(TrustedHostMiddleware, allowed_hosts=allowed_hosts))
    return Starlette(routes=routes, middleware=middleware, lifespan=lifespan)


def allowed_hosts_for(host: str) -> list[str]:
    """Host headers accepted for a server bound to ``host`` (loopback names for a loopback bind)."""
    if host in ("127.0.0.1", "localhost", "::1"):
        return ["127.0.0.1", "localhost", "[::1]", "::1"]
    return ["*"]  # bound to another interface on purpose: the token guards it


@dataclass
class RunningServer:
    """A viewer served on a thread (tests, benches, ``record --live``): its URL and how to stop it."""

    url: str
    port: int
    token: str
    state: ViewerState
    _server: Any
    _thread: threading.Thread

    def stop(self, timeout_s: float = 10.0) -> None:
        self._server.should_exit = True
        self._thread.join(timeout_s)


def _config(state: ViewerState, host: str, port: int, token: str):
    import uvicorn  # noqa: PLC0415

    app = create_app(state, token=token, allowed_hosts=allowed_hosts_for(host))
    return uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False, lifespan="on")


def _url(host: str, port: int, token: str) -> str:
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else (f"[{host}]" if ":" in host else host)
    return f"http://{shown}:{port}/?token={token}"


def check_listenable(host: str, port: int) -> None:
    """Refuse, in one line naming the option to change, an address the server could not listen on (a port in use,
    an address of no interface here); uvicorn would log its own error and then stop."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise InvalidInputError(f"host {host!r} is not an address of this machine ({exc.strerror})",
                                remedy=Remedy(("host",), "to choose another")) from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise InvalidInputError(f"port {port} on {host} is in use",
                                        remedy=Remedy(("port",), "to choose another (0: any free port)")) from None
            raise InvalidInputError(f"host {host} cannot be listened on ({exc.strerror})",
                                    remedy=Remedy(("host",), "to choose another")) from None


def _warm_up_live() -> None:
    try:
        log.debug("viewer: live analysis warmed up in %.2f s", warm_up())
    except SkinstretchError as exc:  # pragma: no cover - the made-up print is analysable
        log.warning("viewer: live analysis warm-up failed: %s", exc)


def start_server(target: ViewTarget, *, host: str = "127.0.0.1", port: int = 0, live: bool = True,
                 timeout_s: float = 30.0) -> RunningServer:
    """Serve ``target`` on a background thread and return once it listens (``port=0`` picks a free port)."""
    import uvicorn  # noqa: PLC0415

    check_listenable(host, port)
    token = secrets.token_urlsafe(24)
    state = ViewerState(target, live=live)
    server = uvicorn.Server(_config(state, host, port, token))
    thread = threading.Thread(target=server.run, name="viewer-server", daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout_s
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            state.close()
            raise InvalidInputError(f"the viewer could not listen on {host}:{port}")
        time.sleep(0.02)
    bound = server.servers[0].sockets[0].getsockname()[1]
    return RunningServer(_url(host, bound, token), bound, token, state, server, thread)


def serve(target: ViewTarget, *, host: str = "127.0.0.1", port: int = 8765, open_browser: bool = True,
          live: bool = True, announce: Callable[[str], None] | None = None, parent_pid: int | None = None) -> None:
    """Serve ``target`` until interrupted (Ctrl-C), printing the URL and opening it in a browser.

    ``parent_pid``: also stop when that process (a recording that started this viewer) is gone, however it ended.
    """
    announce = announce or log.info
    running = start_server(target, host=host, port=port, live=live)
    announce(f"viewer: {running.url}")
    if host not in ("127.0.0.1", "localhost", "::1"):
        announce(f"viewer: listening on {host}: anyone with the URL (and its token) can see this session")
    if open_browser:
        webbrowser.open(running.url)
    try:
        while running._thread.is_alive():
            running._thread.join(0.5)
            if parent_pid is not None and os.getppid() != parent_pid:
                log.info("viewer: the recording that started it ended; stopping")
                break
    finally:
        running.stop()

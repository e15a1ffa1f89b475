"""Start the viewer in a process of its own next to a recording (``skinstretch record --live``, the live bench).

The viewer process reads the session files in SWMR mode and runs the live analysis there, so the recording
process never waits on it: it does not even know the viewer is there. If the viewer cannot start or dies, the
recording goes on.
"""

from __future__ import annotations

import logging
import os
import queue
import subprocess
import sys
import threading
import webbrowser
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from skinstretch.child_process import stop_child_process
from skinstretch.processing.errors import InvalidInputError

log = logging.getLogger(__name__)

__all__ = ["LiveViewerProcess", "live_view", "start_live_viewer"]

URL_PREFIX = "viewer: "


@dataclass
class LiveViewerProcess:
    """A running ``skinstretch view`` process: its URL (with the token) and how to end it."""

    url: str
    process: subprocess.Popen

    def stop(self, timeout_s: float = 10.0) -> None:
        """End the viewer (SIGTERM, then SIGKILL after ``timeout_s``); its output is read by a thread of ours."""
        stop_child_process(self.process, timeout_s=timeout_s, read_output=False)


def start_live_viewer(directory: str | os.PathLike, *, port: int = 0, host: str = "127.0.0.1",
                      open_browser: bool = True, timeout_s: float = 60.0) -> LiveViewerProcess:
    """Start ``skinstretch view DIRECTORY`` (following the newest trial, with the live analysis) in a new process
    and return once it listens. ``directory`` is created if needed: the recording fills it afterwards."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "skinstretch.cli", "view", str(directory), "--port", str(port), "--host", host,
           "--no-browser", "--exit-with-parent", str(os.getpid())]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=None, text=True, bufsize=1)
    lines: queue.Queue[str] = queue.Queue()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    threading.Thread(target=read, name="live-viewer-stdout", daemon=True).start()
    try:
        while True:
            line = lines.get(timeout=timeout_s)
            if line.startswith(URL_PREFIX):
                url = line[len(URL_PREFIX):].strip()
                break
    except queue.Empty:
        proc.kill()
        proc.wait()
        raise InvalidInputError(f"the live viewer did not start within {timeout_s:g} s") from None
    viewer = LiveViewerProcess(url, proc)
    if open_browser:
        webbrowser.open(url)
    return viewer


@contextmanager
def live_view(directory: str | os.PathLike, *, enabled: bool = True, open_browser: bool = True):
    """While the block runs, show ``directory``'s newest trial in a live viewer (a separate process); nothing
    when ``enabled`` is False. A viewer that cannot start is logged and the block runs without it."""
    if not enabled:
        yield None
        return
    try:
        viewer = start_live_viewer(directory, open_browser=open_browser)
    except (InvalidInputError, OSError) as exc:
        log.warning("live view not started: %s", exc)
        viewer = None
    else:
        log.info("live view: %s", viewer.url)
    try:
        yield viewer
    finally:
        if viewer is not None:
            viewer.stop()

"""Stopping a device twin that runs as a child process (the GigE fake camera, the Net F/T box program)."""

from __future__ import annotations

import subprocess

__all__ = ["stop_child_process"]


def stop_child_process(proc: subprocess.Popen, *, timeout_s: float = 5.0) -> str | bytes | None:
    """Ask ``proc`` to stop (SIGTERM), kill it if it has not exited within ``timeout_s``; return what it still wrote
    to its standard-output pipe (None without one). Its pipes are closed afterwards."""
    proc.terminate()
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate(timeout=timeout_s)
    return out

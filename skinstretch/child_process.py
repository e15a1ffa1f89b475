"""Stopping a program this process started: a device twin (the GigE fake camera, the Net F/T box program, the
STReSS firmware on a pty) or the live viewer. It imports nothing of skinstretch's layers, so every layer can use it.
"""

from __future__ import annotations

import subprocess

__all__ = ["stop_child_process"]


def stop_child_process(proc: subprocess.Popen, *, timeout_s: float = 5.0, grace_s: float = 0.0,
                       read_output: bool = True) -> str | bytes | None:
    """End ``proc`` and return what it still wrote to its standard-output pipe (None without one).

    It is first given ``grace_s`` to exit by itself (a program that ends when its input closes, and saves its
    records as it does), then asked to stop (SIGTERM), then killed (SIGKILL) if it has not exited within
    ``timeout_s``. ``read_output=False`` where another thread reads its output: nothing is read here and None is
    returned. Its pipes are closed afterwards.
    """

    def wait(seconds: float) -> str | bytes | None:
        if read_output:
            return proc.communicate(timeout=seconds)[0]  # retried after a timeout without losing output
        proc.wait(seconds)
        return None

    try:
        if grace_s > 0:
            try:
                return wait(grace_s)
            except subprocess.TimeoutExpired:
                pass
        proc.terminate()
        try:
            return wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            return wait(timeout_s)
    finally:
        for pipe in (proc.stdin, proc.stdout, proc.stderr):
            if pipe is not None:
                pipe.close()

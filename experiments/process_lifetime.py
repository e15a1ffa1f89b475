"""Child processes that never outlive the program that started them, whatever ends it (SIGKILL included).

A ``record`` killed with SIGKILL used to leave its two scene-render workers and multiprocessing's resource
tracker running, idle, ~300 MB each, until someone killed them: a pool worker blocks reading its call queue, and
every worker holds a copy of that queue's write end, so none of them ever sees end-of-file. Two layers:

* :func:`die_with_parent`, the initializer of every worker pool the recorder starts (:func:`worker_pool`): the
  kernel sends the worker SIGKILL when its parent dies (``prctl(PR_SET_PDEATHSIG)``, Linux); a worker whose
  parent is already gone when it starts exits at once, and elsewhere a thread polls the parent twice a second.
* :func:`guard_process_tree`, around a whole command: a small watcher process remembers every descendant of the
  command (libraries' processes included: multiprocessing's forkserver and resource tracker, an analysis pool's
  workers) and, once the command has ended, kills those still alive. The resource tracker is left a moment to
  exit by itself first, since it unlinks the shared-memory blocks the dead processes leaked.

Hand-written: the standard library has no parent-death hook; ``prctl`` is reached through ctypes and the process
tree through psutil.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import contextlib
import ctypes
import ctypes.util
import logging
import multiprocessing
import os
import select
import signal
import subprocess
import sys
import threading
import time

log = logging.getLogger(__name__)

__all__ = ["die_with_parent", "worker_pool", "guard_process_tree"]

_PR_SET_PDEATHSIG = 1
#: How often the tree watcher looks for new descendants (s): a process started and orphaned within this window
#: is covered by die_with_parent instead.
SCAN_INTERVAL_S = 0.5
#: How long the resource tracker is given to clean up and exit by itself once everything else is gone (s).
TRACKER_GRACE_S = 1.0


def die_with_parent(parent_pid: int) -> None:
    """Make this process die with ``parent_pid`` (run first in a worker, e.g. as a pool initializer).

    On Linux the kernel delivers SIGKILL when the parent exits (PR_SET_PDEATHSIG: when the *thread* that
    started the worker exits, so start pools from a thread that lives as long as they do). If the parent is
    already gone, exit now. Without prctl, a daemon thread checks the parent every 0.5 s.
    """
    libc_name = ctypes.util.find_library("c")
    armed = False
    if sys.platform.startswith("linux") and libc_name:
        libc = ctypes.CDLL(libc_name, use_errno=True)
        armed = libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(1)
    if not armed:
        threading.Thread(target=_poll_parent, args=(parent_pid,), name="parent-watch", daemon=True).start()


def _poll_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(0.5)
    os._exit(1)


def worker_pool(workers: int) -> cf.ProcessPoolExecutor:
    """A process pool (``spawn``: the recorder runs threads that fork would copy mid-state) whose workers die
    with this process."""
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                  initializer=die_with_parent, initargs=(os.getpid(),))


_WATCHER: list[subprocess.Popen] = []  # one per process, kept referenced for the process's whole life


def guard_process_tree() -> subprocess.Popen | None:
    """Start (once per process) a watcher process that kills whatever this process started (children,
    grandchildren) as soon as this process has ended, however it ended. Returns the watcher (None where it
    cannot start: the workers' own parent-death signal still holds)."""
    if _WATCHER and _WATCHER[0].poll() is None:
        return _WATCHER[0]
    try:
        watcher = subprocess.Popen(
            [sys.executable, "-m", "skinstretch.experiments.process_lifetime", "--watch", str(os.getpid())],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, close_fds=True)
    except OSError as exc:
        log.debug("process-tree guard not started (%s); worker processes still die with their parent", exc)
        return None
    _WATCHER[:] = [watcher]
    return watcher


def _is_resource_tracker(proc) -> bool:
    try:
        return any("resource_tracker" in part for part in proc.cmdline())
    except Exception:  # noqa: BLE001 - gone or unreadable: not the tracker we wait for
        return False


def _watch(pid: int, *, interval_s: float = SCAN_INTERVAL_S) -> int:
    """The watcher's loop: remember the descendants of ``pid`` until it exits, then end the ones still alive."""
    import psutil  # noqa: PLC0415 - only the watcher process needs it

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C in the terminal is for the guarded command
    me = os.getpid()
    try:
        guarded = psutil.Process(pid)
    except psutil.NoSuchProcess:
        return 0
    try:
        pidfd = os.pidfd_open(pid)
    except (AttributeError, OSError):
        pidfd = None
    known: dict[int, psutil.Process] = {}
    while True:
        try:
            for child in guarded.children(recursive=True):
                if child.pid != me:
                    known.setdefault(child.pid, child)
        except psutil.Error:
            pass
        if pidfd is not None:
            if select.select([pidfd], [], [], interval_s)[0]:
                break
        else:
            time.sleep(interval_s)
        if not guarded.is_running():
            break
    victims: dict[int, psutil.Process] = {}
    for proc in list(known.values()):
        try:
            if proc.is_running():  # psutil compares creation times: a reused pid is not ours
                victims[proc.pid] = proc
                for grandchild in proc.children(recursive=True):
                    victims.setdefault(grandchild.pid, grandchild)
        except psutil.Error:
            continue
    victims.pop(me, None)
    trackers = [p for p in victims.values() if _is_resource_tracker(p)]
    for proc in victims.values():
        if proc not in trackers:
            with contextlib.suppress(psutil.Error):
                proc.kill()
    deadline = time.monotonic() + TRACKER_GRACE_S
    while trackers and time.monotonic() < deadline:
        trackers = [p for p in trackers if _running(p)]  # a dead orphan nobody reaps stays a zombie: gone
        time.sleep(0.02)
    for proc in trackers:
        with contextlib.suppress(psutil.Error):
            proc.kill()
    return 0


def _running(proc) -> bool:
    import psutil  # noqa: PLC0415

    try:
        return proc.is_running() and proc.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="kill the leftover descendants of a process once it has ended")
    parser.add_argument("--watch", type=int, required=True, help="process id to guard")
    return _watch(parser.parse_args(argv).watch)


if __name__ == "__main__":  # pragma: no cover - run as the watcher process
    sys.exit(main())

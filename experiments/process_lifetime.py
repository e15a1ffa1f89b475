"""Child processes that never outlive the program that started them, whatever ends it (SIGKILL included).

The one mechanism every process pool of skinstretch uses (the recorder's analysis and scene-render workers, the
analysis executor's workers): :func:`worker_pool`. Two layers:

* **Each process dies with its parent.** The pool's workers are forked from multiprocessing's forkserver (a clean,
  single-threaded process: never forked from this possibly multi-threaded one), which imports the pool's
  ``preload`` modules once so that workers start in milliseconds and share those modules' memory. The forkserver
  and every worker ask the kernel for SIGKILL when their parent dies (``prctl(PR_SET_PDEATHSIG)``, Linux), so a
  SIGKILL of this process takes the forkserver at once and the workers with it. Without that signal the
  forkserver lingered: it exits by itself only once every worker has closed its end of a pipe, and then spends
  a few seconds under load tearing down the numerical libraries it preloaded. A worker also watches this process
  from a thread (:func:`die_with_parent`) where the signal cannot be armed or the forkserver was not bound.
* **Whatever else the command started** (libraries' processes: multiprocessing's resource tracker, Dask's
  nannies, the live viewer) is killed by :func:`guard_process_tree`, a small watcher process that remembers every
  descendant of the command and, once the command has ended, kills those still alive. The resource tracker is
  left a moment to exit by itself first, since it unlinks the shared-memory blocks the dead processes leaked.

Hand-written: the standard library has no parent-death hook and no way to run code in its forkserver other than
its preload list; ``prctl`` is reached through ctypes and the process tree through psutil.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import contextlib
import ctypes
import logging
import multiprocessing
import os
import queue
import select
import signal
import sys
import threading
import time
from typing import Any, Callable, Sequence

log = logging.getLogger(__name__)

__all__ = ["StopRequested", "check_stop", "die_with_parent", "end_pool_now", "guard_process_tree", "stop_deferred",
           "stop_on_signals", "stop_pending", "stop_reason", "stopped_by_signal", "worker_pool"]

_PR_SET_PDEATHSIG = 1
#: How often a worker that cannot count on the parent-death signal checks that its owner is alive (s).
PARENT_CHECK_S = 0.25
#: How often the tree watcher looks for new descendants (s): a process started and orphaned within this window
#: is covered by die_with_parent instead.
SCAN_INTERVAL_S = 0.5
#: How long the resource tracker is given to clean up and exit by itself once everything else is gone (s).
TRACKER_GRACE_S = 1.0


# -- each process dies with its parent ---------------------------------------------------------------------------


def worker_pool(workers: int, *, preload: Sequence[str] = (), initializer: Callable[..., Any] | None = None,
                initargs: tuple = ()) -> cf.ProcessPoolExecutor:
    """A pool of ``workers`` processes that die with this process, whatever kills it (module docstring).

    Workers are forked from multiprocessing's forkserver (``spawn`` where there is none), never from this
    process, which may run threads (the recorder's writer, a force reader) that a fork would copy mid-state.
    ``preload``: modules the forkserver imports once for all its workers; the forkserver is started by the first
    pool of this process, and a later pool's workers import what it lacks after the fork. ``initializer(*initargs)``
    runs in each worker once it is bound to this process.
    """
    if "forkserver" in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context("forkserver")
        _FORKSERVER_PRELOAD.extend(m for m in preload if m not in _FORKSERVER_PRELOAD)
        context.set_forkserver_preload(list(_FORKSERVER_PRELOAD))
        from multiprocessing import forkserver  # noqa: PLC0415 - POSIX only

        _run_on_lasting_thread(forkserver.ensure_running)
    else:  # pragma: no cover - Windows
        context = multiprocessing.get_context("spawn")
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_start_worker,
                                  initargs=(os.getpid(), initializer, initargs))


#: What every forkserver of this process imports; this module first, so that the forkserver is bound to this
#: process (the end of this file) before it spends a second or two importing the others.
_FORKSERVER_PRELOAD: list[str] = [__name__]


def _start_worker(owner_pid: int, initializer: Callable[..., Any] | None, initargs: tuple) -> None:
    die_with_parent(owner_pid)
    if initializer is not None:
        initializer(*initargs)


def die_with_parent(owner_pid: int) -> None:
    """Make this worker die with ``owner_pid``, the process that started its pool (run first in the worker;
    :func:`worker_pool` does).

    The kernel kills the worker when its parent ends: the owner itself, or the owner's forkserver, which dies
    with the owner the same way. A worker whose owner is already gone exits at once. Where the signal cannot be
    armed (not Linux), or the parent is the forkserver, a daemon thread also checks the owner every
    ``PARENT_CHECK_S`` and exits once it is gone.
    """
    armed = _arm_parent_death_signal()
    if not _descends_from(owner_pid):  # the owner died before the signal was armed
        os._exit(1)
    if not armed or os.getppid() != owner_pid:
        threading.Thread(target=_exit_once_orphaned, args=(owner_pid,), name="watch-owner", daemon=True).start()


def _arm_parent_death_signal() -> bool:
    """Ask the kernel to SIGKILL this process when its parent ends (more exactly: the parent's *thread* that
    started it); False where that cannot be asked."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        return ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _descends_from(owner_pid: int) -> bool:
    """True while ``owner_pid`` is this process' parent, or its parent's parent (a worker forked by the owner's
    forkserver). A dead owner's children are re-parented at once, zombie or not, so this never mistakes a dead
    owner, or a new process that reuses its id, for a living one."""
    parent = os.getppid()
    if parent == owner_pid:
        return True
    import psutil  # noqa: PLC0415 - only the workers need it

    try:
        return psutil.Process(parent).ppid() == owner_pid
    except psutil.Error:
        return False


def _exit_once_orphaned(owner_pid: int) -> None:
    while _descends_from(owner_pid):
        time.sleep(PARENT_CHECK_S)
    os._exit(1)


_STARTER: list = []  # [thread, its request queue]: the thread that starts forkservers, for this process' life
_STARTER_LOCK = threading.Lock()


def _run_on_lasting_thread(fn: Callable[[], Any]) -> Any:
    """``fn()`` run on a daemon thread that lives as long as this process.

    A started process' parent-death signal fires when the *thread* that started it ends: a forkserver started
    from a short-lived thread would die, and take the workers of every pool with it, when that thread ends.
    """
    with _STARTER_LOCK:
        if not _STARTER or not _STARTER[0].is_alive():  # none yet, or inherited through a fork (not running here)
            requests: queue.SimpleQueue = queue.SimpleQueue()
            thread = threading.Thread(target=_serve_requests, args=(requests,), name="process-starter", daemon=True)
            thread.start()
            _STARTER[:] = [thread, requests]
        requests = _STARTER[1]
    done: cf.Future = cf.Future()
    requests.put((fn, done))
    return done.result()


def _serve_requests(requests: queue.SimpleQueue) -> None:
    while True:
        fn, done = requests.get()
        try:
            done.set_result(fn())
        except BaseException as exc:  # noqa: BLE001 - handed to the caller through the future
            done.set_exception(exc)


# -- a signal asks the command to stop -----------------------------------------------------------------------------


class StopRequested(KeyboardInterrupt):
    """A signal asked the command to stop: SIGTERM (``kill``, systemd), SIGHUP (a closing terminal) or SIGINT
    (Ctrl-C). A KeyboardInterrupt, raised in the main thread, so every ``finally`` and every handler of Ctrl-C
    closes what it opened (Python's default for SIGTERM ends the process on the spot, like SIGKILL)."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(signal.Signals(signum).name)

    @property
    def exit_status(self) -> int:
        return 128 + self.signum


def stop_reason(exc: BaseException) -> str:
    """Why a command was stopped, for a trial's ``status_reason`` and the last line: ``SIGTERM received``."""
    if isinstance(exc, StopRequested):
        return f"{signal.Signals(exc.signum).name} received"
    return "interrupted (Ctrl-C)"


_STOP_SIGNAL: list[int] = []  # the signal that asked this process to stop (stop_on_signals), if one did
_STOPPED: list[int] = []  # every signal stop_on_signals handled in this process (kept after the block)


def stopped_by_signal() -> bool:
    """Whether a signal handled by :func:`stop_on_signals` asked this process to stop (the command line then
    ends it without the interpreter's slow teardown, once the command has closed what it wrote)."""
    return bool(_STOPPED)


@contextlib.contextmanager
def stop_on_signals(signums: Sequence[int] = (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)):
    """While the block runs, the first of ``signums`` raises :class:`StopRequested` in the main thread; later
    ones are ignored, so that the clean-up it starts (closing files, resting the display, ending workers) is
    not cut short. Python drops an exception raised where it cannot propagate (a finaliser, a weakref callback
    that the signal happened to interrupt): loops that can run long call :func:`check_stop` as well. The
    handlers before are restored at the end."""

    def handler(signum: int, frame) -> None:
        _STOPPED.append(signum)
        if _STOP_SIGNAL:
            log.warning("%s received again while stopping: ignored", signal.Signals(signum).name)
            return
        _STOP_SIGNAL.append(signum)
        if not _DEFERRED:
            raise StopRequested(signum)

    previous = {s: signal.signal(s, handler) for s in signums}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _STOP_SIGNAL.clear()


_DEFERRED: list[int] = []  # stop_deferred blocks running


@contextlib.contextmanager
def stop_deferred():
    """A signal that arrives in the block does not interrupt it (closing a trial's file, logging how it ended):
    it is noted, and the next :func:`check_stop` after the block acts on it."""
    _DEFERRED.append(1)
    try:
        yield
    finally:
        _DEFERRED.pop()


def stop_pending() -> bool:
    """Whether a signal asked this process to stop (see :func:`stop_on_signals`)."""
    return bool(_STOP_SIGNAL)


def check_stop() -> None:
    """Raise :class:`StopRequested` if a signal asked this process to stop (for a loop that can run long: the
    handler's own exception may have been dropped). Not for clean-up code, which must run to its end."""
    if _STOP_SIGNAL:
        raise StopRequested(_STOP_SIGNAL[0])


def end_pool_now(pool: cf.ProcessPoolExecutor) -> None:
    """Cancel what ``pool`` has queued and end its workers now, their tasks unfinished (a command that was asked to
    stop does not wait minutes for an analysis). The standard library has no public way before Python 3.14."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        with contextlib.suppress(OSError, ValueError):
            proc.kill()
    pool.shutdown(wait=True, cancel_futures=True)


# -- whatever else the command started ----------------------------------------------------------------------------


_WATCHER: list[int] = []  # the watcher's pid, one per process


def guard_process_tree() -> int | None:
    """Start (once per process) a watcher process that kills whatever this process started (children,
    grandchildren) as soon as this process has ended, however it ended. Returns the watcher's pid (None where it
    cannot start: the workers' own parent-death signal still holds).

    Spawned without a :class:`subprocess.Popen`: the watcher is meant to outlive this process, and a Popen still
    running when the interpreter ends says so with a ResourceWarning ("subprocess N is still running").
    """
    if _WATCHER and _running_child(_WATCHER[0]):
        return _WATCHER[0]
    devnull = [(os.POSIX_SPAWN_OPEN, fd, os.devnull, flags, 0) for fd, flags in ((0, os.O_RDONLY), (1, os.O_WRONLY))]
    try:
        pid = os.posix_spawn(sys.executable, [sys.executable, "-m", "skinstretch.experiments.process_lifetime",
                                              "--watch", str(os.getpid())], os.environ, file_actions=devnull)
    except OSError as exc:
        log.debug("process-tree guard not started (%s); worker processes still die with their parent", exc)
        return None
    _WATCHER[:] = [pid]
    return pid


def _running_child(pid: int) -> bool:
    """Whether ``pid``, a child of this process, still runs (one that has ended is reaped)."""
    try:
        return os.waitpid(pid, os.WNOHANG) == (0, 0)
    except ChildProcessError:  # not ours (inherited through a fork) or already reaped
        return False


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


def _imported_by_the_forkserver() -> bool:
    """True while multiprocessing's forkserver imports this module (its preload list is the only hook it has)."""
    forkserver = sys.modules.get("multiprocessing.forkserver")
    frame = sys._getframe(1) if forkserver is not None else None
    while frame is not None:
        if frame.f_code is forkserver.main.__code__:
            return True
        frame = frame.f_back
    return False


if _imported_by_the_forkserver():
    _arm_parent_death_signal()  # the forkserver dies with the process it serves, and its workers with it


if __name__ == "__main__":  # pragma: no cover - run as the watcher process
    sys.exit(main())

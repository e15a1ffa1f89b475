"""No process `record` starts outlives it: SIGKILL it mid-session, with analysis on and scene-render workers busy,
and every process of its session is gone within 2 s (render workers, the analysis worker and its pool, the
multiprocessing resource tracker, the tree watcher itself)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil

from skinstretch.experiments.process_lifetime import die_with_parent, worker_pool

CLI = [sys.executable, "-m", "skinstretch.cli"]

PROTOCOL = """\
name: orphans
subject: {id: s01}
camera_mode: full
trials:
  - {name: a, duration_s: 0.6, surface: {kind: flat}}
  - {name: b, duration_s: 0.6, surface: {kind: ridge}}
  - {name: c, duration_s: 0.6, surface: {kind: valley}}
record: {force: true}
analysis: {enabled: true, method: features}
"""


def _alive(proc: psutil.Process) -> bool:
    """Running and not a zombie (a dead orphan waits for pid 1 to reap it: in a container that may be never)."""
    try:
        return proc.is_running() and proc.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def _describe(proc: psutil.Process) -> str:
    try:
        return f"{proc.pid} {' '.join(proc.cmdline())}"
    except psutil.Error:
        return f"{proc.pid} (gone)"


def _session_processes(sid: int) -> list[psutil.Process]:
    """Living processes of session ``sid``."""
    out = []
    for proc in psutil.process_iter():
        try:
            if os.getsid(proc.pid) == sid and _alive(proc):
                out.append(proc)
        except (ProcessLookupError, PermissionError, psutil.Error):
            continue
    return out


def test_sigkill_of_record_leaves_no_process_of_its_session(tmp_path):
    proto = tmp_path / "p.yaml"
    proto.write_text(PROTOCOL)
    # its own session: every process it starts (not re-parented elsewhere by setsid) is found by session id
    child = subprocess.Popen(CLI + ["record", str(proto), "-o", str(tmp_path / "d"), "--no-movie"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    sid = child.pid
    seen: dict[int, str] = {}
    try:
        for line in child.stdout:  # bounded by pytest-timeout
            if line.startswith("trial 2/3"):
                break  # the second trial starts: trial 1 goes to the analysis worker, trial 3 is being rendered
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:  # until the analysis worker has started
            procs = {p.pid: " ".join(p.cmdline()) for p in psutil.Process(sid).children(recursive=True)}
            seen.update(procs)
            workers = [c for c in procs.values() if "multiprocessing-fork" in c]
            if len(workers) >= 3 and any("resource_tracker" in c for c in procs.values()):
                break  # 2 render workers and the analysis worker, and the resource tracker
            time.sleep(0.1)
        assert sum("multiprocessing-fork" in c for c in seen.values()) >= 3, seen
        time.sleep(SETTLE_S)  # let the watcher see the newest ones
        os.kill(child.pid, signal.SIGKILL)
        killed_at = time.monotonic()
        child.wait(10)
        left = _session_processes(sid)
        while left and time.monotonic() - killed_at < 10:
            time.sleep(0.05)
            left = [p for p in left if _alive(p)]
        gone_after = time.monotonic() - killed_at
    finally:
        child.stdout.close()
        for proc in _session_processes(sid):  # whatever the test started and is still there
            try:
                proc.kill()
            except psutil.Error:
                pass
    assert not left, [_describe(p) for p in left]
    assert gone_after <= 2.0, f"the last process of the session went {gone_after:.2f} s after the SIGKILL"


SETTLE_S = 0.6  # > the watcher's scan interval (0.5 s)


def _sleep_forever():
    time.sleep(3600)


def test_pool_workers_die_with_their_parent_at_once(tmp_path):
    """The first layer alone: a pool's workers get SIGKILL from the kernel when their parent dies."""
    code = (f"import sys, time; sys.path.insert(0, {str(Path(__file__).resolve().parents[1])!r})\n"
            "from tests.test_reliability_orphans import _sleep_forever\n"
            "from skinstretch.experiments.process_lifetime import worker_pool\n"
            "if __name__ == '__main__':\n"
            "    pool = worker_pool(2)\n"
            "    futures = [pool.submit(_sleep_forever) for _ in range(2)]\n"
            "    print('ready', flush=True)\n"
            "    time.sleep(3600)\n")
    script = tmp_path / "parent.py"
    script.write_text(code)
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                              start_new_session=True)
    try:
        assert parent.stdout.readline().strip() == "ready"
        deadline = time.monotonic() + 30
        workers = []
        while time.monotonic() < deadline and len(workers) < 2:
            workers = [p for p in psutil.Process(parent.pid).children() if "resource_tracker" not in _describe(p)]
            time.sleep(0.1)
        assert len(workers) == 2
        parent.kill()
        parent.wait(10)
        deadline = time.monotonic() + 2.0
        while any(_alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [_describe(w) for w in workers if _alive(w)]
    finally:
        parent.stdout.close()
        for proc in _session_processes(parent.pid):
            try:
                proc.kill()
            except psutil.Error:
                pass


def test_a_worker_whose_parent_is_already_gone_exits(monkeypatch):
    exits = []
    monkeypatch.setattr(os, "_exit", lambda code: exits.append(code))
    die_with_parent(os.getppid() + 1 if os.getppid() != 1 else 2)  # "my parent" is someone else: already gone
    assert exits == [1]
    assert worker_pool  # the pool factory is the public entry point

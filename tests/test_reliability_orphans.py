"""No process a command starts outlives it: SIGKILL `record`, `demo` or `analyze` while their worker processes are
busy, and every process of its session is gone within 2 s (render and analysis workers, their forkserver, the
multiprocessing resource tracker, the tree watcher itself); and the mechanism underneath
(skinstretch.experiments.process_lifetime) on its own."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import psutil
import pytest

CLI = [sys.executable, "-m", "skinstretch.cli"]
ROOT = Path(__file__).resolve().parents[1]

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

FORKSERVER = "multiprocessing.forkserver"  # in the command line of the forkserver and of every worker it forks


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


def _command_lines(procs: list[psutil.Process]) -> dict[int, str]:
    """Command line by pid of those of ``procs`` still running (a worker may end, or be a zombie, between listing
    and reading)."""
    out = {}
    for proc in procs:
        try:
            out[proc.pid] = " ".join(proc.cmdline())
        except psutil.Error:
            continue
    return out


def _sigkill_when_busy(cmd: list[str], *, started_line: str | None, workers: int) -> tuple[list[psutil.Process], float]:
    """Run ``cmd`` in a session of its own; once it printed ``started_line`` (if given) and its forkserver has forked
    ``workers`` workers (and the resource tracker runs), SIGKILL it. Returns the processes of its session still
    alive, and when the last one went (s after the SIGKILL; 10 s at most)."""
    child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    sid = child.pid
    seen: dict[int, str] = {}
    try:
        for line in child.stdout if started_line else ():  # bounded by pytest-timeout
            if started_line in line:
                break
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            procs = _command_lines(psutil.Process(sid).children(recursive=True))
            seen.update(procs)
            if (sum(FORKSERVER in c for c in procs.values()) >= workers + 1
                    and any("resource_tracker" in c for c in procs.values())):
                break
            time.sleep(0.05)
        assert sum(FORKSERVER in c for c in seen.values()) >= workers + 1, seen
        time.sleep(SETTLE_S)  # let the tree watcher see the newest ones
        os.kill(child.pid, signal.SIGKILL)
        killed_at = time.monotonic()
        child.wait(10)
        left = _session_processes(sid)
        while left and time.monotonic() - killed_at < 10:
            time.sleep(0.05)
            left = [p for p in left if _alive(p)]
        return left, time.monotonic() - killed_at
    finally:
        child.stdout.close()
        for proc in _session_processes(sid):  # whatever the test started and is still there
            try:
                proc.kill()
            except psutil.Error:
                pass
        if child.poll() is None:  # reap it, so no Popen is left to warn at garbage collection
            child.kill()
        child.wait(10)


SETTLE_S = 0.6  # > the watcher's scan interval (0.5 s)


def test_sigkill_of_record_with_analysis_leaves_no_process_of_its_session(tmp_path):
    proto = tmp_path / "p.yaml"
    proto.write_text(PROTOCOL)
    # the second trial starts: trial 1 goes to the analysis worker while trial 3 is being rendered
    left, gone_after = _sigkill_when_busy(CLI + ["record", str(proto), "-o", str(tmp_path / "d"), "--no-movie"],
                                          started_line="trial 2/3", workers=3)
    assert not left, [_describe(p) for p in left]
    assert gone_after <= 2.0, f"the last process of the session went {gone_after:.2f} s after the SIGKILL"


def test_sigkill_of_demo_leaves_no_process_of_its_session(tmp_path):
    left, gone_after = _sigkill_when_busy(CLI + ["demo", "-o", str(tmp_path / "demo")], started_line="trial 2/3",
                                          workers=3)
    assert not left, [_describe(p) for p in left]
    assert gone_after <= 2.0, f"the last process of the session went {gone_after:.2f} s after the SIGKILL"


def test_sigkill_of_analyze_leaves_no_process_of_its_session(tmp_path):
    from skinstretch.simulators.scene import simulate_to_file

    session = simulate_to_file("flatL", tmp_path / "s.h5", n_frames=60, seed=0)
    left, gone_after = _sigkill_when_busy(
        CLI + ["analyze", str(session), "-o", str(tmp_path / "out"), "--workers", "2", "--parallel", "processes"],
        started_line=None, workers=2)
    assert not left, [_describe(p) for p in left]
    assert gone_after <= 2.0, f"the last process of the session went {gone_after:.2f} s after the SIGKILL"


# -- the mechanism on its own ------------------------------------------------------------------------------------


def _sleep_forever():
    time.sleep(3600)


@pytest.mark.parametrize("starter", ["main thread", "short-lived thread"])
def test_a_pools_workers_and_forkserver_die_with_their_owner_at_once(tmp_path, starter):
    """Without the tree watcher: the kernel's parent-death signal alone takes the forkserver, however slowly it
    would shut down (its preloaded module sleeps 5 s at exit here), and the workers with it; the resource tracker
    then exits by itself. Also when the pool was started from a thread that has ended since."""
    (tmp_path / "slow_teardown.py").write_text("import atexit, time\natexit.register(time.sleep, 5)\n")
    start = ("pool = worker_pool(2, preload=['slow_teardown'])\n"
             "futures = [pool.submit(_sleep_forever) for _ in range(2)]\n")
    if starter == "short-lived thread":
        start = ("import threading\n"
                 "box = {}\n"
                 "def start():\n"
                 "    box['pool'] = worker_pool(2, preload=['slow_teardown'])\n"
                 "    box['futures'] = [box['pool'].submit(_sleep_forever) for _ in range(2)]\n"
                 "t = threading.Thread(target=start)\n"
                 "t.start()\n"
                 "t.join()\n")
    script = tmp_path / "owner.py"
    script.write_text(f"import sys, time\nsys.path.insert(0, {str(ROOT)!r})\n"
                      "from tests.test_reliability_orphans import _sleep_forever\n"
                      "from skinstretch.experiments.process_lifetime import worker_pool\n"
                      "if __name__ == '__main__':\n"
                      + textwrap.indent(start + "print('ready', flush=True)\ntime.sleep(3600)\n", "    "))
    owner = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=tmp_path,
                             start_new_session=True)
    try:
        assert owner.stdout.readline().strip() == "ready"
        deadline = time.monotonic() + 60
        tree: list[psutil.Process] = []
        while time.monotonic() < deadline and sum(FORKSERVER in _describe(p) for p in tree) < 3:
            time.sleep(0.05)
            tree = [p for p in psutil.Process(owner.pid).children(recursive=True) if _alive(p)]
        assert sum(FORKSERVER in _describe(p) for p in tree) == 3, (
            "expected the forkserver and 2 workers alive while their owner lives", [_describe(p) for p in tree])
        owner.kill()
        owner.wait(10)
        deadline = time.monotonic() + 2.0
        while any(_alive(p) for p in tree) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [_describe(p) for p in tree if _alive(p)]
    finally:
        owner.stdout.close()
        for proc in _session_processes(owner.pid):
            try:
                proc.kill()
            except psutil.Error:
                pass


def test_a_worker_whose_owner_is_already_gone_exits():
    """The owner died before the worker armed its parent-death signal: the worker exits at once."""
    not_an_ancestor = subprocess.Popen([sys.executable, "-c", "pass"])
    not_an_ancestor.wait()
    code = ("import sys; from skinstretch.experiments.process_lifetime import die_with_parent\n"
            f"die_with_parent({not_an_ancestor.pid}); sys.exit(0)")
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 1
    code = ("import os, sys; from skinstretch.experiments.process_lifetime import die_with_parent\n"
            "die_with_parent(os.getppid()); sys.exit(0)")
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0


def test_the_process_tree_guard_ends_with_its_process_and_says_nothing():
    """The watcher outlives the guarded process on purpose: started as a Popen, every in-process command (the test
    suite's) ended with "ResourceWarning: subprocess N is still running" at interpreter exit."""
    code = ("from skinstretch.experiments.process_lifetime import guard_process_tree as g\n"
            "pid = g()\nassert pid and g() == pid\nprint(pid)")
    done = subprocess.run([sys.executable, "-X", "dev", "-W", "error", "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    watcher = int(done.stdout)
    deadline = time.monotonic() + 10
    while psutil.pid_exists(watcher) and psutil.Process(watcher).status() != psutil.STATUS_ZOMBIE:
        assert time.monotonic() < deadline, "the watcher outlived its process by 10 s"
        time.sleep(0.05)

"""The one way the analysis runs in parallel: a :class:`concurrent.futures.Executor`, chosen once per run.

:func:`make_executor` turns :class:`~skinstretch.experiments.analysis.parameters.ExecutionParams` into an executor
at the edge (the command line, the recorder's analysis process, a Dask task, a user's script) and the analysis only
ever calls ``submit`` on what it is given. Three kinds:

* ``processes``: worker processes started on first use, from the pool every skinstretch process pool comes from
  (:func:`skinstretch.experiments.process_lifetime.worker_pool`: forked from a clean forkserver that has imported
  the measurement once; each worker, and the forkserver, dies with the analysis whatever kills it).
* ``threads`` of this process (OpenCV and the compiled kernels release the GIL);
* ``serial``: every task runs in the caller, at once (:class:`InlineExecutor`; the standard library has none).

No nesting: in a worker process (the recorder's analysis process, a Dask worker) ``processes`` becomes
``threads``, so an analysis keeps to the worker it was given.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import sys
import threading
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any, Callable

from skinstretch.experiments.process_lifetime import worker_pool

__all__ = ["make_executor", "InlineExecutor", "WorkerProcesses", "in_worker_process", "describe_executor"]

log = logging.getLogger(__name__)


def in_worker_process() -> bool:
    """True in a process started by multiprocessing (or a Dask worker): its analysis keeps to threads."""
    return mp.parent_process() is not None


class InlineExecutor(Executor):
    """Runs each task in the caller when it is submitted (the ``serial`` kind)."""

    def submit(self, fn: Callable, /, *args: Any, **kwargs: Any) -> Future:
        f: Future = Future()
        try:
            f.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller through the future, as executors do
            f.set_exception(exc)
        return f


class WorkerProcesses(Executor):
    """A pool of ``workers`` processes started on first use, each bound to this process' life (module docstring)."""

    def __init__(self, workers: int) -> None:
        self.workers = int(workers)
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def _get(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                pool = worker_pool(self.workers, preload=["skinstretch.experiments.analysis.measure"],
                                   initializer=_one_opencv_thread)
                # Every worker is started now, while the caller's main script is hidden (see _main_script_hidden).
                with _main_script_hidden():
                    started = [pool.submit(os.getpid) for _ in range(self.workers)]
                    for f in started:
                        f.result()
                self._pool = pool
            return self._pool

    def submit(self, fn: Callable, /, *args: Any, **kwargs: Any) -> Future:
        return self._get().submit(fn, *args, **kwargs)

    def pids(self) -> list[int]:
        """Process ids of the running workers (none before first use)."""
        pool = self._pool
        return sorted(getattr(pool, "_processes", {}) or {}) if pool is not None else []

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(wait=wait, cancel_futures=cancel_futures)
                self._pool = None


def make_executor(execution) -> Executor:
    """The executor for ``execution`` (an :class:`ExecutionParams`); use it as a context manager so that it is shut
    down at the end of the run."""
    kind, workers = execution.kind, int(execution.workers)
    if kind == "processes" and in_worker_process():
        log.debug("in a worker process: the analysis runs on %d threads of it", workers)
        kind = "threads"
    if kind == "serial" or (kind == "threads" and workers == 1):
        return InlineExecutor()
    if kind == "threads":
        return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="analysis")
    return WorkerProcesses(workers)


def describe_executor(executor: Executor) -> str:
    """How the measurement ran, for the results' parameters."""
    if isinstance(executor, WorkerProcesses):
        return f"processes ({executor.workers})"
    if isinstance(executor, ThreadPoolExecutor):
        return f"threads ({executor._max_workers})"
    if isinstance(executor, InlineExecutor):
        return "serial"
    return type(executor).__name__


def executor_width(executor: Executor) -> int:
    """How many tasks ``executor`` runs at once (1 for one it cannot tell)."""
    if isinstance(executor, WorkerProcesses):
        return executor.workers
    if isinstance(executor, ThreadPoolExecutor):
        return int(executor._max_workers)
    return 1


# -- in each worker process --------------------------------------------------------------------------------------


def _one_opencv_thread() -> None:
    """Each worker uses one OpenCV thread (the parallelism is the processes). Compiled kernels are not loaded ahead:
    a worker loads those its tasks call (a flow run's workers never hold the feature method's, ~65 MB each)."""
    import cv2  # noqa: PLC0415

    cv2.setNumThreads(1)


@contextmanager
def _main_script_hidden():
    """While workers start, the main module looks like an interactive session's (no file, no spec).

    A started process otherwise runs the caller's main script again, as ``__mp_main__``, to find functions
    defined there: a lab script that calls the analysis at top level, without ``if __name__ == "__main__"``,
    would run in every worker. The workers only run the analysis' functions, so they never need it.
    """
    main = sys.modules.get("__main__")
    if main is None:
        yield
        return
    saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if k in main.__dict__}
    main.__dict__.pop("__file__", None)
    main.__dict__["__spec__"] = None
    try:
        yield
    finally:
        main.__dict__.pop("__spec__", None)
        main.__dict__.update(saved)

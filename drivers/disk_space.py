"""Disk space for recordings: refuse what cannot fit, and keep the room to close a file cleanly if the disk fills.

Why this module exists: HDF5 does not survive running out of space. Measured here (h5py 3 / HDF5 1.14, SWMR
writer, 640x484 frames onto a 30 MB tmpfs): the flush that meets ENOSPC raises ``RuntimeError ("Unable to
synchronously flush file ... errno = 28")``, closing the file then fails too ("Can't decrement id ref count"),
the file stays open inside the library, and the process dies with a segmentation fault when the interpreter
exits. If space is freed before the next attempt, the same flush and the close succeed and the file opens in
another process with every frame flushed before the failure. So a recording:

* checks before it starts that it fits (:func:`check_fits`, with the expected size of
  :func:`skinstretch.drivers.session_file.expected_session_bytes`);
* holds a :class:`SpaceReserve` (a few MB allocated next to its file with ``posix_fallocate``) while it writes;
* checks the free space before every write (:func:`free_bytes`, one ``statvfs``: microseconds) and stops, with
  :class:`~skinstretch.drivers.errors.DiskFullError`, before a write could meet ENOSPC;
* if another process fills the disk anyway between the check and the write, releases the reserve and retries
  the flush, then closes the file marked failed.

The free space comes from psutil (``disk_usage``); the reserve is hand-written around ``os.posix_fallocate``
(no library keeps such a reserve).
"""

from __future__ import annotations

import errno
import logging
import os
import time
from pathlib import Path
from typing import Any, Callable

import psutil

from skinstretch.drivers.errors import DiskFullError

__all__ = ["free_bytes", "check_fits", "SpaceReserve", "is_disk_full", "megabytes", "DEFAULT_RESERVE_BYTES",
           "close_on_a_full_disk", "unclosed_files", "CLOSE_RETRY_S"]

log = logging.getLogger(__name__)

#: Reserve held by a session writer: its chunk caches (1 MB per dataset) and metadata fit in it several times.
DEFAULT_RESERVE_BYTES = 4 << 20


def megabytes(n: float) -> str:
    """``n`` bytes as "12.3 MB" (10^6 bytes, as df -H and file managers show them)."""
    return f"{n / 1e6:.1f} MB"


def free_bytes(path: str | os.PathLike) -> int:
    """Bytes an unprivileged writer may still use on the file system holding ``path`` (or its nearest existing
    ancestor)."""
    try:
        return int(psutil.disk_usage(os.fspath(path)).free)  # statvfs: f_bavail * f_frsize; microseconds
    except FileNotFoundError:
        p = Path(path)
        while not p.exists() and p.parent != p:
            p = p.parent
        return int(psutil.disk_usage(str(p)).free)


def check_fits(path: str | os.PathLike, needed_bytes: float, *, what: str) -> int:
    """Refuse (DiskFullError, one line naming ``path``) when ``needed_bytes`` do not fit; returns the free bytes."""
    free = free_bytes(path)
    if needed_bytes > free:
        raise DiskFullError(f"{path}: {megabytes(needed_bytes)} needed for {what}, only {megabytes(free)} free on "
                            "that disk; free some space or record elsewhere (-o)")
    return free


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` says the disk is full: DiskFullError, an OSError ENOSPC / EDQUOT, or HDF5's error text
    carrying ``errno = 28`` (h5py raises RuntimeError or OSError with the C library's errno in the message)."""
    if isinstance(exc, DiskFullError):
        return True
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    text = str(exc)
    return isinstance(exc, (OSError, RuntimeError)) and (
        f"errno = {errno.ENOSPC}," in text or "No space left on device" in text)


class SpaceReserve:
    """``nbytes`` allocated in a hidden file next to ``path`` until :meth:`release` (idempotent) deletes it.

    Creating it needs the space: DiskFullError when the disk cannot give it (nothing is left behind). A reserve
    left by a killed process is replaced.
    """

    def __init__(self, path: str | os.PathLike, nbytes: int = DEFAULT_RESERVE_BYTES) -> None:
        target = Path(path)
        self.path = target.with_name(f".{target.name}.reserve")
        self.nbytes = int(nbytes)
        self._held = False
        if self.nbytes <= 0:
            return
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        except OSError as exc:
            raise DiskFullError(f"{self.path}: cannot create the disk reserve ({exc.strerror})") from None
        try:
            try:
                os.posix_fallocate(fd, 0, self.nbytes)
            except OSError as exc:
                if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL):
                    raise
                _write_zeros(fd, self.nbytes)  # a file system without fallocate
            self._held = True
        except OSError as exc:
            os.close(fd)
            self._unlink()
            if is_disk_full(exc):
                raise DiskFullError(f"{target}: no room for the {megabytes(self.nbytes)} kept to close the file "
                                    "cleanly; the disk is full") from None
            raise
        os.close(fd)

    @property
    def held(self) -> bool:
        return self._held

    def release(self) -> bool:
        """Give the space back to the file system (returns whether there was any to give)."""
        if not self._held:
            return False
        self._held = False
        self._unlink()
        return True

    def _unlink(self) -> None:
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
        except OSError as exc:  # the space may stay taken; the caller's close will tell
            log.warning("could not remove the disk reserve %s: %s", self.path, exc)

    def __enter__(self) -> "SpaceReserve":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _write_zeros(fd: int, nbytes: int) -> None:
    block = bytes(1 << 20)
    left = nbytes
    while left > 0:
        left -= os.write(fd, block[: min(left, len(block))])
    os.fsync(fd)


#: How long :func:`close_on_a_full_disk` waits for space to come back when even the reserve was not enough.
CLOSE_RETRY_S = 1.0
_UNCLOSED: list[tuple[Path, Any]] = []  # and the objects kept alive with each


def close_on_a_full_disk(f: Any, path: str | os.PathLike, *, last_writes: Callable[[], None] = lambda: None,
                         reserve: SpaceReserve | None = None, lost: str, keep: Any = None) -> None:
    """Make ``last_writes`` and close the HDF5 file ``f`` (an ``h5py.File``); while the disk is full (``reserve``
    given back first), retry the writes and the flush for up to ``CLOSE_RETRY_S`` (space may come back) before
    giving up with DiskFullError naming ``path`` and what is ``lost``. The handle then stays open, listed by
    :func:`unclosed_files`: closing it would fail and leave HDF5 unable to shut down. It is kept alive with
    ``keep`` (the owner of its dataset handles) until the process ends: a dataset handle dropped on a full disk
    prints h5py's "Exception ignored" tracebacks."""
    deadline = time.monotonic() + CLOSE_RETRY_S
    while True:
        try:
            last_writes()
            f.flush()
            break
        except (OSError, RuntimeError) as exc:
            if not is_disk_full(exc):
                f.close()
                raise
            if reserve is not None:
                reserve.release()
            if time.monotonic() >= deadline:
                _UNCLOSED.append((Path(path), (f, keep)))
                raise DiskFullError(f"{path}: disk full for {CLOSE_RETRY_S:g} s, the file cannot be closed ({lost})"
                                    ) from None
            time.sleep(0.05)
    f.close()


def unclosed_files() -> list[Path]:
    """HDF5 files this process could not close because the disk stayed full (normally none).

    HDF5 keeps such a file open, and crashes while shutting down the library at interpreter exit; a program that
    sees any should end with ``os._exit`` once its output is flushed (the command line does).
    """
    return [path for path, _ in _UNCLOSED]

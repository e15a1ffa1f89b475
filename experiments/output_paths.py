"""Output paths, checked before anything is recorded or any device is opened: one line naming the path and what
is wrong with it (read-only file system, no permission, a file where a directory is expected, an output that
exists already, no space left).

Every command that writes uses these two checks first (``record``, ``play``, ``simulate``, ``analyze``,
``calibrate``, ``flow``):

* :func:`check_output_dir` for a directory that will receive files (created later by the caller);
* :func:`check_output_file` for a new file: an existing one is refused, naming the argument that replaces it
  (:data:`REPLACE_IT`: ``--overwrite``) where the caller allows that (docs/experiments.md, "Outputs that exist
  already");
* :func:`hold_output_dir` while writing into a directory that only one writer may use at a time (an analysis'
  OUTDIR): a second writer is refused at once, naming the first.

Both test for real: a throw-away file is created and removed in the nearest existing directory, because
permission bits do not tell (root ignores them, a read-only mount or a full disk does not show in them). Nothing
is created that the check does not remove. :func:`os_error_line` turns an ``OSError`` met later (while writing)
into the same kind of line.

>>> check_output_file("/proc/version")
Traceback (most recent call last):
...
skinstretch.experiments.output_paths.OutputPathError: /proc/version: exists already; choose another name (nothing is overwritten)
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import socket
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from skinstretch.processing.errors import ConfigError, Remedy

__all__ = ["OutputDirBusyError", "OutputPathError", "REPLACE_IT", "check_output_dir", "check_output_file",
           "hold_output_dir", "os_error_line"]

log = logging.getLogger(__name__)

#: The remedy of an output that exists already, for a writer that may replace it: ``overwrite=True`` in Python,
#: ``--overwrite`` on the command line (docs/experiments.md, "Outputs that exist already").
REPLACE_IT = Remedy(("overwrite",), "to replace it", True)

_PROBLEMS = {
    errno.EROFS: "is on a read-only file system",
    errno.EACCES: "no permission to write there",
    errno.EPERM: "no permission to write there",
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.ENOTDIR: "a part of the path is a file, not a directory",
    errno.ENAMETOOLONG: "the name is too long",
    errno.ELOOP: "too many symbolic links",
}


class OutputPathError(ConfigError):
    """An output path cannot be written; the message is ``PATH: what is wrong``."""


def os_error_line(exc: OSError, path: str | os.PathLike | None = None) -> str:
    """``PATH: what is wrong`` for an OSError met while writing (the path from the error when not given)."""
    where = path if path is not None else (exc.filename or "?")
    return f"{where}: {_PROBLEMS.get(exc.errno, exc.strerror or str(exc))}"


def _nearest_existing(path: Path) -> Path:
    """``path`` or its closest existing ancestor; OutputPathError when something on the way is not a directory."""
    probe = path
    while True:
        try:
            if probe.exists():
                break
        except OSError as exc:  # e.g. no permission to look inside the parent
            raise OutputPathError(os_error_line(exc, probe)) from None
        if probe.is_symlink():
            raise OutputPathError(f"{probe}: is a dangling symbolic link")
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe != path and not probe.is_dir():
        raise OutputPathError(f"{probe}: is a file, not a directory (on the way to {path})")
    return probe


def _probe_writable(directory: Path, target: Path) -> None:
    """Create and remove a file in ``directory``; OutputPathError naming ``target`` when that fails."""
    try:
        fd, name = tempfile.mkstemp(dir=directory, prefix=".skinstretch-write-test-")
    except OSError as exc:
        detail = "" if directory == target else f" (checked at {directory})"
        raise OutputPathError(f"{target}: {_PROBLEMS.get(exc.errno, exc.strerror or str(exc))}{detail}") from None
    os.close(fd)
    os.unlink(name)


def check_output_dir(path: str | os.PathLike, *, must_be_empty: bool = False, remedy: Remedy | None = None) -> Path:
    """Check that files can be written into directory ``path`` (existing, or creatable: its nearest existing
    ancestor is a writable directory). Returns ``path`` as a Path; nothing is left behind.

    ``must_be_empty``: an existing directory holding anything is an error (``remedy``: the argument that allows
    it, named as the caller spells it, e.g. ``--resume`` on the command line).
    """
    path = Path(path)
    base = _nearest_existing(path)
    if base == path:
        if not path.is_dir():
            raise OutputPathError(f"{path}: is a file, not a directory")
        if must_be_empty:
            try:
                occupied = any(path.iterdir())
            except OSError as exc:
                raise OutputPathError(os_error_line(exc, path)) from None
            if occupied:
                raise OutputPathError(f"{path}: is not empty", remedy=remedy)
    _probe_writable(base, path)
    return path


def check_output_file(path: str | os.PathLike, *, overwrite: bool = False, remedy: Remedy | None = None) -> Path:
    """Check that a new file ``path`` can be written: not a directory, not an existing file (unless
    ``overwrite``), in a directory that exists or can be created and is writable. Returns ``path`` as a Path.

    ``remedy``: the argument that allows replacing an existing file, named as the caller spells it (e.g.
    ``--overwrite`` on the command line); without one, an existing file is never overwritten.
    """
    path = Path(path)
    try:
        exists = path.exists()
    except OSError as exc:
        raise OutputPathError(os_error_line(exc, path)) from None
    if exists and path.is_dir():
        raise OutputPathError(f"{path}: is a directory, not a file")
    if exists and not overwrite:
        if remedy is not None:
            raise OutputPathError(f"{path}: exists already", remedy=remedy)
        raise OutputPathError(f"{path}: exists already; choose another name (nothing is overwritten)")
    base = _nearest_existing(path.parent)
    if base == path.parent and not base.is_dir():
        raise OutputPathError(f"{base}: is a file, not a directory (on the way to {path})")
    _probe_writable(base, path)
    return path


#: The lock file a writer holds in its output directory (:func:`hold_output_dir`); removed when it is done.
LOCK_FILE = ".skinstretch-lock"


class OutputDirBusyError(OutputPathError):
    """Another program is writing into this output directory now; the message names the directory and it."""


@contextmanager
def hold_output_dir(path: str | os.PathLike, *, holder: str) -> Iterator[Path]:
    """Hold directory ``path`` for this writer alone while the block runs; OutputDirBusyError at once, naming the
    directory and who holds it, when another writer holds it.

    The directory is checked (:func:`check_output_dir`) and created; the lock is the kernel's (``flock`` on
    ``path/.skinstretch-lock``, which names ``holder``, the process and the host), so a holder that dies, even by
    SIGKILL, lets go of it at once: the file it leaves behind is recognised as stale and taken over. Two analyses
    started into one directory used to wipe each other's work in progress and leave no result. A directory this
    call created is removed again if it is still empty at the end (a refused run leaves nothing).
    """
    path = check_output_dir(path)
    created = not path.exists()
    path.mkdir(parents=True, exist_ok=True)
    lock = path / LOCK_FILE
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            other = os.read(fd, 512).decode("utf-8", "replace").strip() or "another program (starting)"
            os.close(fd)
            raise OutputDirBusyError(f"{path}: in use by {other}; wait for it to end or write elsewhere") from None
        try:  # the holder before may have removed the file between our open and our lock: lock the one on disk
            if os.fstat(fd).st_ino == os.stat(lock).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    try:
        stale = os.read(fd, 512).decode("utf-8", "replace").strip()
        if stale:
            log.info("%s: taking over the lock left by %s (gone)", path, stale)
        os.ftruncate(fd, 0)
        os.pwrite(fd, (f"{holder} (pid {os.getpid()} on {socket.gethostname()}, since "
                       f"{time.strftime('%Y-%m-%d %H:%M:%S')})\n").encode(), 0)
        yield path
    finally:
        lock.unlink(missing_ok=True)  # before letting go: a writer waiting on this file then opens a new one
        os.close(fd)
        if created:
            with contextlib.suppress(OSError):
                path.rmdir()  # only when empty

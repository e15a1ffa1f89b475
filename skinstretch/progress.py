"""The one progress bar of skinstretch (tqdm on standard error), or a silent stand-in when it is switched off.

Long computations (simulating, analysing, importing) take ``progress=True/False``; the command line switches
bars off with ``--quiet``. Callers always get an object with ``update(n)``, ``close()`` and context-manager use.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from typing import Any, Iterator

__all__ = ["progress_bar", "logging_above_bars"]


class _NoBar:
    n = 0

    def update(self, n: int = 1) -> None:
        self.n += n

    def close(self) -> None:
        pass

    def __enter__(self) -> "_NoBar":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def progress_bar(total: int | None, *, enabled: bool, desc: str, unit: str = "frame") -> Any:
    """A tqdm bar of ``total`` steps when ``enabled``, otherwise a stand-in that only counts."""
    if not enabled:
        return _NoBar()
    from tqdm import tqdm  # noqa: PLC0415 - only when a bar is shown

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False)


@contextlib.contextmanager
def logging_above_bars(enabled: bool) -> Iterator[None]:
    """While a bar is shown, skinstretch's log lines go above it on a line of their own (tqdm clears the bar, writes
    the line, draws the bar again) instead of being appended to the bar's line. Nothing changes when ``enabled``
    is False."""
    if not enabled:
        yield
        return
    from tqdm.contrib.logging import logging_redirect_tqdm  # noqa: PLC0415

    with logging_redirect_tqdm(loggers=[logging.getLogger("skinstretch")]):
        yield

"""``njit``: numba's compiler with an on-disk cache that can never make a call fail.

numba's ``cache=True`` names its cache files after the source file (``pores._small_blobs-52.py311.nbi`` in
``processing/__pycache__``) but stores the importing module's name inside them. A kernel compiled once while its
file was imported under another name (``pores`` from inside ``processing/``, a doctest run, a helper script) leaves
an entry that every later ``processing.pores`` import fails to load, with ``ModuleNotFoundError: No module named
'pores'`` from the first call. Parallel test workers writing the same entry can likewise leave one unreadable.

Here an entry that cannot be loaded is treated as missing: the kernel is compiled again and the entry rewritten.
A failure to write the cache (read-only checkout) only costs the compilation next time.
"""

from __future__ import annotations

import warnings

import numba

try:  # numba's internal cache class; without it (another numba layout) plain cache=True is used
    from numba.core.caching import FunctionCache
    from numba.core.dispatcher import Dispatcher
except ImportError:  # pragma: no cover - depends on the installed numba
    FunctionCache = Dispatcher = None

__all__ = ["njit"]


class _TolerantCache(FunctionCache or object):
    """numba's per-function disk cache, with load and save failures turned into cache misses."""

    def load_overload(self, sig, target_context):
        try:
            return super().load_overload(sig, target_context)
        except Exception:  # noqa: BLE001 - any unreadable entry (foreign module name, truncated file) is a miss
            return None

    def save_overload(self, sig, data):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", numba.NumbaWarning)
                super().save_overload(sig, data)
        except Exception:  # noqa: BLE001 - not writable: compile again next time
            pass


def njit(*args, cache: bool = True, **options):
    """``numba.njit`` with the tolerant disk cache (``cache=True``, the default here); same arguments otherwise.

    Usable bare (``@njit``) or with options (``@njit(nogil=True)``).
    """

    def decorate(func):
        if FunctionCache is None or not hasattr(Dispatcher, "enable_caching"):
            return numba.njit(cache=cache, **options)(func)  # pragma: no cover - other numba versions
        dispatcher = numba.njit(**options)(func)
        if cache:
            try:
                # What Dispatcher.enable_caching() does, with the tolerant cache class.
                dispatcher._cache = _TolerantCache(dispatcher.py_func)
            except RuntimeError:
                pass  # no file to cache next to (a function defined in an interactive session): compile only
        return dispatcher

    if args:
        if len(args) == 1 and callable(args[0]) and not options:
            return decorate(args[0])
        raise TypeError("njit takes the function alone or keyword options only")
    return decorate

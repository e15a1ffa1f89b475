"""``njit``: numba's compiler with an on-disk cache that can never make a call fail.

numba's ``cache=True`` names its cache files after the source file (``pores._small_blobs-52.py311.nbi`` in
``processing/__pycache__``) but stores the importing module's name inside them. A kernel compiled once while its
file was imported under another name (``pores`` from inside ``processing/``, a doctest run, a helper script) leaves
an entry that every later ``skinstretch.processing.pores`` import fails to load, with ``ModuleNotFoundError: No module named
'pores'`` from the first call. Parallel test workers writing the same entry can likewise leave one unreadable.

Here an entry that cannot be loaded is treated as missing: the kernel is compiled again and the entry rewritten.
A failure to write the cache (read-only checkout) only costs the compilation next time. An entry is also keyed on
the compiled functions it calls from other files, which numba's own key leaves out (:func:`_callee_fingerprint`).
"""

from __future__ import annotations

import hashlib
import logging
import warnings

import numba

try:  # numba's internal cache class; without it (another numba layout) plain cache=True is used
    from numba.core.caching import FunctionCache
    from numba.core.dispatcher import Dispatcher
except ImportError:  # pragma: no cover - depends on the installed numba
    FunctionCache = Dispatcher = None

__all__ = ["njit", "announce_compilation"]

log = logging.getLogger(__name__)


def _callee_fingerprint(py_func) -> str:
    """A hash of the compiled functions ``py_func`` calls (found among its globals, recursively): their bytecode,
    constants and the plain values they read from their modules.

    numba keys a cache entry on the function's own bytecode and invalidates it when the function's file changes,
    but a compiled callee from another file is linked into the entry: after an edit of that file the caller would
    keep running the old callee (``skinstretch.processing.stretch`` calls ``skinstretch.processing.delaunay``'s triangulation). With this
    fingerprint in the key, such an entry is a miss and is compiled again.
    """
    parts: list[bytes] = []
    seen: set[int] = set()

    def visit(func) -> None:
        code = getattr(func, "__code__", None)
        if code is None or id(code) in seen:
            return
        seen.add(id(code))
        glb = getattr(func, "__globals__", {})
        for name in code.co_names:
            value = glb.get(name)
            target = getattr(value, "py_func", None)  # a numba dispatcher
            if target is not None:
                parts.append(f"{name}:{target.__module__}.{target.__qualname__}".encode())
                parts.append(target.__code__.co_code)
                parts.append(_canonical([c for c in target.__code__.co_consts if not hasattr(c, "co_code")]).encode())
                visit(target)
            elif func is not py_func and isinstance(value, (int, float, bool, str, bytes, tuple)):
                # A callee's module constants are frozen into the caller's code (the caller's own are covered by
                # its file's stamp).
                parts.append(f"{name}={_canonical(value)}".encode())

    visit(py_func)
    return hashlib.sha256(b"\0".join(parts)).hexdigest()


def _canonical(value) -> str:
    """``repr`` that is the same in every process: set constants (``x in {"a", "b"}``) iterate in an order that
    changes with the string hash seed."""
    if isinstance(value, (set, frozenset)):
        return "{" + ",".join(sorted(_canonical(v) for v in value)) + "}"
    if isinstance(value, (list, tuple)):
        return "(" + ",".join(_canonical(v) for v in value) + ")"
    return repr(value)


class _TolerantCache(FunctionCache or object):
    """numba's per-function disk cache, with load and save failures turned into cache misses, and entries keyed
    also on the compiled functions they call (:func:`_callee_fingerprint`)."""

    def _index_key(self, sig, codegen):
        key = super()._index_key(sig, codegen)
        try:
            return (*key[:-1], (*key[-1], _callee_fingerprint(self._py_func)))
        except Exception:  # noqa: BLE001 - an unusual function: numba's own key (its file stamp still applies)
            return key

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


class _FirstCompilation(numba.core.event.Listener):
    """Logs one line at the first kernel numba compiles in this process (not at one it loads from its cache)."""

    def __init__(self) -> None:
        self.said = False

    def on_start(self, event) -> None:
        if not self.said:
            self.said = True
            name = getattr(getattr(event.data.get("dispatcher"), "py_func", None), "__qualname__", "a kernel")
            log.warning("compiling the analysis' kernels (numba, starting with %s): this run is slower; `./run` "
                        "compiles them at set-up and later runs load them from the cache", name)

    def on_end(self, event) -> None:
        pass


_listener: _FirstCompilation | None = None


def announce_compilation() -> None:
    """From now on, say in one log line when this process compiles a kernel at run time (its disk cache missed:
    an install or an edit since ``./run`` set things up; ``python -m skinstretch.experiments.compile_kernels``).
    Idempotent."""
    global _listener
    if _listener is None:
        _listener = _FirstCompilation()
        numba.core.event.install_listener("numba:compile", _listener)


announce_compilation()  # every kernel's module imports this one: a compilation anywhere is announced

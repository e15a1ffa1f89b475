"""Exact percentiles of more values than the analysis holds (the summary's edge-change percentiles).

:class:`StreamedPercentiles` writes the values it is given to a scratch file and counts them in a histogram of the
top 16 bits of a sort key (the float's bits, made to order like the values). To find a rank, it reads the file
back a block at a time, narrowing the histogram bin that holds the rank by 16 more bits a pass, until the bin's
values fit in memory; at most four passes. The result is :func:`numpy.percentile`'s ("linear" method) to the bit:
the same two order statistics, interpolated by numpy itself. Hand-written: numpy and scipy need every value in
memory; the streaming estimators of other libraries (t-digest, P-square) are approximate.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from skinstretch.processing.errors import InsufficientDataError

__all__ = ["StreamedPercentiles"]

_BITS = 16
_BINS = 1 << _BITS
_SIGN = np.uint64(1 << 63)


def _keys(values: np.ndarray) -> np.ndarray:
    """uint64 keys that order like the float64 values (negative: every bit flipped; positive: sign bit set)."""
    u = values.view(np.uint64)
    return np.where(u & _SIGN, ~u, u | _SIGN)


def _values(keys: np.ndarray) -> np.ndarray:
    keys = np.asarray(keys, dtype=np.uint64)
    return np.where(keys & _SIGN, keys & ~_SIGN, ~keys).view(np.float64)


class StreamedPercentiles:
    """Values added in any number of blocks; :meth:`percentiles` as :func:`numpy.percentile` of them all.

    ``in_memory`` values at most are collected at once (the rest stays in the scratch file, in ``scratch_dir``;
    None: the system's temporary directory)."""

    def __init__(self, *, scratch_dir: str | os.PathLike | None = None, in_memory: int = 1 << 18,
                 block: int = 1 << 18) -> None:
        self._file = tempfile.TemporaryFile(dir=None if scratch_dir is None else Path(scratch_dir),
                                            prefix="skinstretch-values-")
        self._hist = np.zeros(_BINS, np.int64)
        self.count = 0
        self._nan = False
        self._in_memory = int(in_memory)
        self._block = int(block)

    def add(self, values: np.ndarray) -> None:
        v = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        if v.size == 0:
            return
        self._nan = self._nan or bool(np.isnan(v).any())
        self._file.write(v.tobytes())
        self._hist += np.bincount((_keys(v) >> np.uint64(64 - _BITS)).astype(np.int64), minlength=_BINS)
        self.count += v.size

    def _blocks(self) -> Iterator[np.ndarray]:
        self._file.flush()
        self._file.seek(0)
        while True:
            v = np.fromfile(self._file, dtype=np.float64, count=self._block)
            if v.size == 0:
                return
            yield v

    def _order_statistics(self, ranks: Sequence[int]) -> dict[int, float]:
        """Value of each 0-based rank in the sorted values."""
        out: dict[int, float] = {}
        # Each rank's search: the key bits fixed so far (prefix, their number) and the rank among the values
        # sharing them; the histogram of the next bits (level 0: the one counted while adding).
        search = {}
        for r in set(int(r) for r in ranks):
            cum = np.cumsum(self._hist)
            b = int(np.searchsorted(cum, r, side="right"))
            search[r] = (np.uint64(b), _BITS, r - int(cum[b] - self._hist[b]), int(self._hist[b]))
        while search:
            collect = {r: s for r, s in search.items() if s[3] <= self._in_memory or s[1] == 64}
            refine = {r: s for r, s in search.items() if r not in collect}
            for r, (prefix, bits, _, _) in list(collect.items()):
                if bits == 64:  # the whole key is known
                    out[r] = float(_values(prefix))
                    del collect[r]
            gathered = {r: [] for r in collect}
            hists = {r: np.zeros(_BINS, np.int64) for r in refine}
            if collect or refine:
                for v in self._blocks():
                    k = _keys(v)
                    for r, (prefix, bits, _, _) in collect.items():
                        gathered[r].append(v[(k >> np.uint64(64 - bits)) == prefix])
                    for r, (prefix, bits, _, _) in refine.items():
                        sel = k[(k >> np.uint64(64 - bits)) == prefix]
                        shift = np.uint64(64 - bits - _BITS)
                        nxt = ((sel >> shift) & np.uint64(_BINS - 1)).astype(np.int64)
                        hists[r] += np.bincount(nxt, minlength=_BINS)
            for r, (_, _, within, _) in collect.items():
                vals = np.concatenate(gathered[r])
                out[r] = float(np.partition(vals, within)[within])
            search = {}
            for r, (prefix, bits, within, _) in refine.items():
                h = hists[r]
                cum = np.cumsum(h)
                b = int(np.searchsorted(cum, within, side="right"))
                search[r] = ((prefix << np.uint64(_BITS)) | np.uint64(b), bits + _BITS, within - int(cum[b] - h[b]),
                             int(h[b]))
        return out

    def percentiles(self, q: Sequence[float]) -> list[float]:
        """:func:`numpy.percentile` of every value added, at ``q`` (percent), "linear" method."""
        n = self.count
        if n == 0:
            raise InsufficientDataError("no values to take percentiles of")
        if self._nan:
            return [float("nan")] * len(q)
        # numpy's virtual index, its two neighbours (clipped at the ends as numpy clips them) and weight
        vi = (n - 1) * (np.asarray(q, dtype=np.float64) / 100)
        prev = np.floor(vi)
        above = vi >= n - 1
        lo = np.where(above, n - 1, np.maximum(prev, 0)).astype(np.int64)
        hi = np.where(above, n - 1, np.minimum(prev + 1, n - 1)).astype(np.int64)
        gamma = np.where(above, 0.0, vi - prev)
        stats = self._order_statistics([*lo.tolist(), *hi.tolist()])
        return [float(np.quantile(np.array([stats[a], stats[b]]), g)) for a, b, g in zip(lo, hi, gamma)]

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "StreamedPercentiles":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

"""The renderer's per-pixel work (:mod:`skinstretch.simulators.scene`): compiled kernels (numba, nogil) and the
two bands of image rows they run on, in a shared thread pool.

- :func:`node_maps`: master-image coordinates of every pixel from the exact inverse deformation at nodes every
  8 px, by separable Catmull-Rom interpolation;
- :func:`compose_radiance`: print, contact and glass-fixed light composed into the scene radiance;
- :func:`row_bands` / :func:`run_bands`: the bands and the pool (a forked child makes its own).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor, wait

import numba
import numpy as np

N_BANDS = 2
_POOL: ThreadPoolExecutor | None = None
_POOL_PID = 0
_POOL_LOCK = threading.Lock()


def row_bands(height: int, n_bands: int) -> list[tuple[int, int]]:
    """(first row, end row) of ``n_bands`` bands of image rows."""
    bands = [(i * height // n_bands, (i + 1) * height // n_bands) for i in range(n_bands)]
    return [b for b in bands if b[1] > b[0]]


def run_bands(fn, bands, threads: int) -> None:
    """fn(band) for every band, the first in this thread and the others in a shared pool when threads > 1."""
    if threads <= 1 or len(bands) == 1:
        for bd in bands:
            fn(bd)
        return
    global _POOL, _POOL_PID
    with _POOL_LOCK:
        if _POOL is None or _POOL_PID != os.getpid():  # a forked child does not inherit the pool's threads
            _POOL = ThreadPoolExecutor(max_workers=N_BANDS - 1, thread_name_prefix="scene-band")
            _POOL_PID = os.getpid()
    futures = [_POOL.submit(fn, bd) for bd in bands[1:]]
    try:
        fn(bands[0])
    finally:
        wait(futures)
    for f in futures:
        f.result()


@numba.njit(cache=True, nogil=True)
def _catmull_rom(f):  # pragma: no cover - compiled
    return (((-0.5 * f + 1.0) * f - 0.5) * f, (1.5 * f - 2.5) * f * f + 1.0, ((-1.5 * f + 2.0) * f + 0.5) * f,
            (0.5 * f - 0.5) * f * f)


@numba.njit(cache=True, nogil=True)
def node_maps(X, u0, s0, inv_step, r0, r1, width, n0, node_step):  # pragma: no cover - compiled
    """Master column / row maps (float32) of image rows r0..r1 from the skin points X (mm) at the nodes, by
    separable Catmull-Rom interpolation in float64. Node (i, j) of X is node row n0 + i; node (n, j) sits at pixel
    (node_step (j - 1), node_step (n - 1))."""
    nr = X.shape[0]
    h = r1 - r0
    cols = np.empty(width, dtype=np.int64)
    wx = np.empty((width, 4), dtype=np.float64)
    for j in range(width):
        t = j / node_step + 1.0
        c = int(np.floor(t))
        cols[j] = c - 1
        wx[j, 0], wx[j, 1], wx[j, 2], wx[j, 3] = _catmull_rom(t - c)
    tmp = np.empty((nr, 2, width), dtype=np.float64)  # every node row interpolated along x
    for i in range(nr):
        for ch in range(2):
            for j in range(width):
                c = cols[j]
                tmp[i, ch, j] = (wx[j, 0] * X[i, c, ch] + wx[j, 1] * X[i, c + 1, ch] + wx[j, 2] * X[i, c + 2, ch]
                                 + wx[j, 3] * X[i, c + 3, ch])
    mx = np.empty((h, width), dtype=np.float32)
    my = np.empty((h, width), dtype=np.float32)
    for i in range(h):
        t = (r0 + i) / node_step + 1.0
        a = int(np.floor(t))
        w0, w1, w2, w3 = _catmull_rom(t - a)
        a = a - 1 - n0
        for j in range(width):
            u = w0 * tmp[a, 0, j] + w1 * tmp[a + 1, 0, j] + w2 * tmp[a + 2, 0, j] + w3 * tmp[a + 3, 0, j]
            s = w0 * tmp[a, 1, j] + w1 * tmp[a + 1, 1, j] + w2 * tmp[a + 2, 1, j] + w3 * tmp[a + 3, 1, j]
            mx[i, j] = (u - u0) * inv_step
            my[i, j] = (s - s0) * inv_step
    return mx, my


@numba.njit(cache=True, nogil=True)
def compose_radiance(v, coverage, mx, my, surface_contact, gain, background, ridge, valley, u0, s0, step, a, b, edge,
                     out):  # pragma: no cover
    """Radiance = gain * (background + contact * (skin - background)), contact = soft ellipse * surface contact
    (* the print's coverage of the skin when ``coverage`` has the shape of ``v``; a real print's, see
    :mod:`skinstretch.simulators.print_texture`)."""
    h, w = v.shape
    rmean = 0.5 * (a + b)
    has_coverage = coverage.shape[0] == h and coverage.shape[1] == w
    for i in range(h):
        for j in range(w):
            du = (u0 + mx[i, j] * step) / a
            ds = (s0 + my[i, j] * step) / b
            q = (1.0 - np.sqrt(du * du + ds * ds)) * rmean / edge + 0.5
            q = 0.0 if q < 0.0 else (1.0 if q > 1.0 else q)
            contact = q * q * (3.0 - 2.0 * q) * surface_contact[i, j]
            if has_coverage:
                contact *= coverage[i, j]
            skin = ridge + (valley - ridge) * v[i, j]
            bg = background[i, j]
            out[i, j] = gain[i, j] * (bg + contact * (skin - bg))

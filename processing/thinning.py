"""Thinning of the binary valley image to an 8-connected, near-minimal skeleton (seed 4.6).

Modified Zhang-Suen thinning with the Ritter-Wilson conditions of seed Figure 26 (they keep 2x2 blocks from being
eroded away), followed by one deletion pass with each of the four staircase kernels of seed Figure 27, which remove
the corner pixels of staircases that would otherwise look like valley bifurcations.

Both are table driven: the 8 neighbours of a pixel form an 8-bit code (bit ``i - 1`` is the seed's ``p_i``:
p1 = N, p2 = NE, p3 = E, p4 = SE, p5 = S, p6 = SW, p7 = W, p8 = NW) and a 256-entry table says whether the pixel
may be deleted. The compiled loop only re-checks a pixel when its neighbourhood changed since its last check with
the same table, so the work is proportional to the foreground's contour plus the number of deletions.
"""

from __future__ import annotations

import numba
import numpy as np

from processing.errors import InvalidInputError

__all__ = ["thin", "zhang_suen_tables", "staircase_table", "neighbour_code"]



def _bits(code: int) -> list[int]:
    return [(code >> i) & 1 for i in range(8)]


def zhang_suen_tables() -> tuple[np.ndarray, np.ndarray]:
    """Deletion tables of the two passes of the modified Zhang-Suen algorithm (seed Figure 26(b)).

    Returns
    -------
    first, second : (256,) bool
        Whether a foreground pixel with that neighbour code is deleted in the first / second pass.
    """
    first = np.zeros(256, dtype=np.bool_)
    second = np.zeros(256, dtype=np.bool_)
    for code in range(256):
        p = [None] + _bits(code)  # p[1]..p[8] as in the seed
        n = sum(p[1:])
        t = sum(1 for i in range(1, 9) if p[i] == 0 and p[i % 8 + 1] == 1)
        common = 2 <= n <= 6 and t == 1
        first[code] = common and p[1] * p[3] * p[5] == 0 and p[3] * p[5] == 0
        second[code] = common and p[1] * p[3] * p[7] == 0 and p[1] * p[7] == 0
    return first, second


def staircase_table() -> np.ndarray:
    """(4, 256) bool: the four staircase deletion kernels of seed Figure 27(a).

    Kernel ``k`` deletes the centre when two orthogonal 4-neighbours are set and the three pixels opposite the
    corner they form are clear; the remaining ("don't care") pixels each touch one of the two set neighbours, so
    the deletion never changes connectivity nor moves a line end.
    """
    table = np.zeros((4, 256), dtype=np.bool_)
    # (set a, set b, clear x, clear y, clear z) as p indices, rotating N-E, E-S, S-W, W-N.
    kernels = [(1, 3, 5, 6, 7), (3, 5, 7, 8, 1), (5, 7, 1, 2, 3), (7, 1, 3, 4, 5)]
    for k, (a, b, x, y, z) in enumerate(kernels):
        for code in range(256):
            p = [None] + _bits(code)
            table[k, code] = p[a] == 1 and p[b] == 1 and p[x] == 0 and p[y] == 0 and p[z] == 0
    return table


_FIRST, _SECOND = zhang_suen_tables()
_STAIRS = staircase_table()


@numba.njit(cache=True, nogil=True, inline="always")
def neighbour_code(img, r, c):  # pragma: no cover - compiled
    """8-bit neighbour code of pixel (r, c); bit i-1 is p_i (p1 = N, clockwise)."""
    code = 0
    if img[r - 1, c]:
        code |= 1
    if img[r - 1, c + 1]:
        code |= 2
    if img[r, c + 1]:
        code |= 4
    if img[r + 1, c + 1]:
        code |= 8
    if img[r + 1, c]:
        code |= 16
    if img[r + 1, c - 1]:
        code |= 32
    if img[r, c - 1]:
        code |= 64
    if img[r - 1, c - 1]:
        code |= 128
    return code


@numba.njit(cache=True, nogil=True, inline="always")
def _code_flat(f, i, w):  # pragma: no cover - compiled
    return (
        f[i - w]
        | (f[i - w + 1] << 1)
        | (f[i + 1] << 2)
        | (f[i + w + 1] << 3)
        | (f[i + w] << 4)
        | (f[i + w - 1] << 5)
        | (f[i - 1] << 6)
        | (f[i - w - 1] << 7)
    )


@numba.njit(cache=True, nogil=True)
def _thin_zero_border(img, first, second, stairs):  # pragma: no cover - compiled
    """Thin ``img`` (0/1, zero outer ring) in place.

    Whether a pixel is deleted by a sub-iteration depends only on its neighbour code and on the sub-iteration's
    table. So a pixel is (re)checked with a table only when its neighbourhood changed since it was last checked
    with that table: the work list starts with the contour (an interior pixel, code 255, is never deletable) and a
    deletion puts the deleted pixel's 8 neighbours back on it. The result is that of checking every foreground
    pixel in every sub-iteration, at a cost proportional to the number of deletions.
    """
    h, w = img.shape
    f = img.ravel()
    n = h * w
    # pending bit 1: to check with the first table, bit 2: with the second; bit 4: on the work list.
    pend = np.zeros(n, np.uint8)
    n_fg = 0
    for i in range(n):
        if f[i]:
            n_fg += 1
    work = np.empty(n_fg, np.int32)
    dele = np.empty(n_fg, np.int32)
    n_work = 0
    for i in range(w, n - w):
        if f[i] and _code_flat(f, i, w) != 255:
            work[n_work] = i
            n_work += 1
            pend[i] = 7
    offs = np.array([-w - 1, -w, -w + 1, -1, 1, w - 1, w, w + 1])
    step = 0
    idle = 0
    while n_work > 0 and idle < 2:
        bit = 1 if step == 0 else 2
        table = first if step == 0 else second
        n_del = 0
        for k in range(n_work):
            i = work[k]
            if pend[i] & bit:
                pend[i] &= ~bit
                if table[_code_flat(f, i, w)]:
                    dele[n_del] = i
                    n_del += 1
        for k in range(n_del):
            f[dele[k]] = 0
            pend[dele[k]] = 0
        # Keep the pixels with a check still pending, then add the deleted pixels' neighbours (needing both).
        m = 0
        for k in range(n_work):
            i = work[k]
            if f[i] and pend[i] & 3:
                work[m] = i
                m += 1
            else:
                pend[i] &= 3
        n_work = m
        for k in range(n_del):
            i = dele[k]
            for j in range(8):
                q = i + offs[j]
                if f[q]:
                    if pend[q] & 4 == 0:
                        work[n_work] = q
                        n_work += 1
                    pend[q] = 7
        idle = idle + 1 if n_del == 0 else 0
        step = 1 - step
    # Staircase removal (seed Figure 27): one in-place pass per kernel over the skeleton, in raster order, so each
    # deletion is judged on the current skeleton and connectivity is preserved.
    n_sk = 0
    for i in range(n):
        if f[i]:
            dele[n_sk] = i
            n_sk += 1
    for s in range(4):
        for k in range(n_sk):
            i = dele[k]
            if f[i] and stairs[s, _code_flat(f, i, w)]:
                f[i] = 0
    return img


def thin(binary: np.ndarray) -> np.ndarray:
    """Thin a binary image to an 8-connected, near-minimal skeleton (seed 4.6).

    Parameters
    ----------
    binary : (H, W) uint8 or bool
        Foreground = non-zero (the valleys, with the blob pores already removed).

    Returns
    -------
    (H, W) uint8
        1 on the skeleton, 0 elsewhere. The outermost pixel ring of the image is always 0 (the seed treats the
        image edge as border, 4.8.6), which also lets the compiled code skip bounds checks.

    Examples
    --------
    >>> import numpy as np
    >>> b = np.zeros((9, 20), np.uint8); b[3:6, 2:18] = 1
    >>> s = thin(b)
    >>> int(s.sum()), int(s[:, 2:18].any(axis=0).sum())
    (14, 14)
    """
    if not isinstance(binary, np.ndarray) or binary.ndim != 2 or binary.dtype not in (np.uint8, np.bool_):
        raise InvalidInputError(
            f"binary must be a 2-D uint8 or bool image, got {getattr(binary, 'dtype', type(binary))}"
            f" {getattr(binary, 'shape', '')}"
        )
    if min(binary.shape) < 3:
        raise InvalidInputError(f"binary of shape {binary.shape} is too small to thin (needs at least 3x3)")
    img = (binary != 0).view(np.uint8).copy()
    img[0, :] = 0
    img[-1, :] = 0
    img[:, 0] = 0
    img[:, -1] = 0
    return _thin_zero_border(img, _FIRST, _SECOND, _STAIRS)

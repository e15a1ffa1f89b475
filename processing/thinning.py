"""Thinning of the binary valley image to an 8-connected, near-minimal skeleton (seed 4.6).

Modified Zhang-Suen thinning with the Ritter-Wilson conditions of seed Figure 26 (they keep 2x2 blocks from being
eroded away), followed by one deletion pass with each of the four staircase kernels of seed Figure 27, which remove
the corner pixels of staircases that would otherwise look like valley bifurcations.

Both are table driven: the 8 neighbours of a pixel form an 8-bit code (bit ``i - 1`` is the seed's ``p_i``:
p1 = N, p2 = NE, p3 = E, p4 = SE, p5 = S, p6 = SW, p7 = W, p8 = NW) and a 256-entry table says whether the pixel
may be deleted. The compiled loop only visits contour pixels: a pixel becomes a candidate when a neighbour is
reachable (bucketed by distance to the background), so the work is proportional to the foreground area plus the
skeleton length times the number of iterations.
"""

from __future__ import annotations

import cv2
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
def _thin_zero_border(img, depth, first, second, stairs):  # pragma: no cover - compiled
    """Thin ``img`` (0/1, zero outer ring) in place. ``depth`` is the chessboard distance to the background.

    A parallel sub-iteration only deletes pixels that touch the background at its start, so it peels at most one
    layer: a pixel at chessboard depth d cannot be deleted before sub-iteration d - 1. Pixels are therefore
    bucketed by depth and enter the candidate list when their layer can first be reached; deleted pixels leave it.
    """
    h, w = img.shape
    f = img.ravel()
    d = depth.ravel()
    n = h * w
    counts = np.zeros(256, np.int64)
    for i in range(n):
        if f[i]:
            counts[min(d[i], 255)] += 1
    start = np.zeros(257, np.int64)
    for v in range(256):
        start[v + 1] = start[v] + counts[v]
    total = start[256]
    order = np.empty(total, np.int32)
    pos = start[:256].copy()
    for i in range(n):
        if f[i]:
            v = min(d[i], 255)
            order[pos[v]] = i
            pos[v] += 1
    cand = np.empty(total, np.int32)
    dele = np.empty(total, np.int32)
    n_cand = 0
    level = 0
    sub = 0
    while True:
        changed = False
        for step in range(2):
            while level < 256 and level <= sub + 1:
                for k in range(start[level], start[level + 1]):
                    cand[n_cand] = order[k]
                    n_cand += 1
                level += 1
            sub += 1
            table = first if step == 0 else second
            n_del = 0
            m = 0
            for k in range(n_cand):
                i = cand[k]
                if table[_code_flat(f, i, w)]:
                    dele[n_del] = i
                    n_del += 1
                else:
                    cand[m] = i
                    m += 1
            n_cand = m
            for k in range(n_del):
                f[dele[k]] = 0
            if n_del:
                changed = True
        if not changed and (level >= 256 or start[level] == total):
            break
    # Staircase removal (seed Figure 27): one in-place pass per kernel over the skeleton, in raster order, so each
    # deletion is judged on the current skeleton and connectivity is preserved.
    skel = np.sort(cand[:n_cand])
    for s in range(4):
        for k in range(n_cand):
            i = skel[k]
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
    depth = cv2.distanceTransform(img, cv2.DIST_C, 3)
    depth = np.minimum(depth, 255).astype(np.uint8)
    return _thin_zero_border(img, depth, _FIRST, _SECOND, _STAIRS)

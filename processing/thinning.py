"""Thinning of the binary valley image to an 8-connected, near-minimal skeleton (seed 4.6).

Modified Zhang-Suen thinning with the Ritter-Wilson conditions of seed Figure 26 (they keep 2x2 blocks from being
eroded away), followed by one deletion pass with each of the four staircase kernels of seed Figure 27, which remove
the corner pixels of staircases that would otherwise look like valley bifurcations.

Both are defined by tables: the 8 neighbours of a pixel form an 8-bit code (bit ``i - 1`` is the seed's ``p_i``:
p1 = N, p2 = NE, p3 = E, p4 = SE, p5 = S, p6 = SW, p7 = W, p8 = NW) and a 256-entry table says whether the pixel
may be deleted. The Zhang-Suen passes run on bit-packed rows, 64 pixels per machine word, with the tables'
conditions written as bitwise logic (about 10 times faster than a per-pixel table lookup on a 640 x 484 frame);
the staircase passes, which are sequential, look the table up per skeleton pixel, found from the packed words one
set bit at a time. Packing and unpacking are numpy's packbits / unpackbits.

Hand-written because no library has these rules: ``cv2.ximgproc.thinning`` (Zhang-Suen, Guo-Hall) and
``skimage.morphology.thin`` / ``skeletonize`` leave out the Ritter-Wilson conditions and the staircase passes.
"""

from __future__ import annotations

import numpy as np

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit

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


_STAIRS = staircase_table()
_Z = np.uint64(0)
_ONE = np.uint64(1)
_S63 = np.uint64(63)


@njit(nogil=True, inline="always")
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


@njit(nogil=True, inline="always")
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


@njit(nogil=True, inline="always")
def _at_least_two(a, b, c, d, e, f, g, h):  # pragma: no cover - compiled
    """Bit-sliced counting of eight bit planes: (at least one set, at least two set), per bit."""
    ones = a
    twos = b & ones
    ones |= b
    twos |= c & ones
    ones |= c
    twos |= d & ones
    ones |= d
    twos |= e & ones
    ones |= e
    twos |= f & ones
    ones |= f
    twos |= g & ones
    ones |= g
    twos |= h & ones
    ones |= h
    return ones, twos


@njit(nogil=True)
def _zhang_suen_bits(bits, h, nw):  # pragma: no cover - compiled
    """Modified Zhang-Suen thinning of the bit-packed image ``bits`` (h, nw + 2) uint64, in place.

    64 pixels at a time: the eight neighbour planes are shifted copies of the rows above, at and below, and the
    deletion tests of :func:`zhang_suen_tables` are bitwise: 2 <= B <= 6 is "at least two neighbours set and at
    least two clear", A = 1 is "exactly one 0 -> 1 transition" around the ring, then p3 p5 = 0 (first pass) or
    p1 p7 = 0 (second pass). All deletions of a sub-iteration are decided on the image before it (the parallel
    algorithm). A word is only re-tested when a word of its 3 x 3 word neighbourhood changed during the last two
    sub-iterations (otherwise the same table would give the same answer as at its last test).
    """
    dl = np.zeros((h, nw + 2), np.uint64)
    chg = np.ones((h, nw + 2), np.uint8)  # changed in the last two sub-iterations (per word)
    new = np.zeros((h, nw + 2), np.uint8)
    prev_new = np.ones((h, nw + 2), np.uint8)
    step = 0
    idle = 0
    while idle < 2:
        n_del = 0
        for r in range(1, h - 1):
            for j in range(1, nw + 1):
                c = bits[r, j]
                dl[r, j] = _Z
                if c == _Z:
                    continue
                if not (chg[r - 1, j - 1] | chg[r - 1, j] | chg[r - 1, j + 1] | chg[r, j - 1] | chg[r, j]
                        | chg[r, j + 1] | chg[r + 1, j - 1] | chg[r + 1, j] | chg[r + 1, j + 1]):
                    continue
                u = bits[r - 1, j]
                d = bits[r + 1, j]
                p1 = u
                p2 = (u >> _ONE) | (bits[r - 1, j + 1] << _S63)
                p3 = (c >> _ONE) | (bits[r, j + 1] << _S63)
                p4 = (d >> _ONE) | (bits[r + 1, j + 1] << _S63)
                p5 = d
                p6 = (d << _ONE) | (bits[r + 1, j - 1] >> _S63)
                p7 = (c << _ONE) | (bits[r, j - 1] >> _S63)
                p8 = (u << _ONE) | (bits[r - 1, j - 1] >> _S63)
                _, two_set = _at_least_two(p1, p2, p3, p4, p5, p6, p7, p8)
                _, two_clear = _at_least_two(~p1, ~p2, ~p3, ~p4, ~p5, ~p6, ~p7, ~p8)
                t_any, t_two = _at_least_two(
                    ~p1 & p2, ~p2 & p3, ~p3 & p4, ~p4 & p5, ~p5 & p6, ~p6 & p7, ~p7 & p8, ~p8 & p1
                )
                m = c & two_set & two_clear & t_any & ~t_two
                if step == 0:
                    m &= ~(p3 & p5)
                else:
                    m &= ~(p1 & p7)
                dl[r, j] = m
        for r in range(1, h - 1):
            for j in range(1, nw + 1):
                m = dl[r, j]
                if m != _Z:
                    bits[r, j] &= ~m
                    new[r, j] = 1
                    n_del += 1
                else:
                    new[r, j] = 0
        for r in range(h):
            for j in range(nw + 2):
                chg[r, j] = new[r, j] | prev_new[r, j]
                prev_new[r, j] = new[r, j]
        idle = idle + 1 if n_del == 0 else 0
        step = 1 - step
    return bits


@njit(nogil=True)
def _staircases(out, sk, stairs):  # pragma: no cover - compiled
    """The staircase passes (seed Figure 27) on the unpacked skeleton ``out``, in place: one pass per kernel over
    the skeleton pixels ``sk`` (flat indices, raster order), each deletion judged on the current skeleton."""
    w = out.shape[1]
    f = out.ravel()
    for s in range(4):
        for k in range(sk.size):
            i = sk[k]
            if f[i] and stairs[s, _code_flat(f, i, w)]:
                f[i] = 0
    return out


_DEBRUIJN = np.uint64(0x03F79D71B4CB0A89)
#: Bit index of an isolated bit ``b`` (a power of two): ``_DEBRUIJN_INDEX[(b * _DEBRUIJN) >> 58]``.
_DEBRUIJN_INDEX = np.zeros(64, np.int64)
for _i in range(64):
    _DEBRUIJN_INDEX[int(((1 << _i) * 0x03F79D71B4CB0A89 % (1 << 64)) >> 58)] = _i


@njit(nogil=True)
def _set_bits(bits, w, table):  # pragma: no cover - compiled
    """Flat indices (raster order) of the set pixels of packed rows, one step per set bit (not per pixel)."""
    h = bits.shape[0]
    nw = bits.shape[1] - 2
    n = 0
    for r in range(h):
        for j in range(1, nw + 1):
            x = bits[r, j]
            while x != _Z:
                x &= x - _ONE
                n += 1
    out = np.empty(n, np.int64)
    k = 0
    for r in range(h):
        for j in range(1, nw + 1):
            x = bits[r, j]
            base = r * w + (j - 1) * 64
            while x != _Z:
                low = x & (~x + _ONE)
                out[k] = base + table[(low * _DEBRUIJN) >> np.uint64(58)]
                k += 1
                x ^= low
    return out


def _pack_rows(binary: np.ndarray, nw: int) -> np.ndarray:
    """(h, nw + 2) uint64 words of the non-zero pixels of ``binary`` (bit c % 64 of word 1 + c // 64), its outer
    pixel ring left out (zero): numpy's packbits, ~6x faster than a per-pixel loop."""
    h, w = binary.shape
    packed = np.packbits(binary.view(np.uint8) != 0, axis=1, bitorder="little")
    buf = np.zeros((h, (nw + 2) * 8), np.uint8)
    buf[:, 8 : 8 + packed.shape[1]] = packed
    bits = buf.view(np.uint64)
    bits[0] = 0
    bits[h - 1] = 0
    bits[:, 1] &= ~np.uint64(1)
    bits[:, 1 + (w - 1) // 64] &= ~(np.uint64(1) << np.uint64((w - 1) % 64))
    return bits


def _unpack_rows(bits: np.ndarray, w: int) -> np.ndarray:
    """The (h, w) uint8 0/1 image of packed rows (the inverse of :func:`_pack_rows`)."""
    nw = bits.shape[1] - 2
    return np.ascontiguousarray(np.unpackbits(bits[:, 1 : nw + 1].view(np.uint8), axis=1, bitorder="little")[:, :w])


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
    h, w = binary.shape
    nw = (w + 63) // 64
    # Bit-packed rows: pixel c of row r is bit c % 64 of word 1 + c // 64; words 0 and nw + 1 stay zero (so do
    # the outer pixel ring and the padding bits), so the neighbour shifts need no bounds checks.
    bits = _pack_rows(np.ascontiguousarray(binary), nw)
    _zhang_suen_bits(bits, h, nw)
    return _staircases(_unpack_rows(bits, w), _set_bits(bits, w, _DEBRUIJN_INDEX), _STAIRS)

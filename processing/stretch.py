"""Skin stretch from tracked points (seed 5.3): triangulation changes and local movement of skin patches.

* :func:`triangulation_strain` (seed 5.3.1): the points tracked from frame a to frame b are triangulated
  (Delaunay) in frame a; the triangulation is kept in frame b and the relative change of every edge length and
  triangle area is measured. Any span b - a works (the seed uses 1 and 11 frames).
* :func:`local_movement` (seed 5.3.2, Figure 59): average movement relative to the fingertip inside a disk.
* :func:`patch_area_change` (Figure 61): relative area change of the tetragon of 4 neighbouring patch centres.
* :func:`horizontal_stretch_profile` (Figure 62, 94): change in stretch along x from the average horizontal
  movement of two vertical strips of width w either side of each position.

Strains are fractions (0.01 = 1 %). Degenerate inputs raise :class:`InsufficientDataError` or are flagged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from skinstretch.processing.delaunay import _triangulate
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.jit import njit
from skinstretch.processing.tracking import MotionSample


@dataclass(frozen=True)
class TriangulationStrain:
    """Relative changes of a Delaunay triangulation between two frames (seed 5.3.1).

    Attributes
    ----------
    frame_a, frame_b : int
    ids : (n,) int64
        Ids (track indices) of the triangulated points.
    points : (n, 2) float64
        Their positions in frame a.
    triangles : (m, 3) int64
        Rows of ``points``, counter-clockwise on the image in frame a.
    edges : (e, 2) int64
        Rows of ``points``, each edge once.
    edge_length : (e,) float64
        Length in frame a, px.
    edge_change : (e,) float64
        ``L_b / L_a - 1``.
    area : (m,) float64
        Area in frame a, px^2.
    area_change : (m,) float64
        ``A_b / A_a - 1`` with signed areas: below -1 exactly where ``flipped``.
    flipped : (m,) bool
        The triangle changed orientation (a tracking error or a fold): its area change is not a strain.
    n_dropped : int
        Duplicate points and degenerate (zero-area) triangles left out.
    """

    frame_a: int
    frame_b: int
    ids: np.ndarray
    points: np.ndarray
    triangles: np.ndarray
    edges: np.ndarray
    edge_length: np.ndarray
    edge_change: np.ndarray
    area: np.ndarray
    area_change: np.ndarray
    flipped: np.ndarray
    n_dropped: int = 0


@njit(nogil=True)
def _distinct_finite(pa, d):  # pragma: no cover - compiled
    """Rows of ``pa`` (n, 2) with finite ``pa`` and ``d`` that are the first of their value rounded to 1e-6 px, in
    increasing order (what a lexsort of the rounded rows followed by run heads gives)."""
    n = pa.shape[0]
    fin = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        if np.isfinite(pa[i, 0]) and np.isfinite(pa[i, 1]) and np.isfinite(d[i, 0]) and np.isfinite(d[i, 1]):
            fin[m] = i
            m += 1
    fin = fin[:m]
    rx = np.empty(m)
    ry = np.empty(m)
    for k in range(m):
        rx[k] = np.round(pa[fin[k], 0], 6)
        ry[k] = np.round(pa[fin[k], 1], 6)
    # Sort by (x, y); stable, so the first row of a run of equal values has the smallest index.
    order = np.argsort(ry, kind="mergesort")
    order = order[np.argsort(rx[order], kind="mergesort")]
    keep = np.zeros(m, np.bool_)
    for k in range(m):
        j = order[k]
        if k == 0 or rx[j] != rx[order[k - 1]] or ry[j] != ry[order[k - 1]]:
            keep[j] = True
    return fin[keep]


@njit(nogil=True)
def _spaced(pa, rows, ids, min_spacing):  # pragma: no cover - compiled
    """The ``rows`` of ``pa`` kept when points are taken in increasing ``ids`` (the oldest tracks first) and a point
    closer than ``min_spacing`` to one already taken is left out; in increasing row order. A grid of cells
    at least ``min_spacing`` wide holds the points taken (each point looks at its 3 x 3 cells)."""
    m = rows.size
    if min_spacing <= 0 or m < 2:
        return rows
    x0 = np.inf
    y0 = np.inf
    x1 = -np.inf
    y1 = -np.inf
    for k in range(m):
        x0 = min(x0, pa[rows[k], 0])
        y0 = min(y0, pa[rows[k], 1])
        x1 = max(x1, pa[rows[k], 0])
        y1 = max(y1, pa[rows[k], 1])
    # Cells at least min_spacing wide (so a close point is in the 3 x 3 around), at most ~512 per side.
    cell = max(min_spacing, (x1 - x0) / 512.0, (y1 - y0) / 512.0)
    nx = int((x1 - x0) / cell) + 1
    ny = int((y1 - y0) / cell) + 1
    head = np.full(nx * ny, -1, np.int64)
    nxt = np.full(m, -1, np.int64)
    keep = np.zeros(m, np.bool_)
    s2 = min_spacing * min_spacing
    for k in np.argsort(ids[rows], kind="mergesort"):
        x, y = pa[rows[k], 0], pa[rows[k], 1]
        cx = int((x - x0) / cell)
        cy = int((y - y0) / cell)
        free = True
        for gy in range(max(cy - 1, 0), min(cy + 2, ny)):
            for gx in range(max(cx - 1, 0), min(cx + 2, nx)):
                j = head[gy * nx + gx]
                while j >= 0 and free:
                    dx = pa[rows[j], 0] - x
                    dy = pa[rows[j], 1] - y
                    if dx * dx + dy * dy < s2:
                        free = False
                    j = nxt[j]
        if free:
            keep[k] = True
            nxt[k] = head[cy * nx + cx]
            head[cy * nx + cx] = k
    return rows[keep]


@njit(nogil=True)
def _triangle_changes(pa, pb, tri, max_edge, min_area, min_quality):
    """After the Delaunay triangulation (in place on ``tri``): orient each triangle counter-clockwise on the image,
    leave out degenerate, long and sliver triangles, and measure the areas (frames a and b, signed in b) and the
    unique edges (sorted (low, high) rows) with their lengths in both frames. Signed area
    ``-((b - a) x (c - a)) / 2``: positive is counter-clockwise as seen on the image (y points down)."""
    m = tri.shape[0]
    keep = np.zeros(m, np.bool_)
    area_a = np.empty(m)
    q = 4.0 * np.sqrt(3.0)
    for t in range(m):
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        s = -0.5 * ((pa[b, 0] - pa[a, 0]) * (pa[c, 1] - pa[a, 1]) - (pa[c, 0] - pa[a, 0]) * (pa[b, 1] - pa[a, 1]))
        if s < 0:
            tri[t, 1], tri[t, 2] = c, b
        s = abs(s)
        area_a[t] = s
        ok = s >= min_area
        e2 = 0.0
        emax = 0.0
        for i in range(3):
            u, v = tri[t, i], tri[t, (i + 1) % 3]
            e = math.hypot(pa[u, 0] - pa[v, 0], pa[u, 1] - pa[v, 1])
            e2 += e * e
            emax = max(emax, e)
        ok = ok and emax <= max_edge
        if min_quality > 0:
            ok = ok and q * s >= min_quality * e2
        keep[t] = ok
    tri = tri[keep]
    area_a = area_a[keep]
    k = tri.shape[0]
    area_b = np.empty(k)
    n = pa.shape[0]
    keys = np.empty(3 * k, np.int64)
    for t in range(k):
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        area_b[t] = -0.5 * (
            (pb[b, 0] - pb[a, 0]) * (pb[c, 1] - pb[a, 1]) - (pb[c, 0] - pb[a, 0]) * (pb[b, 1] - pb[a, 1])
        )
        for i in range(3):
            u, v = tri[t, i], tri[t, (i + 1) % 3]
            keys[3 * t + i] = min(u, v) * n + max(u, v)
    keys = np.unique(keys)
    edges = np.empty((keys.size, 2), np.int64)
    la = np.empty(keys.size)
    lb = np.empty(keys.size)
    for e in range(keys.size):
        u, v = keys[e] // n, keys[e] % n
        edges[e, 0], edges[e, 1] = u, v
        la[e] = math.hypot(pa[u, 0] - pa[v, 0], pa[u, 1] - pa[v, 1])
        lb[e] = math.hypot(pb[u, 0] - pb[v, 0], pb[u, 1] - pb[v, 1])
    return tri, area_a, area_b, edges, la, lb


# Why a pair gave no strain (:attr:`StrainBatch.status`).
STRAIN_OK, TOO_FEW_POINTS, COLLINEAR, NO_USABLE_TRIANGLE = 0, 1, 2, 3


@njit(nogil=True)
def _strain_batch(points, disp, ids, offsets, max_edge, min_area, min_quality, min_spacing):  # pragma: no cover
    """The triangulation strain of every pair (rows ``offsets[i]:offsets[i + 1]`` of ``points`` and ``disp``) in
    one call without the GIL. Output rows (``kept`` points, triangle corners, edge ends) index ``points``."""
    n_pairs = offsets.size - 1
    total = offsets[n_pairs]
    status = np.zeros(n_pairs, np.int8)
    n_distinct = np.zeros(n_pairs, np.int64)
    n_dropped = np.zeros(n_pairs, np.int64)
    kept = np.empty(total, np.int64)
    kept_off = np.zeros(n_pairs + 1, np.int64)
    # A triangulation of m points has at most 2m - 5 triangles and 3m - 6 edges.
    tri_out = np.empty((2 * total, 3), np.int64)
    area_a_out = np.empty(2 * total)
    area_b_out = np.empty(2 * total)
    tri_off = np.zeros(n_pairs + 1, np.int64)
    edge_out = np.empty((3 * total, 2), np.int64)
    la_out = np.empty(3 * total)
    lb_out = np.empty(3 * total)
    edge_off = np.zeros(n_pairs + 1, np.int64)
    nk = nt = ne = 0
    for i in range(n_pairs):
        o0, o1 = offsets[i], offsets[i + 1]
        pa_in = points[o0:o1]
        d_in = disp[o0:o1]
        n_in = 0
        for k in range(o1 - o0):
            if np.isfinite(pa_in[k, 0]) and np.isfinite(pa_in[k, 1]) and np.isfinite(d_in[k, 0]) and np.isfinite(d_in[k, 1]):
                n_in += 1
        first = _spaced(pa_in, _distinct_finite(pa_in, d_in), ids[o0:o1], min_spacing)
        m = first.size
        n_distinct[i] = m
        for k in range(m):
            kept[nk + k] = o0 + first[k]
        nk += m
        kept_off[i + 1] = nk
        n_dropped[i] = n_in - m
        tri_off[i + 1] = nt
        edge_off[i + 1] = ne
        if m < 3:
            status[i] = TOO_FEW_POINTS
            continue
        pa = np.empty((m, 2))
        pb = np.empty((m, 2))
        for k in range(m):
            for c in range(2):
                pa[k, c] = pa_in[first[k], c]
                pb[k, c] = pa[k, c] + d_in[first[k], c]
        tri = _triangulate(pa[:, 0].copy(), pa[:, 1].copy())
        n_simplices = tri.shape[0]
        if n_simplices == 0:
            status[i] = COLLINEAR
            continue
        tri, area_a, area_b, edges, la, lb = _triangle_changes(pa, pb, tri, max_edge, min_area, min_quality)
        n_dropped[i] += n_simplices - tri.shape[0]
        if tri.shape[0] == 0:
            status[i] = NO_USABLE_TRIANGLE
            continue
        for t in range(tri.shape[0]):
            for c in range(3):
                tri_out[nt, c] = o0 + first[tri[t, c]]
            area_a_out[nt] = area_a[t]
            area_b_out[nt] = area_b[t]
            nt += 1
        for e in range(edges.shape[0]):
            edge_out[ne, 0] = o0 + first[edges[e, 0]]
            edge_out[ne, 1] = o0 + first[edges[e, 1]]
            la_out[ne] = la[e]
            lb_out[ne] = lb[e]
            ne += 1
        tri_off[i + 1] = nt
        edge_off[i + 1] = ne
    return (
        status, n_distinct, n_dropped, kept[:nk].copy(), kept_off, tri_out[:nt].copy(), area_a_out[:nt].copy(),
        area_b_out[:nt].copy(), tri_off, edge_out[:ne].copy(), la_out[:ne].copy(), lb_out[:ne].copy(), edge_off,
    )


@dataclass(frozen=True)
class StrainBatch:
    """The triangulation strain of many frame pairs (:func:`triangulation_strains`) as flat tables.

    ``points``, ``displacement`` and ``ids`` are the pairs' samples end to end; every row number below indexes
    them, and ``*_offsets`` (P + 1 entries) delimit each pair's rows. The fields mean what the same names of
    :class:`TriangulationStrain` mean.
    """

    frame_a: np.ndarray  # (P,) int64
    frame_b: np.ndarray  # (P,) int64
    n_points: np.ndarray  # (P,) int64: the sample's size
    status: np.ndarray  # (P,) int8: STRAIN_OK, or why the pair has no strain (TOO_FEW_POINTS, COLLINEAR, ...)
    n_distinct: np.ndarray  # (P,) int64: finite distinct points triangulated
    n_dropped: np.ndarray  # (P,) int64
    points: np.ndarray  # (N, 2)
    displacement: np.ndarray  # (N, 2)
    ids: np.ndarray  # (N,)
    kept: np.ndarray  # (K,) rows triangulated
    kept_offsets: np.ndarray
    triangles: np.ndarray  # (T, 3) rows, counter-clockwise on the image in frame a
    triangle_offsets: np.ndarray
    area: np.ndarray
    area_change: np.ndarray
    flipped: np.ndarray
    edges: np.ndarray  # (E, 2) rows, (low, high)
    edge_offsets: np.ndarray
    edge_length: np.ndarray
    edge_change: np.ndarray

    def failure(self, i: int) -> str | None:
        """Why pair ``i`` has no strain, or None when it has one."""
        code = int(self.status[i])
        if code == STRAIN_OK:
            return None
        pair, n = f"frames {int(self.frame_a[i])}->{int(self.frame_b[i])}", int(self.n_distinct[i])
        if code == TOO_FEW_POINTS:
            return f"{pair}: {n} distinct matched points, need at least 3"
        if code == COLLINEAR:
            return f"{pair}: the {n} matched points are collinear"
        return f"{pair}: no usable triangle (points nearly collinear or too far apart)"


def triangulation_strains(
    samples: Sequence[MotionSample],
    *,
    max_edge_px: float | None = None,
    min_area_px2: float = 1.0,
    min_quality: float = 0.1,
    min_spacing_px: float = 0.0,
) -> StrainBatch:
    """:func:`triangulation_strain` of every sample in one compiled call (no GIL held: a caller can run several
    batches on threads). A pair that has no strain carries the reason (:meth:`StrainBatch.failure`) instead of
    raising."""
    if not (np.isfinite(min_spacing_px) and min_spacing_px >= 0):
        raise InvalidInputError(f"min_spacing_px must be a non-negative number, got {min_spacing_px!r}")
    pts, disp, ids = [], [], []
    for s in samples:
        p = np.asarray(s.points, dtype=np.float64).reshape(-1, 2)
        d = np.asarray(s.displacement, dtype=np.float64).reshape(-1, 2)
        i = np.asarray(s.ids, dtype=np.int64).reshape(-1)
        if d.shape != p.shape or i.shape[0] != p.shape[0]:
            raise InvalidInputError(
                f"sample arrays disagree: points {p.shape}, displacement {d.shape}, ids {i.shape}"
            )
        pts.append(p)
        disp.append(d)
        ids.append(i)
    counts = np.array([p.shape[0] for p in pts], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    points = np.concatenate(pts) if pts else np.zeros((0, 2))
    displacement = np.concatenate(disp) if disp else np.zeros((0, 2))
    all_ids = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    (status, n_distinct, n_dropped, kept, kept_off, tri, area_a, area_b, tri_off, edges, la, lb,
     edge_off) = _strain_batch(
        points, displacement, all_ids, offsets, np.inf if max_edge_px is None else float(max_edge_px),
        float(min_area_px2), float(min_quality), float(min_spacing_px),
    )
    return StrainBatch(
        frame_a=np.array([int(s.frame_a) for s in samples], dtype=np.int64),
        frame_b=np.array([int(s.frame_b) for s in samples], dtype=np.int64),
        n_points=counts,
        status=status,
        n_distinct=n_distinct,
        n_dropped=n_dropped,
        points=points,
        displacement=displacement,
        ids=all_ids,
        kept=kept,
        kept_offsets=kept_off,
        triangles=tri,
        triangle_offsets=tri_off,
        area=area_a,
        area_change=area_b / area_a - 1.0,
        flipped=area_b <= 0,
        edges=edges,
        edge_offsets=edge_off,
        edge_length=la,
        edge_change=lb / la - 1.0,
    )


def triangulation_strain(
    sample: MotionSample,
    *,
    max_edge_px: float | None = None,
    min_area_px2: float = 1.0,
    min_quality: float = 0.1,
    min_spacing_px: float = 0.0,
) -> TriangulationStrain:
    """Relative edge-length and triangle-area change of the Delaunay triangulation of ``sample.points``.

    Parameters
    ----------
    sample : MotionSample
        Points in frame a and their displacement to frame b.
    max_edge_px, min_area_px2 : float
        Triangles with an edge longer than this in frame a (hull slivers), or smaller than this, are left out.
    min_quality : float
        Slivers are left out: shape quality ``4 sqrt(3) A / (a^2 + b^2 + c^2)`` (1 equilateral, 0 flat) below this.
    min_spacing_px : float
        Points are taken in increasing ``ids`` (the oldest tracks first) and one closer than this to a point already
        taken is left out (0: every point): an edge's strain error is its ends' displacement error over its length.

    Raises InsufficientDataError for fewer than 3 distinct points, or all of them collinear.

    Examples
    --------
    >>> import numpy as np
    >>> p = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    >>> s = MotionSample(0, 1, p, p * 0.02, np.arange(4))  # 2 % uniform expansion
    >>> r = triangulation_strain(s)
    >>> np.allclose(r.edge_change, 0.02), np.allclose(r.area_change, 1.02**2 - 1)
    (True, True)
    """
    b = triangulation_strains([sample], max_edge_px=max_edge_px, min_area_px2=min_area_px2, min_quality=min_quality,
                              min_spacing_px=min_spacing_px)
    reason = b.failure(0)
    if reason is not None:
        raise InsufficientDataError(reason)
    row = np.full(b.points.shape[0], -1, np.int64)  # input row -> row of the triangulated points
    row[b.kept] = np.arange(b.kept.size)
    return TriangulationStrain(
        frame_a=int(sample.frame_a),
        frame_b=int(sample.frame_b),
        ids=b.ids[b.kept],
        points=b.points[b.kept],
        triangles=row[b.triangles],
        edges=row[b.edges],
        edge_length=b.edge_length,
        edge_change=b.edge_change,
        area=b.area,
        area_change=b.area_change,
        flipped=b.flipped,
        n_dropped=int(b.n_dropped[0]),
    )


@dataclass(frozen=True)
class LocalMovement:
    """Average movement relative to the fingertip around each centre (seed 5.3.2).

    ``movement`` is NaN exactly where ``valid`` is False (no point inside the window).
    """

    centers: np.ndarray  # (..., 2) px in frame a
    movement: np.ndarray  # (..., 2) px
    count: np.ndarray  # (...) int64
    valid: np.ndarray  # (...) bool


def local_movement(
    sample: MotionSample, *, fingertip_displacement: np.ndarray, centers: np.ndarray, radius_px: float
) -> LocalMovement:
    """Mean displacement minus fingertip displacement of the points within ``radius_px`` of each centre (disk).

    ``centers`` may have any leading shape (e.g. a (GY, GX, 2) grid).
    """
    if not radius_px > 0:
        raise InvalidInputError(f"radius_px must be positive, got {radius_px!r}")
    centers = np.asarray(centers, dtype=np.float64)
    if centers.shape[-1] != 2:
        raise InvalidInputError(f"centers must end in an axis of 2, got shape {centers.shape}")
    ft = np.asarray(fingertip_displacement, dtype=np.float64).reshape(2)
    flat = centers.reshape(-1, 2)
    rel = np.asarray(sample.displacement, dtype=np.float64) - ft
    sums = np.zeros_like(flat)
    count = np.zeros(flat.shape[0], np.int64)
    if len(sample):
        lists = cKDTree(np.asarray(sample.points, dtype=np.float64)).query_ball_point(flat, radius_px)
        lengths = np.fromiter((len(lst) for lst in lists), dtype=np.int64, count=flat.shape[0])
        if lengths.sum():
            owner = np.repeat(np.arange(flat.shape[0]), lengths)
            members = np.concatenate([np.asarray(lst, dtype=np.int64) for lst in lists if lst])
            np.add.at(sums, owner, rel[members])
            count = lengths
    valid = count > 0
    mov = np.full_like(flat, np.nan)
    mov[valid] = sums[valid] / count[valid][:, None]
    shape = centers.shape[:-1]
    return LocalMovement(centers, mov.reshape(*shape, 2), count.reshape(shape), valid.reshape(shape))


def patch_area_change(centers: np.ndarray, movement: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative area change of the tetragons of 4 neighbouring patch centres (seed 5.3.2, Figure 61).

    Parameters
    ----------
    centers, movement : (GY, GX, 2) arrays
        Patch centres in frame a and their movement (relative to the fingertip; a common motion cancels).
    valid : (GY, GX) bool

    Returns
    -------
    change : (GY-1, GX-1) float64
        ``A_b / A_a - 1``; NaN exactly where ``ok`` is False.
    ok : (GY-1, GX-1) bool
        All four corners valid and the tetragon non-degenerate.
    """
    centers = np.asarray(centers, dtype=np.float64)
    movement = np.asarray(movement, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if centers.ndim != 3 or centers.shape[2] != 2 or movement.shape != centers.shape or valid.shape != centers.shape[:2]:
        raise InvalidInputError(
            f"centers {centers.shape}, movement {movement.shape}, valid {valid.shape} must be (GY, GX, 2) and (GY, GX)"
        )

    def area(p):
        a, b, c, d = p[:-1, :-1], p[:-1, 1:], p[1:, 1:], p[1:, :-1]
        xs = np.stack([a[..., 0], b[..., 0], c[..., 0], d[..., 0]])
        ys = np.stack([a[..., 1], b[..., 1], c[..., 1], d[..., 1]])
        return 0.5 * np.sum(xs * np.roll(ys, -1, axis=0) - np.roll(xs, -1, axis=0) * ys, axis=0)

    after = centers + np.where(valid[..., None], movement, 0.0)
    a0, a1 = area(centers), area(after)
    ok = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, 1:] & valid[1:, :-1] & (np.abs(a0) > 1e-9)
    change = np.full(a0.shape, np.nan)
    change[ok] = a1[ok] / a0[ok] - 1.0
    return change, ok


@dataclass(frozen=True)
class StretchProfile:
    """Change in horizontal stretch at positions along x (seed 5.3.2, Figure 62). NaN exactly where not ``valid``."""

    x: np.ndarray  # (P,) px
    change: np.ndarray  # (P,) fraction
    valid: np.ndarray  # (P,) bool


def horizontal_stretch_profile(
    sample: MotionSample,
    *,
    fingertip_displacement: np.ndarray,
    x_positions: np.ndarray,
    strip_width_px: float,
    min_points: int = 3,
) -> StretchProfile:
    """Change in horizontal stretch at each x between frames a and b (seed 5.3.2, Figure 62).

    The points (frame-a positions) in the strips ``[x - w, x)`` and ``[x, x + w)`` give a mean horizontal movement
    relative to the fingertip and a mean position each; the change in stretch at x is the difference of the two
    movements over the distance between the two mean positions (positive = expansion). Dividing by that distance
    rather than by ``w`` keeps the result exact for a linear field however the points are spread in the strips
    (features are sparse where the image is dark). The fingertip movement is subtracted as the seed does; it
    cancels in the difference. A position is invalid when a strip has fewer than ``min_points`` points or when a
    strip's points do not cover it (their mean position more than ``w / 4`` from the strip's centre: the strip runs
    off the contact area, the image or a band without features), so the value always describes the skin at x.

    Examples
    --------
    >>> pts = np.column_stack([np.arange(0.0, 100.0), np.zeros(100)])
    >>> s = MotionSample(0, 1, pts, np.column_stack([0.01 * pts[:, 0], np.zeros(100)]), np.arange(100))
    >>> p = horizontal_stretch_profile(s, fingertip_displacement=np.zeros(2), x_positions=np.array([50.0, 95.0]),
    ...                                strip_width_px=20.0)
    >>> np.round(p.change, 6).tolist(), p.valid.tolist()
    ([0.01, nan], [True, False])
    """
    if not strip_width_px > 0:
        raise InvalidInputError(f"strip_width_px must be positive, got {strip_width_px!r}")
    if int(min_points) < 1:
        raise InvalidInputError(f"min_points must be at least 1, got {min_points!r}")
    w = float(strip_width_px)
    xs = np.asarray(x_positions, dtype=np.float64).reshape(-1)
    px = np.asarray(sample.points, dtype=np.float64)[:, 0] if len(sample) else np.zeros(0)
    ft = float(np.asarray(fingertip_displacement, dtype=np.float64).reshape(-1)[0])
    dx = (np.asarray(sample.displacement, dtype=np.float64)[:, 0] - ft) if len(sample) else np.zeros(0)
    keep = np.isfinite(px) & np.isfinite(dx)
    px, dx = px[keep], dx[keep]
    order = np.argsort(px)
    px, dx = px[order], dx[order]
    csum_d = np.concatenate([[0.0], np.cumsum(dx)])
    csum_x = np.concatenate([[0.0], np.cumsum(px)])

    def strip(lo):
        i0 = np.searchsorted(px, lo, side="left")
        i1 = np.searchsorted(px, lo + w, side="left")
        n = i1 - i0
        with np.errstate(invalid="ignore", divide="ignore"):
            return (csum_d[i1] - csum_d[i0]) / n, (csum_x[i1] - csum_x[i0]) / n, n

    dl, cl, nl = strip(xs - w)
    dr, cr, nr = strip(xs)
    valid = (nl >= min_points) & (nr >= min_points)
    valid &= (np.abs(cl - (xs - 0.5 * w)) <= 0.25 * w) & (np.abs(cr - (xs + 0.5 * w)) <= 0.25 * w)
    change = np.full(xs.shape, np.nan)
    change[valid] = (dr[valid] - dl[valid]) / (cr[valid] - cl[valid])
    return StretchProfile(xs, change, valid)


def mean_profile(profiles: list[StretchProfile], *, min_pairs: int = 1) -> StretchProfile:
    """Average of profiles at the same positions over a sequence (seed Figure 94), ignoring invalid entries.

    A position is valid when at least ``min_pairs`` profiles have a value there.
    """
    if not profiles:
        raise InsufficientDataError("no stretch profile to average")
    if int(min_pairs) < 1:
        raise InvalidInputError(f"min_pairs must be at least 1, got {min_pairs!r}")
    x = profiles[0].x
    total = np.zeros(x.shape)
    count = np.zeros(x.shape)
    for p in profiles:
        if p.x.shape != x.shape or not np.allclose(p.x, x):
            raise InvalidInputError("profiles must share their x positions")
        total += np.where(p.valid, p.change, 0.0)
        count += p.valid
    valid = count >= int(min_pairs)
    change = np.full(x.shape, np.nan)
    change[valid] = total[valid] / count[valid]
    return StretchProfile(x, change, valid)


@dataclass(frozen=True)
class ProfilePattern:
    """What a stretch profile shows (seed 6.3.2, Figure 94), positions in the profile's units.

    ``amplitude`` is the RMS of the valid values; ``compression``/``expansion`` are the most negative/positive
    values and ``compression_at``/``expansion_at`` where they are. ``compression_first`` says whether the
    compression comes before the expansion in the sliding direction: the seed's finding is True for a ridge,
    False for a valley; on a flat surface there is no pattern and only ``amplitude`` means something.
    """

    amplitude: float
    compression: float
    compression_at: float
    expansion: float
    expansion_at: float
    compression_first: bool


def profile_pattern(profile: StretchProfile, *, direction: float, margin: float = 0.0) -> ProfilePattern:
    """Summarise a profile: its amplitude and the order of its compression and expansion lobes.

    ``direction`` is the sign of the sliding motion along the profile's axis (positive = towards larger x).
    Values within ``margin`` of either end of the valid positions are left out: there the strips reach the edge
    of the contact area, where skin touches or leaves the glass, which is not the pattern of a shape.
    """
    if not np.isfinite(direction) or direction == 0:
        raise InvalidInputError(f"direction must be a non-zero number, got {direction!r}")
    if not (np.isfinite(margin) and margin >= 0):
        raise InvalidInputError(f"margin must be a non-negative number, got {margin!r}")
    ok = np.asarray(profile.valid, dtype=bool).copy()
    x_all = np.asarray(profile.x, dtype=np.float64)
    if ok.any():
        lo, hi = x_all[ok].min(), x_all[ok].max()
        ok &= (x_all >= lo + margin) & (x_all <= hi - margin)
    if ok.sum() < 3:
        raise InsufficientDataError(f"a profile pattern needs 3 valid positions, got {int(ok.sum())}")
    x, c = x_all[ok], np.asarray(profile.change)[ok]
    i, j = int(np.argmin(c)), int(np.argmax(c))
    return ProfilePattern(
        amplitude=float(np.sqrt(np.mean(c**2))),
        compression=float(c[i]),
        compression_at=float(x[i]),
        expansion=float(c[j]),
        expansion_at=float(x[j]),
        compression_first=bool(np.sign(direction) * (x[j] - x[i]) > 0),
    )

"""Skeleton editing (seed 4.8.1-4.8.4): syntactic rules that repair the valley skeleton graph.

The rules run compiled on :class:`skinstretch.processing.skeleton_graph.GraphArrays`; :func:`edit_graph` runs the
chain of them, as the extraction does. The public functions take and return a
:class:`skinstretch.processing.skeleton_graph_lists.SkeletonGraph` (an edited copy):

- :func:`remove_short_valleys` (4.8.1): a valley bounded by two endings and shorter than ~0.2 mm is a pore.
- :func:`heal_broken_valleys` (4.8.2): join facing endings closer than ~0.6 mm, best confidence (eq. 4.4) first;
  given the image (:class:`GapEvidence`), never across a ridge: a gap whose line crosses more than
  ``max_ridge_px`` of skin as dark as the ridges around is left open.
- :func:`remove_short_spurs` (4.8.3): a short branch roughly perpendicular to its valley is deleted (a pore is
  left at its tip when it was long enough to be one).
- :func:`remove_bridges` (4.8.4): a short valley between two bifurcations, roughly perpendicular to both valleys,
  is a pore joining two valleys.

Beyond the seed: given the ridge flow, a spur or bridge is a pore's when it crosses the ridges more than it
follows them (within 45 degrees of their normal); a stub of one or two pixels goes whatever its direction. Given
the background, a branch that ends at it (a valley leaving the contact) is no spur, and a valley between two forks
that runs along it is no bridge. The evidence: docs/tuning-log.md.

All lengths here are pixels: :mod:`skinstretch.processing.extraction` converts the seed's millimetres once.
The results depend on the order of the loops, which is part of the rules: edges and nodes in id order, a pass
visiting the edges alive when it starts (an edge a merge creates waits for the next pass), sums in the order written.
"""

from __future__ import annotations

import math
import operator

import numpy as np
from pydantic import model_validator

from skinstretch.processing.argument_checks import positive_number
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit
from skinstretch.processing.validated_dataclass import PositiveFloat, PositiveInt, validated_dataclass
from skinstretch.processing.skeleton_graph import (
    _NODES,
    _PATH,
    _PORES,
    GraphArrays,
    _add_edge,
    _add_pore,
    _alive_edges,
    _counts,
    _edge_direction,
    _n_px,
    _other_end,
    _path_room,
    _put_path_from,
    _remove_edge,
    _remove_node,
    _settle,
    _unlink_edge,
    edit_with_room,
)
from skinstretch.processing.ridge_flow import RidgeFlow, flow_normal_at
from skinstretch.processing.skeleton_graph_lists import SkeletonGraph

__all__ = [
    "remove_short_valleys",
    "heal_broken_valleys",
    "remove_short_spurs",
    "remove_bridges",
    "edit_graph",
    "line_pixels",
    "GapEvidence",
]



@njit(nogil=True)
def _short_valleys(G, max_len):  # pragma: no cover - compiled
    for e in _alive_edges(G):
        a = G.edge_ab[e, 0]
        b = G.edge_ab[e, 1]
        if a == b or G.node_deg[a] != 1 or G.node_deg[b] != 1 or G.edge_length[e] >= max_len:
            continue
        # Centre of mass of both ends then the pixels, summed in that order.
        cx = G.node_xy[a, 0] + G.node_xy[b, 0]
        cy = G.node_xy[a, 1] + G.node_xy[b, 1]
        s = G.edge_span[e, 0]
        m = G.edge_span[e, 1]
        for k in range(s, s + m):
            cx += G.path[k, 0]
            cy += G.path[k, 1]
        cx /= m + 2
        cy /= m + 2
        _remove_edge(G, e)
        _remove_node(G, a)
        _remove_node(G, b)
        _add_pore(G, cx, cy, 0.0)


@njit(nogil=True)
def _grown_pairs(iu, ju, dist, cos):  # pragma: no cover - compiled
    n = iu.size
    iu2 = np.empty(2 * n, np.int64)
    ju2 = np.empty(2 * n, np.int64)
    dist2 = np.empty(2 * n)
    cos2 = np.empty((2, 2 * n))
    for k in range(n):  # (explicit loops: numba compiles slice copies slowly)
        iu2[k] = iu[k]
        ju2[k] = ju[k]
        dist2[k] = dist[k]
        cos2[0, k] = cos[0, k]
        cos2[1, k] = cos[1, k]
    return iu2, ju2, dist2, cos2


@njit(nogil=True)
def _heal_candidates(G, d_max, n_px):  # pragma: no cover - compiled
    """Healing candidates: the valley endings with a trusted direction (``ends``, in id order) and their pairs
    (i < j, in order) closer than ``d_max``, not the two ends of one valley, with the cosines of the angles between
    the bridging line and the outward direction of each valley, ``cos`` (2, K). Their arccos is taken by numpy (its
    vectorised arccos can differ from the C library's in the last bit)."""
    nn = G.used[_NODES] if d_max > 0 else 0
    ends = np.empty(nn, np.int64)
    inx = np.empty(nn)
    iny = np.empty(nn)
    m = 0
    for v in range(nn):
        if not G.node_alive[v] or G.node_deg[v] != 1:
            continue
        dx, dy, ok = _edge_direction(G, v, G.node_adj[v, 0], n_px)  # inward: from the ending into its valley
        if ok:
            ends[m] = v
            inx[m] = dx
            iny[m] = dy
            m += 1
    iu = np.empty(16, np.int64)
    ju = np.empty(16, np.int64)
    dist = np.empty(16)
    cos = np.empty((2, 16))
    k = 0
    for i in range(m):
        xi = G.node_xy[ends[i], 0]
        yi = G.node_xy[ends[i], 1]
        edge_i = G.node_adj[ends[i], 0]
        for j in range(i + 1, m):
            dx = G.node_xy[ends[j], 0] - xi
            dy = G.node_xy[ends[j], 1] - yi
            if abs(dx) >= d_max or abs(dy) >= d_max:  # hypot >= both: too far (exactly as the test below)
                continue
            d = math.hypot(dx, dy)  # the C library's, as numpy's hypot
            # Not the two ends of one valley (joining them would make a loop).
            if not (d < d_max and d > 0) or G.node_adj[ends[j], 0] == edge_i:
                continue
            # The gap must continue each valley: the bridging line against the outward (= -inward) directions.
            ux = dx / d
            uy = dy / d
            c1 = -(ux * inx[i] + uy * iny[i])
            c2 = ux * inx[j] + uy * iny[j]
            if k == iu.size:
                iu, ju, dist, cos = _grown_pairs(iu, ju, dist, cos)
            iu[k] = i
            ju[k] = j
            dist[k] = d
            cos[0, k] = min(max(c1, -1.0), 1.0)
            cos[1, k] = min(max(c2, -1.0), 1.0)
            k += 1
    out = np.empty((2, k))
    for c in range(k):
        out[0, c] = cos[0, c]
        out[1, c] = cos[1, c]
    return ends[:m], iu[:k], ju[:k], dist[:k], out


@njit(nogil=True)
def _line(x0, y0, x1, y1):  # pragma: no cover - compiled
    """:func:`skinstretch.processing.skeleton_editing.line_pixels`."""
    n = max(abs(x1 - x0), abs(y1 - y0))
    out = np.empty((n + 1, 2), np.int64)
    if n == 0:
        out[0, 0] = x0
        out[0, 1] = y0
        return out
    for i in range(n + 1):
        t = i / n
        out[i, 0] = np.int64(np.rint(x0 + (x1 - x0) * t))
        out[i, 1] = np.int64(np.rint(y0 + (y1 - y0) * t))
    return out


@njit(nogil=True)
def _touches(skeleton, line, x1, y1, x2, y2):  # pragma: no cover - compiled
    """Whether any skeleton pixel other than the two endings and their own valley neighbours lies in the
    8-neighbourhood of the line's inner pixels (all but its first and last)."""
    h, w = skeleton.shape
    for k in range(1, line.shape[0] - 1):
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                x = line[k, 0] + dx
                y = line[k, 1] + dy
                if x < 0 or x >= w or y < 0 or y >= h or skeleton[y, x] == 0:
                    continue
                near1 = max(abs(x - x1), abs(y - y1)) <= 1
                near2 = max(abs(x - x2), abs(y - y2)) <= 1
                if not (near1 or near2):
                    return True
    return False


@njit(nogil=True)
def _delete_pores_near_segment(G, ax, ay, bx, by, radius):  # pragma: no cover - compiled
    vx = bx - ax
    vy = by - ay
    l2 = vx * vx + vy * vy
    for q in range(G.used[_PORES]):
        px = G.pore[q, 0]
        py = G.pore[q, 1]
        t = 0.0
        if l2 > 0:
            t = ((px - ax) * vx + (py - ay) * vy) / l2
            t = min(max(t, 0.0), 1.0)
        if math.hypot(px - (ax + t * vx), py - (ay + t * vy)) <= radius:
            G.pore_alive[q] = False


@njit(nogil=True)
def _stable_argsort(keys):  # pragma: no cover - compiled
    """np.argsort(keys, kind="stable") for keys without NaN (a bottom-up merge sort; numba's own is slow to
    compile)."""
    n = keys.size
    order = np.arange(n)
    tmp = np.empty(n, np.int64)
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid = min(lo + width, n)
            hi = min(lo + 2 * width, n)
            i = lo
            j = mid
            for k in range(lo, hi):
                if i < mid and (j >= hi or keys[order[j]] >= keys[order[i]]):
                    tmp[k] = order[i]
                    i += 1
                else:
                    tmp[k] = order[j]
                    j += 1
        order, tmp = tmp, order
        width *= 2
    return order


@njit(nogil=True)
def _heal_apply(G, ends, iu, ju, dist, acos, d_max, t_max):  # pragma: no cover - compiled
    """Heal the candidates of :func:`_heal_candidates` whose angles (``acos``, radians) are below ``t_max``
    degrees, best confidence (seed eq. 4.4) first."""
    k = iu.size
    si = np.empty(k, np.int64)
    sj = np.empty(k, np.int64)
    neg_conf = np.empty(k)
    n = 0
    for c in range(k):
        t1 = acos[0, c] * (180.0 / math.pi)  # np.degrees
        t2 = acos[1, c] * (180.0 / math.pi)
        if t1 < t_max and t2 < t_max:
            si[n] = iu[c]
            sj[n] = ju[c]
            neg_conf[n] = -((d_max - dist[c]) / d_max * (t_max - t1) / t_max * (t_max - t2) / t_max)  # eq. 4.4
            n += 1
    order = _stable_argsort(neg_conf[:n])  # best first; ties keep the (i, j) order
    healed = np.zeros(ends.size, np.bool_)
    for c in order:
        i = si[c]
        j = sj[c]
        if healed[i] or healed[j]:
            continue
        n1 = ends[i]
        n2 = ends[j]
        x1 = int(np.rint(G.node_xy[n1, 0]))
        y1 = int(np.rint(G.node_xy[n1, 1]))
        x2 = int(np.rint(G.node_xy[n2, 0]))
        y2 = int(np.rint(G.node_xy[n2, 1]))
        line = _line(x1, y1, x2, y2)
        if _touches(G.skeleton, line, x1, y1, x2, y2):
            continue
        healed[i] = True
        healed[j] = True
        if G.node_deg[n1] == 0 or G.node_deg[n2] == 0:
            raise IndexError("a healed ending has no valley")
        e1 = G.node_adj[n1, 0]
        e2 = G.node_adj[n2, 0]
        a = _other_end(G, e1, n1)
        b = _other_end(G, e2, n2)
        n_inner = max(line.shape[0] - 2, 0)
        start = _path_room(G, G.edge_span[e1, 1] + n_inner + 2 + G.edge_span[e2, 1])
        p = _put_path_from(G, start, e1, a)
        G.path[p, 0] = x1
        G.path[p, 1] = y1
        p += 1
        for t in range(1, 1 + n_inner):
            G.path[p, 0] = line[t, 0]
            G.path[p, 1] = line[t, 1]
            p += 1
        G.path[p, 0] = x2
        G.path[p, 1] = y2
        p = _put_path_from(G, p + 1, e2, n2)
        G.used[_PATH] = p
        length = G.edge_length[e1] + G.edge_length[e2] + math.hypot(float(x2 - x1), float(y2 - y1))
        _unlink_edge(G, e1)
        _unlink_edge(G, e2)
        G.node_alive[n1] = False
        G.node_alive[n2] = False
        for t in range(line.shape[0]):
            G.skeleton[line[t, 1], line[t, 0]] = 1
        _add_edge(G, a, b, start, p - start, length)
        _delete_pores_near_segment(G, x1, y1, x2, y2, 1.5)


@njit(nogil=True)
def _perpendicular(G, node, edge, n_px, max_dev):  # pragma: no cover - compiled
    """Whether ``edge`` leaves ``node`` within ``max_dev`` degrees of perpendicular to each of the node's other
    valleys (the seed's angles theta_1..theta_4)."""
    sx, sy, _ = _edge_direction(G, node, edge, n_px)
    if sx == 0 and sy == 0:
        return False
    for k in range(G.node_deg[node]):
        other = G.node_adj[node, k]
        if other == edge:
            continue
        ox, oy, _ = _edge_direction(G, node, other, n_px)
        theta = math.degrees(math.acos(max(-1.0, min(1.0, sx * ox + sy * oy))))
        if abs(theta - 90.0) > max_dev:
            return False
    return True


@njit(nogil=True)
def _bridge_end(G, node, edge, n_px, max_dev):  # pragma: no cover - compiled
    """Whether ``node`` can end the bridge ``edge``: a bifurcation of three valleys with the bridge perpendicular to
    the other two, or a crossing of four where one valley continues the bridge straight on (within ``max_dev``)
    and the bridge is perpendicular to the other two."""
    d = G.node_deg[node]
    if d == 3:
        return _perpendicular(G, node, edge, n_px, max_dev)
    if d != 4:
        return False
    sx, sy, _ = _edge_direction(G, node, edge, n_px)
    if sx == 0 and sy == 0:
        return False
    # The angles with the three other valleys (the bridge is not a self-loop: it is listed once), sorted.
    t0 = t1 = t2 = 0.0
    n = 0
    for k in range(4):
        other = G.node_adj[node, k]
        if other == edge:
            continue
        ox, oy, _ = _edge_direction(G, node, other, n_px)
        if ox == 0 and oy == 0:
            return False
        t = math.degrees(math.acos(max(-1.0, min(1.0, sx * ox + sy * oy))))
        if n == 0:
            t0 = t
        elif n == 1:
            t1 = t
        else:
            t2 = t
        n += 1
    if n != 3:
        return False
    if t1 < t0:
        t0, t1 = t1, t0
    if t2 < t1:
        t1, t2 = t2, t1
        if t1 < t0:
            t0, t1 = t1, t0
    return t2 >= 180.0 - max_dev and abs(t0 - 90.0) <= max_dev and abs(t1 - 90.0) <= max_dev


@njit(nogil=True)
def _across_amount(G, a, b, fc2, fs2, fcell):  # pragma: no cover - compiled
    """cos 2 (alpha - phi) of the chord from node ``a`` to node ``b`` (angle alpha) and the ridges' normal (phi, at
    the chord's middle): 1 straight across the ridges, -1 along them; NaN for no chord or no flow there."""
    dx = G.node_xy[b, 0] - G.node_xy[a, 0]
    dy = G.node_xy[b, 1] - G.node_xy[a, 1]
    d2 = dx * dx + dy * dy
    if d2 == 0:
        return np.nan
    c2, s2 = flow_normal_at(fc2, fs2, fcell, G.node_xy[a, 0] + dx / 2, G.node_xy[a, 1] + dy / 2)
    if c2 == 0 and s2 == 0:
        return np.nan
    return ((dx * dx - dy * dy) * c2 + 2.0 * dx * dy * s2) / d2


@njit(nogil=True)
def _across_flow(G, a, b, fc2, fs2, fcell):  # pragma: no cover - compiled
    """Whether the chord from node ``a`` to node ``b`` crosses the ridge flow more than it follows it (within 45
    degrees of the ridges' normal, taken at the chord's middle), as the branch a pore makes does."""
    return _across_amount(G, a, b, fc2, fs2, fcell) > 0


@njit(nogil=True)
def _branch_end(G, node, edge, n_px, max_dev, flow):  # pragma: no cover - compiled
    """:func:`_bridge_end`, or with the ridge flow (``flow``) only its shape: a bifurcation of three valleys, or a
    crossing of four where one valley continues ``edge`` straight on (the branch itself is judged by
    :func:`_across_flow`)."""
    if not flow:
        return _bridge_end(G, node, edge, n_px, max_dev)
    d = G.node_deg[node]
    if d == 3:
        return True
    if d != 4:
        return False
    sx, sy, _ = _edge_direction(G, node, edge, n_px)
    if sx == 0 and sy == 0:
        return False
    for k in range(4):
        other = G.node_adj[node, k]
        if other == edge:
            continue
        ox, oy, _ = _edge_direction(G, node, other, n_px)
        if math.degrees(math.acos(max(-1.0, min(1.0, sx * ox + sy * oy)))) >= 180.0 - max_dev:
            return True
    return False


@njit(nogil=True)
def _near_background(background, reach, x, y):  # pragma: no cover - compiled
    """Whether a pixel of ``background`` lies within ``reach`` of (x, y) (never, for an empty mask)."""
    h, w = background.shape
    if h == 0:
        return False
    r = int(np.ceil(reach))
    ic = int(np.rint(x))
    ir = int(np.rint(y))
    for rr in range(max(ir - r, 0), min(ir + r, h - 1) + 1):
        for cc in range(max(ic - r, 0), min(ic + r, w - 1) + 1):
            if background[rr, cc] and (cc - x) ** 2 + (rr - y) ** 2 <= reach * reach:
                return True
    return False


@njit(nogil=True)
def _path_near_background(G, e, background, reach):  # pragma: no cover - compiled
    """Whether a pixel of edge ``e`` (its end nodes included) lies within ``reach`` of ``background``."""
    if background.shape[0] == 0:
        return False
    for node in (G.edge_ab[e, 0], G.edge_ab[e, 1]):
        if _near_background(background, reach, G.node_xy[node, 0], G.node_xy[node, 1]):
            return True
    s = G.edge_span[e, 0]
    for k in range(s, s + G.edge_span[e, 1]):
        if _near_background(background, reach, G.path[k, 0], G.path[k, 1]):
            return True
    return False


@njit(nogil=True)
def _short_spurs(G, lo, hi, max_dev, n_px, fc2, fs2, fcell, background, open_reach):  # pragma: no cover - compiled
    """4.8.3 in one pass over the edges (the seed's), or with the flow in passes until nothing changes: deleting a
    stub can merge what is left of a pore's spur into a new edge, which only the next pass sees. A branch that ends
    within ``open_reach`` of the background is a valley leaving the contact, whatever its length: it stays."""
    flow = fc2.size > 0
    changed = True
    while changed:
        changed = False
        for e in _alive_edges(G):
            if not G.edge_alive[e] or G.edge_length[e] >= hi:
                continue
            a = G.edge_ab[e, 0]
            b = G.edge_ab[e, 1]
            da = G.node_deg[a]
            db = G.node_deg[b]
            if da == 1 and (db == 3 or db == 4):
                end = a
                bif = b
            elif db == 1 and (da == 3 or da == 4):
                end = b
                bif = a
            else:
                continue
            if not _branch_end(G, bif, e, n_px, max_dev, flow):
                continue
            if _near_background(background, open_reach, G.node_xy[end, 0], G.node_xy[end, 1]):
                continue
            # With the flow, a stub of one or two pixels (thinning leaves them on round blobs) has no direction to
            # judge: it goes.
            if flow and G.edge_length[e] >= 3.0 and not _across_flow(G, bif, end, fc2, fs2, fcell):
                continue
            tx = G.node_xy[end, 0]
            ty = G.node_xy[end, 1]
            _remove_edge(G, e)
            _remove_node(G, end)
            _settle(G, bif)
            if G.edge_length[e] > lo:
                _add_pore(G, tx, ty, 0.0)
            changed = flow


@njit(nogil=True)
def _is_bridge(G, e, lo, hi, max_dev, n_px, flow, fc2, fs2, fcell, background, open_reach):  # pragma: no cover - compiled
    """Whether the alive edge ``e`` is a bridge of 4.8.4 (see :func:`remove_bridges`); one that comes within
    ``open_reach`` of the background joins two valleys where the ridge between them has left the contact, which
    is no pore."""
    a = G.edge_ab[e, 0]
    b = G.edge_ab[e, 1]
    length = G.edge_length[e]
    if a == b or not (lo <= length <= hi):
        return False
    if not (_branch_end(G, a, e, n_px, max_dev, flow) and _branch_end(G, b, e, n_px, max_dev, flow)):
        return False
    if flow and not _across_flow(G, a, b, fc2, fs2, fcell):
        return False
    return not _path_near_background(G, e, background, open_reach)


@njit(nogil=True)
def _bridges(G, lo, hi, max_dev, n_px, fc2, fs2, fcell, background, open_reach):  # pragma: no cover - compiled
    flow = fc2.size > 0
    changed = True
    while changed:
        changed = False
        edges = _alive_edges(G)
        if flow:
            # The bridges of a pass most squarely across the ridges first: where a pore's bridge and a short stretch
            # of a true valley (between a fork and the pore's junction) share a node, removing one settles the node
            # and the other is no longer a bridge; the pore's crosses the ridges, the valley's follows them.
            keys = np.zeros(edges.size)
            for i in range(edges.size):
                e = edges[i]
                if _is_bridge(G, e, lo, hi, max_dev, n_px, flow, fc2, fs2, fcell, background, open_reach):
                    keys[i] = -_across_amount(G, G.edge_ab[e, 0], G.edge_ab[e, 1], fc2, fs2, fcell)
            edges = edges[_stable_argsort(keys)]
        for e in edges:
            if not G.edge_alive[e] or not _is_bridge(G, e, lo, hi, max_dev, n_px, flow, fc2, fs2, fcell, background, open_reach):
                continue
            a = G.edge_ab[e, 0]
            b = G.edge_ab[e, 1]
            s = G.edge_span[e, 0]
            m = G.edge_span[e, 1]
            if m:
                cx = 0.0
                cy = 0.0
                for k in range(s, s + m):
                    cx += G.path[k, 0]  # integers: the sum is exact, as numpy's mean's
                    cy += G.path[k, 1]
                cx /= m
                cy /= m
            else:
                cx = (G.node_xy[a, 0] + G.node_xy[b, 0]) / 2
                cy = (G.node_xy[a, 1] + G.node_xy[b, 1]) / 2
            _remove_edge(G, e)
            _settle(G, a)
            _settle(G, b)
            _add_pore(G, cx, cy, 0.0)
            changed = True


@njit(nogil=True)
def _edit_to_healing(G, short_valley_px, heal_px, n_px):  # pragma: no cover - compiled
    """Extraction's editing, first part: counts, 4.8.1 (when ``short_valley_px`` > 0), counts and the healing
    candidates (when ``heal_px`` > 0)."""
    counts = np.zeros((5, 3), np.int64)
    _counts(G, counts[0])
    if short_valley_px > 0:
        _short_valleys(G, short_valley_px)
        _counts(G, counts[1])
    ends, iu, ju, dist, cos = _heal_candidates(G, heal_px, n_px)  # none when heal_px is 0
    return counts, ends, iu, ju, dist, cos


@njit(nogil=True)
def _edit_from_healing(
    G, counts, ends, iu, ju, dist, acos, heal_px, heal_deg, spur_lo, spur_hi, spur_dev, bridge_lo, bridge_hi,
    bridge_dev, n_px, fc2, fs2, fcell, background, open_reach,
):  # pragma: no cover - compiled  # fmt: skip
    """Extraction's editing, second part: 4.8.2, 4.8.3, 4.8.4, each when its upper length is > 0, with counts."""
    if heal_px > 0:
        _heal_apply(G, ends, iu, ju, dist, acos, heal_px, heal_deg)
        _counts(G, counts[2])
    if spur_hi > 0:
        _short_spurs(G, spur_lo, spur_hi, spur_dev, n_px, fc2, fs2, fcell, background, open_reach)
        _counts(G, counts[3])
    if bridge_hi > 0:
        _bridges(G, bridge_lo, bridge_hi, bridge_dev, n_px, fc2, fs2, fcell, background, open_reach)
        _counts(G, counts[4])



def _angle_limit(value: float, name: str) -> float:
    if not (isinstance(value, (int, float, np.number)) and 0 < value <= 90):
        raise InvalidInputError(f"{name} must be an angle in (0, 90] degrees, got {value!r}")
    return float(value)


def _length_range(lo: float, hi: float) -> tuple[float, float]:
    lo = positive_number(lo, "min_length_px")
    hi = positive_number(hi, "max_length_px")
    if lo >= hi:
        raise InvalidInputError(f"min_length_px ({lo}) must be below max_length_px ({hi})")
    return lo, hi


def line_pixels(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """Pixels (x, y) of the 8-connected straight line from (x0, y0) to (x1, y1), both ends included."""
    return _line(operator.index(x0), operator.index(y0), operator.index(x1), operator.index(y1))


#: A gap pixel belongs to a ridge when it is in the darkest quarter of the range between the local levels of the
#: valleys and of the ridges (the 90th and 10th percentiles of the image around the gap).
RIDGE_DARKNESS = 0.75


@validated_dataclass
class GapEvidence:
    """What healing (4.8.2) asks the image: is the gap between two facing endings a ridge (module doc)?

    Attributes
    ----------
    image : (H, W) float32
        The frame as the binarization sees it (valleys bright, ridges dark).
    window_px : int
        Half-side of the square around the gap's middle whose 10th and 90th percentiles are the ridges' and the
        valleys' levels there (about one ridge period, so that both are in it).
    max_ridge_px : float
        Longest stretch of ridge-dark skin (px along the gap's line) a healed gap may cross.
    """

    image: np.ndarray
    window_px: PositiveInt
    max_ridge_px: PositiveFloat

    @model_validator(mode="after")
    def _image_is_2d(self) -> "GapEvidence":
        if np.ndim(self.image) != 2:
            raise InvalidInputError(f"GapEvidence.image must be a 2-D array, got shape {np.shape(self.image)}")
        return self

    def crosses_ridge(self, x1: float, y1: float, x2: float, y2: float) -> bool:
        """Whether the straight line between two endings crosses more than ``max_ridge_px`` of ridge-dark skin in
        one stretch."""
        line = _line(int(np.rint(x1)), int(np.rint(y1)), int(np.rint(x2)), int(np.rint(y2)))
        h, w = self.image.shape
        inner = line[1:-1]
        inner = inner[(inner[:, 0] >= 0) & (inner[:, 0] < w) & (inner[:, 1] >= 0) & (inner[:, 1] < h)]
        if inner.shape[0] == 0:
            return False
        cx, cy, r = int(np.rint((x1 + x2) / 2)), int(np.rint((y1 + y2) / 2)), int(self.window_px)
        around = self.image[max(cy - r, 0) : cy + r + 1, max(cx - r, 0) : cx + r + 1]
        ridge, valley = np.percentile(around, [10.0, 90.0])
        dark = self.image[inner[:, 1], inner[:, 0]] < valley - RIDGE_DARKNESS * (valley - ridge)
        if not dark.any():
            return False
        # Longest run of dark pixels, in px along the line (each step of the line is that long).
        step = math.hypot(x2 - x1, y2 - y1) / (line.shape[0] - 1)
        edges = np.diff(np.concatenate([[0], dark.view(np.int8), [0]]))
        runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
        return float(runs.max()) * step > self.max_ridge_px


# The public functions check their arguments, convert the graph and run the compiled rules above through the two
# calls of _run_rules.


_NO_FLOW = (np.zeros((0, 0)), np.zeros((0, 0)), 1)
_NO_BACKGROUND = (np.zeros((0, 0), np.bool_), 0.0)


def _flow_arrays(flow: RidgeFlow | None):
    if flow is None:
        return _NO_FLOW
    if not isinstance(flow, RidgeFlow):
        raise InvalidInputError(f"flow must be a RidgeFlow or None, got {type(flow).__name__}")
    return flow.cos2, flow.sin2, flow.cell_px


def _gap_evidence(gaps):
    if gaps is not None and not isinstance(gaps, GapEvidence):
        raise InvalidInputError(f"gaps must be a GapEvidence or None, got {type(gaps).__name__}")
    return gaps


def _background_arrays(background, reach_px):
    if background is None:
        return _NO_BACKGROUND
    background = np.asarray(background)
    if background.ndim != 2 or background.dtype != np.bool_:
        raise InvalidInputError(f"background must be a 2-D bool mask, got {background.dtype} of shape {background.shape}")
    return np.ascontiguousarray(background), positive_number(reach_px, "open_reach_px")


def _run_rules(arrays, n_px, sv=0.0, heal=(0.0, 0.0), spurs=(0.0, 0.0, 0.0), bridges=(0.0, 0.0, 0.0),
               flow=None, background=None, open_reach_px=0.0, gaps=None) -> np.ndarray:
    """Run the rules whose first length is > 0, in the order of seed 4.8, on ``arrays`` (in place); (5, 3) counts."""
    counts, ends, iu, ju, dist, cos = _edit_to_healing(arrays, sv, heal[0], n_px)
    # numpy's arccos (vectorised: it can differ from the C library's acos in the last bit), as the rule always had.
    acos = np.arccos(cos)
    if gaps is not None and iu.size:
        # A candidate whose gap crosses a ridge is no broken valley: its angles are set beyond any limit.
        xy = arrays.node_xy
        facing = np.flatnonzero(np.degrees(acos).max(axis=0) < heal[1])
        for c in facing.tolist():
            a, b = ends[iu[c]], ends[ju[c]]
            if gaps.crosses_ridge(xy[a, 0], xy[a, 1], xy[b, 0], xy[b, 1]):
                acos[:, c] = math.pi
    _edit_from_healing(arrays, counts, ends, iu, ju, dist, acos, *heal, *spurs, *bridges, n_px, *_flow_arrays(flow),
                       *_background_arrays(background, open_reach_px))
    return counts


def _edited(graph: SkeletonGraph, n_px: int, **rules) -> SkeletonGraph:
    """An edited copy of ``graph`` (its skeleton back in the input's dtype)."""
    arrays, _ = edit_with_room(lambda room: graph.to_arrays(room=room), lambda a: _run_rules(a, n_px, **rules))
    g = SkeletonGraph.from_arrays(arrays)
    if graph.skeleton.dtype != g.skeleton.dtype:
        g.skeleton = g.skeleton.astype(graph.skeleton.dtype)
    return g


# ------------------------------------------------------------------------------------------------- 4.8.1


def remove_short_valleys(graph: SkeletonGraph, *, max_length_px: float) -> SkeletonGraph:
    """Replace every valley bounded by two endings and shorter than ``max_length_px`` by a pore (seed 4.8.1).

    The pore is placed at the centre of mass of the valley's pixels (both endings included). Returns an edited copy.
    """
    return _edited(graph, 1, sv=positive_number(max_length_px, "max_length_px"))


# ------------------------------------------------------------------------------------------------- 4.8.2


def heal_broken_valleys(
    graph: SkeletonGraph,
    *,
    max_distance_px: float,
    max_angle_deg: float,
    orientation_px: int,
    gaps: GapEvidence | None = None,
) -> SkeletonGraph:
    """Bridge the gaps of broken valleys (seed 4.8.2, Figures 36-38).

    Candidate pairs of valley endings are closer than ``max_distance_px`` and the bridging line deviates by less
    than ``max_angle_deg`` from the continuation of both valleys. They are healed in decreasing order of the
    confidence of eq. 4.4, each ending at most once, and only if the bridging line touches no skeleton pixel other
    than the two endings (so healing never crosses or joins a third valley). Pores in the 8-neighbourhood of the
    bridging line are deleted (they belong to the healed valley). Returns an edited copy.

    Beyond the seed: with ``gaps`` (:class:`GapEvidence`) a gap that crosses a ridge is not healed (module doc).
    """
    heal = (positive_number(max_distance_px, "max_distance_px"), _angle_limit(max_angle_deg, "max_angle_deg"))
    return _edited(graph, _n_px(orientation_px), heal=heal, gaps=_gap_evidence(gaps))


# ------------------------------------------------------------------------------------------------- 4.8.3 / 4.8.4


def remove_short_spurs(
    graph: SkeletonGraph,
    *,
    min_length_px: float,
    max_length_px: float,
    max_deviation_deg: float,
    orientation_px: int,
    flow: RidgeFlow | None = None,
    background: np.ndarray | None = None,
    open_reach_px: float = 3.0,
) -> SkeletonGraph:
    """Delete short spurs roughly perpendicular to their valley (seed 4.8.3, Figures 40-41).

    A spur is a valley from a bifurcation with three valleys to an ending, shorter than ``max_length_px``, whose
    angles with the two other valleys at the bifurcation are within ``max_deviation_deg`` of 90 degrees. The spur
    and its ending are deleted and the bifurcation re-evaluated (it becomes a plain valley point). When the spur is
    longer than ``min_length_px``, a pore is added at its tip. Returns an edited copy.

    Beyond the seed: the spur may also leave a crossing of four valleys where a bridge (4.8.4) continues it
    straight on, the last pore of a row of pores across the ridges (see :func:`remove_bridges`). With ``flow``
    (a :class:`skinstretch.processing.ridge_flow.RidgeFlow`) the angle test is against the ridges (module doc).
    With ``background`` (the out-of-contact mask, bool), a branch ending within ``open_reach_px`` of it is a valley
    leaving the contact, cut short by the contact's edge rather than short: it stays (module doc).
    """
    spurs = (*_length_range(min_length_px, max_length_px), _angle_limit(max_deviation_deg, "max_deviation_deg"))
    return _edited(graph, _n_px(orientation_px), spurs=spurs, flow=flow, background=background,
                   open_reach_px=open_reach_px)


def remove_bridges(
    graph: SkeletonGraph,
    *,
    min_length_px: float,
    max_length_px: float,
    max_deviation_deg: float,
    orientation_px: int,
    flow: RidgeFlow | None = None,
    background: np.ndarray | None = None,
    open_reach_px: float = 3.0,
) -> SkeletonGraph:
    """Replace bridges between adjacent valleys by pores (seed 4.8.4, Figures 43-44).

    A bridge is a valley between two distinct bifurcations of three valleys each, with a length in
    [``min_length_px``, ``max_length_px``] and all four angles with the neighbouring valleys within
    ``max_deviation_deg`` of 90 degrees. It is deleted, a pore is added at its centre of mass and both
    bifurcations are re-evaluated. Returns an edited copy. With ``flow`` the angle test is against the ridges,
    the bridges most squarely across them first; with ``background`` (bool mask) a valley that comes within
    ``open_reach_px`` of it is no bridge (module doc).

    Beyond the seed: a row of pores across several ridges, each wide enough to join its two valleys in the binary
    image, makes a chain of bridges that cross each valley at one point, i.e. nodes of four valleys. A bridge may
    also end at such a crossing when one of the crossing's valleys continues it straight on (within
    ``max_deviation_deg``) and the other two are perpendicular to it; the crossing keeps three valleys and the
    next bridge of the chain is taken on the next pass. Passes repeat until nothing changes.
    """
    bridges = (*_length_range(min_length_px, max_length_px), _angle_limit(max_deviation_deg, "max_deviation_deg"))
    return _edited(graph, _n_px(orientation_px), bridges=bridges, flow=flow, background=background,
                   open_reach_px=open_reach_px)


def edit_graph(
    arrays: GraphArrays,
    *,
    orientation_px: int,
    short_valley_px: float | None = None,
    heal: tuple[float, float] | None = None,
    spurs: tuple[float, float, float] | None = None,
    bridges: tuple[float, float, float] | None = None,
    flow: RidgeFlow | None = None,
    background: np.ndarray | None = None,
    open_reach_px: float = 3.0,
    gaps: GapEvidence | None = None,
) -> np.ndarray:
    """The skeleton rules of seed 4.8.1-4.8.4 in order, on graph arrays edited in place (the extraction's chain).

    Each rule runs when its parameters are given: ``short_valley_px`` (:func:`remove_short_valleys`), ``heal`` =
    (max distance px, max angle deg), ``spurs`` and ``bridges`` = (min length px, max length px, max deviation deg);
    ``flow`` makes the spur and bridge rules judge by the ridge flow, ``background`` keeps the spurs that end
    within ``open_reach_px`` of it and the bridges that come that close, ``gaps`` leaves open the gaps that cross a
    ridge (module doc). The same result as the public functions in turn, in two compiled calls.

    Returns (5, 3) int64 counts of valley endings, valley bifurcations and pores, initially and after each rule (0
    for rules that did not run). Raises :class:`skinstretch.processing.skeleton_graph.GraphCapacityError` when the arrays run out of
    room, leaving them half-edited (see :func:`skinstretch.processing.skeleton_graph.edit_with_room`).
    """
    rules = {}
    if short_valley_px is not None:
        rules["sv"] = positive_number(short_valley_px, "short_valley_px")
    if heal is not None:
        rules["heal"] = (positive_number(heal[0], "max_distance_px"), _angle_limit(heal[1], "max_angle_deg"))
    if spurs is not None:
        rules["spurs"] = (*_length_range(*spurs[:2]), _angle_limit(spurs[2], "max_deviation_deg"))
    if bridges is not None:
        rules["bridges"] = (*_length_range(*bridges[:2]), _angle_limit(bridges[2], "max_deviation_deg"))
    return _run_rules(arrays, _n_px(orientation_px), flow=flow, background=background, open_reach_px=open_reach_px,
                      gaps=_gap_evidence(gaps), **rules)


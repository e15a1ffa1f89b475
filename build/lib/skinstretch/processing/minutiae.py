"""Skeleton analysis (seed 4.7): valley endings, valley bifurcations and pores from the valley skeleton.

Each skeleton pixel is classified by its number of 8-neighbours: 0 = pore, 1 = valley ending, 3 or more = valley
bifurcation pixel, 2 = plain valley. Connected groups of bifurcation pixels are one bifurcation, placed at their
centre of mass. The compiled tracer then walks every valley branch once, from node to node, which turns the skeleton
into a graph: nodes (endings and bifurcations) joined by edges (valleys, with their pixel paths). Orientations
(seed Figure 30) and every editing rule of seed 4.8 work on that graph.

Orientation convention (the feature table's): degrees counter-clockwise from +x with y up the image,
``atan2(-dy, dx)``, in [0, 360). A valley ending points along its valley, from the minutia to the N-th valley pixel;
a bifurcation bisects the smallest angle between its valleys.

The graph is compiled (numba, without the GIL): :class:`GraphArrays` holds it in flat arrays, and the tracer, the
orientations, the feature list and the skeleton rules of seed 4.8.1-4.8.4 all run on those arrays.
:class:`SkeletonGraph` is the same graph in Python lists, for the public functions (:func:`trace_skeleton`,
:func:`node_orientation`, the rules of :mod:`skinstretch.processing.editing`), which convert to and from the arrays.

The rules are compiled here, not in :mod:`skinstretch.processing.editing` (which holds their public functions and their
documentation), because they are built from this module's primitives: numba's disk cache checks only the source
file of each compiled function, so compiled rules in another file would keep stale copies of the primitives after a
change here.
"""

from __future__ import annotations

import math
import operator
from collections import namedtuple
from dataclasses import dataclass, field

import numpy as np

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind
from skinstretch.processing.jit import njit

__all__ = [
    "SkeletonGraph",
    "trace_skeleton",
    "node_kind",
    "branch_direction",
    "node_orientation",
    "GraphArrays",
    "GraphCapacityError",
    "trace_arrays",
    "edit_with_room",
    "graph_features",
]

_ENDING = int(FeatureKind.VALLEY_ENDING)
_BIFURCATION = int(FeatureKind.VALLEY_BIFURCATION)
_PORE = int(FeatureKind.PORE)
_DBL_MIN = 2.2250738585072014e-308

#: The graph in flat arrays, with room for what the editing rules add (an edit that runs out of room raises
#: :class:`GraphCapacityError`; :func:`edit_with_room` starts again with more):
#:
#: - ``node_xy`` (N, 2) float64, ``node_alive`` (N,) bool, ``node_deg`` (N,) int64;
#: - ``node_adj`` (N, W) int64: the edge ids at each node, the first ``node_deg`` entries of the row, in the order
#:   they were attached (a self-loop appears twice);
#: - ``edge_ab`` (E, 2) int64 end nodes, ``edge_span`` (E, 2) int64 start and length of the edge's pixels in
#:   ``path``, ``edge_length`` (E,) float64, ``edge_alive`` (E,) bool;
#: - ``path`` (P, 2) int64: interior pixels (x, y) of the edges, each edge's run from ``edge_ab[e, 0]`` to
#:   ``edge_ab[e, 1]``; a new edge's pixels are appended, old runs are never moved;
#: - ``pore`` (Q, 3) float64 x, y and blob diameter (0 for pores from the skeleton or editing), ``pore_alive``;
#: - ``skeleton`` (H, W) uint8, kept in step with the graph;
#: - ``used`` (4,) int64: numbers of nodes, edges, path pixels and pores in use.
GraphArrays = namedtuple(
    "GraphArrays",
    "node_xy node_alive node_deg node_adj edge_ab edge_span edge_length edge_alive path pore pore_alive skeleton used",
)

_NODES, _EDGES, _PATH, _PORES = 0, 1, 2, 3


class GraphCapacityError(RuntimeError):
    """A compiled edit needed more room than :class:`GraphArrays` had (raised midway: the arrays are then left
    half-edited). The callers start again from their input with more room (``room``); the capacities hold what
    the editing rules can add, except for the path pixels of long merged valleys, so this stays rare."""


# --------------------------------------------------------------------------------------------- numerics


@njit(nogil=True)
def _split(a):  # pragma: no cover - compiled
    c = 134217729.0 * a  # 2**27 + 1: Veltkamp's split into two halves of 26 bits
    hi = c - (c - a)
    return hi, a - hi


@njit(nogil=True)
def _square(x):  # pragma: no cover - compiled
    """x * x as an exact sum hi + lo (Dekker's product; the same pair as CPython's fma form)."""
    z = x * x
    xh, xl = _split(x)
    return z, ((xh * xh - z) + 2.0 * xh * xl) + xl * xl


@njit(nogil=True)
def _hypot(x, y):  # pragma: no cover - compiled
    """CPython's ``math.hypot(x, y)`` bit for bit (Modules/mathmodule.c, vector_norm: lossless scaling, exact
    squares, compensated sum, corrected square root); numba's math.hypot is the C library's, which can differ by
    one ulp."""
    x = abs(x)
    y = abs(y)
    if math.isinf(x) or math.isinf(y):
        return math.inf
    if math.isnan(x) or math.isnan(y):
        return math.nan
    mx = x if x > y else y
    if mx == 0.0:
        return mx
    post = 1.0
    _, e = math.frexp(mx)
    if e < -1023:  # subnormal: scale up first, as CPython does
        x /= _DBL_MIN
        y /= _DBL_MIN
        mx /= _DBL_MIN
        post = _DBL_MIN
        _, e = math.frexp(mx)
    scale = math.ldexp(1.0, -e)
    csum = 1.0
    frac1 = 0.0
    frac2 = 0.0
    for v in (x, y):
        hi, lo = _square(v * scale)
        s = csum + hi
        frac2 += (csum - s) + hi
        csum = s
        frac1 += lo
    h = math.sqrt(csum - 1.0 + (frac1 + frac2))
    hi, lo = _square(h)
    hi = -hi
    lo = -lo
    s = csum + hi
    frac2 += (csum - s) + hi
    csum = s
    frac1 += lo
    h += (csum - 1.0 + (frac1 + frac2)) / (2.0 * h)
    return post * (h / scale)


@njit(nogil=True)
def _angle_deg(dx, dy):  # pragma: no cover - compiled
    return math.degrees(math.atan2(-dy, dx)) % 360.0


# --------------------------------------------------------------------------------------------- tracing


@njit(nogil=True)
def _rank(sorted_px, q):  # pragma: no cover - compiled
    """Index of ``q`` in ``sorted_px`` (bisection; it is there)."""
    lo = 0
    hi = sorted_px.size
    while lo < hi:
        mid = (lo + hi) >> 1
        if sorted_px[mid] < q:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(nogil=True)
def _neighbours(f, i, offs):  # pragma: no cover - compiled
    c = 0
    for j in range(8):
        if f[i + offs[j]] != 0:
            c += 1
    return c


@njit(nogil=True)
def _trace_graph(src, pore_x, pore_y, pore_size, room):  # pragma: no cover - compiled
    """The graph of the skeleton ``src`` (uint8 (H, W) C-ordered, non-zero on the skeleton; its outer ring is
    ignored).

    Isolated pixels become pores, followed by the extra pores given; self-loops shorter than 4 px are dropped.
    The arrays get the room editing can need (see :class:`GraphCapacityError`), ``room`` times. Apart from the
    skeleton it returns (0/1), the only image-sized state is that skeleton: while tracing, its bytes
    hold 1 + the neighbour count (and 16 once a valley pixel is traced), and the node of a node pixel is found by
    bisection in the sorted node pixels.
    """
    h, w = src.shape
    n = h * w
    sk = np.empty((h, w), np.uint8)
    f = sk.reshape(n)
    s = src.reshape(n)
    for i in range(n):
        f[i] = s[i] != 0
    for x in range(w):
        f[x] = 0
        f[n - w + x] = 0
    for y in range(1, h - 1):
        f[y * w] = 0
        f[y * w + w - 1] = 0
    # Skeleton pixels in raster order, eight bytes (0/1) at a time: a skeleton covers ~3% of a frame. The product
    # with 0x0101... sums a word's bytes into its top byte; with 0x0001...07, the lowest set byte's index.
    n8 = n // 8
    words = f[: n8 * 8].view(np.uint64)
    n_sk = 0
    for j in range(n8):
        n_sk += np.int64((words[j] * np.uint64(0x0101010101010101)) >> np.uint64(56))
    for i in range(n8 * 8, n):
        n_sk += f[i]
    offs = np.array([-w, -w + 1, 1, w + 1, w, w - 1, -1, -w - 1])
    pix = np.empty(n_sk, np.int64)
    k = 0
    for j in range(n8):
        wd = words[j]
        while wd != 0:
            low = wd & (~wd + np.uint64(1))
            wd ^= low
            pix[k] = 8 * j + np.int64((low * np.uint64(0x0001020304050607)) >> np.uint64(56))
            k += 1
    for i in range(n8 * 8, n):
        if f[i]:
            pix[k] = i
            k += 1
    # Neighbour counts, kept in the skeleton bytes as 1 + count (still non-zero for the pixels counted later).
    n_node_px = 0
    node_px_deg = 0
    n_iso = 0
    for k in range(n_sk):
        i = pix[k]
        c = _neighbours(f, i, offs)
        f[i] = 1 + c
        if c == 1 or c >= 3:
            n_node_px += 1
            node_px_deg += c
        elif c == 0:
            n_iso += 1
    node_px = np.empty(n_node_px, np.int64)
    r = 0
    for k in range(n_sk):
        d = f[pix[k]] - 1
        if d == 1 or d >= 3:
            node_px[r] = pix[k]
            r += 1
    # Nodes: endings (1 neighbour) and 8-connected groups of bifurcation pixels (3+ neighbours), numbered in the
    # raster order of their first pixel.
    node_id = np.full(n_node_px, -1, np.int64)
    sx = np.zeros(n_node_px)
    sy = np.zeros(n_node_px)
    sn = np.zeros(n_node_px, np.int64)
    iso = np.empty(n_iso, np.int64)
    stack = np.empty(n_node_px, np.int64)
    n_nodes = 0
    n_iso = 0
    r = 0
    for k in range(n_sk):
        i = pix[k]
        d = f[i] - 1
        if d == 0:
            iso[n_iso] = i
            n_iso += 1
        elif d == 1:
            node_id[r] = n_nodes
            sx[n_nodes] = i % w
            sy[n_nodes] = i // w
            sn[n_nodes] = 1
            n_nodes += 1
            r += 1
        elif d >= 3:
            if node_id[r] < 0:
                node_id[r] = n_nodes
                stack[0] = i
                top = 1
                while top > 0:
                    top -= 1
                    p = stack[top]
                    sx[n_nodes] += p % w
                    sy[n_nodes] += p // w
                    sn[n_nodes] += 1
                    for j in range(8):
                        q = p + offs[j]
                        if f[q] != 0 and f[q] - 1 >= 3:
                            rq = _rank(node_px, q)
                            if node_id[rq] < 0:
                                node_id[rq] = n_nodes
                                stack[top] = q
                                top += 1
                n_nodes += 1
            r += 1
    # Edges: every branch traced once, from a node pixel to the next node pixel. An edge leaves a node pixel toward
    # one of its neighbours, so there are at most node_px_deg of them. Editing adds at most as many again plus half
    # the number of nodes (each merge removes two edges; each healing at least one, and uses two endings).
    dxs = np.array([0, 1, 1, 1, 0, -1, -1, -1])
    dys = np.array([-1, -1, 0, 1, 1, 1, 0, -1])
    steplen = np.array([1.0, math.sqrt(2.0), 1.0, math.sqrt(2.0), 1.0, math.sqrt(2.0), 1.0, math.sqrt(2.0)])
    cap = (3 * node_px_deg + 16) * room
    edge_ab = np.empty((cap, 2), np.int64)
    edge_span = np.empty((cap, 2), np.int64)
    edge_length = np.empty(cap)
    # Every valley pixel is written once at most (a pixel with two neighbours is entered from one and left by the
    # other, and a traced one is never entered again): the path needs no more room than the skeleton's pixels.
    # (Growing it inside the loop would cost a third of the tracing time.) Twice as much again is left for editing,
    # which appends the pixels of every merged valley: up to 2x the skeleton's pixels in all on the simulated scenes.
    path = np.empty(((3 * n_sk + 64) * room, 2), np.int64)
    n_path = 0
    n_edges = 0
    r = 0
    for k in range(n_sk):
        p = pix[k]
        dp = (f[p] & 15) - 1
        if not (dp == 1 or dp >= 3):
            continue
        a = node_id[r]
        r += 1
        px = p % w
        py = p // w
        for j in range(8):
            q = p + offs[j]
            fq = f[q]
            if fq == 0:
                continue
            dq = (fq & 15) - 1
            if dq == 1 or dq >= 3:
                b = node_id[_rank(node_px, q)]
                # Two node pixels touching: an edge without interior pixels, recorded once (from the ending side).
                if b != a and dp == 1 and (dq != 1 or p < q):
                    edge_ab[n_edges, 0] = a
                    edge_ab[n_edges, 1] = b
                    edge_span[n_edges, 0] = n_path
                    edge_span[n_edges, 1] = 0
                    edge_length[n_edges] = steplen[j]
                    n_edges += 1
                continue
            if fq & 16:  # already traced from its other end
                continue
            start = n_path
            length = steplen[j]
            prev = p
            cur = q
            cx = px + dxs[j]
            cy = py + dys[j]
            end_node = -1
            while True:
                f[cur] |= 16
                path[n_path, 0] = cx
                path[n_path, 1] = cy
                n_path += 1
                # A plain valley pixel has exactly two neighbours: the one we came from and the next.
                nxt = -1
                nxt_j = 0
                for jj in range(8):
                    rr = cur + offs[jj]
                    if f[rr] != 0 and rr != prev:
                        nxt = rr
                        nxt_j = jj
                        break
                if nxt < 0:
                    break
                length += steplen[nxt_j]
                dn = (f[nxt] & 15) - 1
                if dn == 1 or dn >= 3:
                    end_node = node_id[_rank(node_px, nxt)]
                    break
                prev = cur
                cur = nxt
                cx += dxs[nxt_j]
                cy += dys[nxt_j]
            # A branch that dead-ends without reaching a node cannot happen on a valid skeleton: dropped. Self-loops
            # shorter than 4 px are a thick junction's inner corner, not a valley: dropped.
            if end_node < 0 or (end_node == a and length < 4.0):
                n_path = start
                continue
            edge_ab[n_edges, 0] = a
            edge_ab[n_edges, 1] = end_node
            edge_span[n_edges, 0] = start
            edge_span[n_edges, 1] = n_path - start
            edge_length[n_edges] = length
            n_edges += 1
    for k in range(n_sk):
        f[pix[k]] = 1
    edge_alive = np.zeros(edge_ab.shape[0], np.bool_)
    for e in range(n_edges):
        edge_alive[e] = True
    node_deg = np.zeros(n_nodes, np.int64)
    for e in range(n_edges):
        node_deg[edge_ab[e, 0]] += 1
        node_deg[edge_ab[e, 1]] += 1
    width = 4
    for v in range(n_nodes):
        width = max(width, node_deg[v])
    node_adj = np.zeros((n_nodes, width * room), np.int64)  # editing never raises a node's degree
    for v in range(n_nodes):
        node_deg[v] = 0
    for e in range(n_edges):
        for a in (edge_ab[e, 0], edge_ab[e, 1]):
            node_adj[a, node_deg[a]] = e
            node_deg[a] += 1
    node_xy = np.empty((n_nodes, 2))
    node_alive = np.empty(n_nodes, np.bool_)
    for v in range(n_nodes):
        m = max(sn[v], 1)
        node_xy[v, 0] = sx[v] / m
        node_xy[v, 1] = sy[v] / m
        node_alive[v] = node_deg[v] > 0
    n_pores = n_iso + pore_x.size
    pore = np.zeros(((n_pores + 2 * n_edges + n_nodes + 16) * room, 3))  # one pore per edge removed at most
    pore_alive = np.zeros(pore.shape[0], np.bool_)
    for k in range(n_iso):
        pore[k, 0] = iso[k] % w
        pore[k, 1] = iso[k] // w
    for k in range(pore_x.size):
        pore[n_iso + k, 0] = pore_x[k]
        pore[n_iso + k, 1] = pore_y[k]
        pore[n_iso + k, 2] = pore_size[k]
    for k in range(n_pores):
        pore_alive[k] = True
    used = np.array([n_nodes, n_edges, n_path, n_pores], np.int64)
    return GraphArrays(
        node_xy, node_alive, node_deg, node_adj, edge_ab, edge_span, edge_length, edge_alive, path, pore, pore_alive,
        sk, used,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------- primitives
# The compiled forms of the SkeletonGraph methods of the same names, with the same effects in the same order.


@njit(nogil=True)
def _other_end(G, edge, node):  # pragma: no cover - compiled
    return G.edge_ab[edge, 1] if G.edge_ab[edge, 0] == node else G.edge_ab[edge, 0]


@njit(nogil=True)
def _detach(G, node, edge):  # pragma: no cover - compiled
    """Remove the first ``edge`` from the node's list, keeping the order of the others (list.remove)."""
    d = G.node_deg[node]
    for k in range(d):
        if G.node_adj[node, k] == edge:
            for j in range(k, d - 1):
                G.node_adj[node, j] = G.node_adj[node, j + 1]
            G.node_deg[node] = d - 1
            return
    raise ValueError("edge not listed at its node")


# (remove_edge and remove_node with erase=False and erase=True are separate functions: numba would compile a
# function twice, once for each literal value of a flag.)


@njit(nogil=True)
def _unlink_edge(G, edge):  # pragma: no cover - compiled
    """``remove_edge(edge, erase=False)``; returns whether the edge was alive."""
    if not G.edge_alive[edge]:
        return False
    G.edge_alive[edge] = False
    _detach(G, G.edge_ab[edge, 0], edge)
    _detach(G, G.edge_ab[edge, 1], edge)
    return True


@njit(nogil=True)
def _remove_edge(G, edge):  # pragma: no cover - compiled
    """``remove_edge(edge)``: its pixels are erased."""
    if _unlink_edge(G, edge):
        s = G.edge_span[edge, 0]
        for k in range(s, s + G.edge_span[edge, 1]):
            G.skeleton[G.path[k, 1], G.path[k, 0]] = 0


@njit(nogil=True)
def _remove_node(G, node):  # pragma: no cover - compiled
    """``remove_node(node)``: its pixel is erased."""
    G.node_alive[node] = False
    G.skeleton[int(np.rint(G.node_xy[node, 1])), int(np.rint(G.node_xy[node, 0]))] = 0


@njit(nogil=True)
def _add_edge(G, a, b, start, count, length):  # pragma: no cover - compiled
    """Append the edge (a, b) whose pixels are ``path[start:start + count]``; returns its id."""
    e = G.used[_EDGES]
    if e >= G.edge_ab.shape[0] or max(G.node_deg[a] + (a == b), G.node_deg[b]) >= G.node_adj.shape[1]:
        raise GraphCapacityError("no room for an edge")
    G.edge_ab[e, 0] = a
    G.edge_ab[e, 1] = b
    G.edge_span[e, 0] = start
    G.edge_span[e, 1] = count
    G.edge_length[e] = length
    G.edge_alive[e] = True
    G.node_adj[a, G.node_deg[a]] = e
    G.node_deg[a] += 1
    G.node_adj[b, G.node_deg[b]] = e
    G.node_deg[b] += 1
    G.used[_EDGES] = e + 1
    return e


@njit(nogil=True)
def _add_pore(G, x, y, size):  # pragma: no cover - compiled
    q = G.used[_PORES]
    if q >= G.pore.shape[0]:
        raise GraphCapacityError("no room for a pore")
    G.pore[q, 0] = x
    G.pore[q, 1] = y
    G.pore[q, 2] = size
    G.pore_alive[q] = True
    G.used[_PORES] = q + 1


@njit(nogil=True)
def _path_room(G, n):  # pragma: no cover - compiled
    """Check that ``n`` more path pixels fit; returns where they go."""
    start = G.used[_PATH]
    if start + n > G.path.shape[0]:
        raise GraphCapacityError("no room for path pixels")
    return start


@njit(nogil=True)
def _put_path_from(G, dst, edge, node):  # pragma: no cover - compiled
    """Copy the pixels of ``edge`` ordered away from ``node`` to ``path[dst:]`` (room checked); returns the end."""
    s = G.edge_span[edge, 0]
    m = G.edge_span[edge, 1]
    if G.edge_ab[edge, 0] == node:
        for k in range(m):
            G.path[dst + k, 0] = G.path[s + k, 0]
            G.path[dst + k, 1] = G.path[s + k, 1]
    else:
        for k in range(m):
            G.path[dst + k, 0] = G.path[s + m - 1 - k, 0]
            G.path[dst + k, 1] = G.path[s + m - 1 - k, 1]
    return dst + m


@njit(nogil=True)
def _settle(G, node):  # pragma: no cover - compiled
    """See :meth:`SkeletonGraph.settle`."""
    if not G.node_alive[node]:
        return
    d = G.node_deg[node]
    if d == 0:
        G.node_alive[node] = False
    elif d == 2 and G.node_adj[node, 0] != G.node_adj[node, 1]:
        e1 = G.node_adj[node, 0]
        e2 = G.node_adj[node, 1]
        a = _other_end(G, e1, node)
        b = _other_end(G, e2, node)
        start = _path_room(G, G.edge_span[e1, 1] + 1 + G.edge_span[e2, 1])
        if G.used[_EDGES] >= G.edge_ab.shape[0]:
            raise GraphCapacityError("no room for an edge")
        k = _put_path_from(G, start, e1, a)
        G.path[k, 0] = int(np.rint(G.node_xy[node, 0]))
        G.path[k, 1] = int(np.rint(G.node_xy[node, 1]))
        k = _put_path_from(G, k + 1, e2, node)
        G.used[_PATH] = k
        length = G.edge_length[e1] + G.edge_length[e2]
        _unlink_edge(G, e1)
        _unlink_edge(G, e2)
        G.node_alive[node] = False
        _add_edge(G, a, b, start, k - start, length)


@njit(nogil=True)
def _alive_edges(G):  # pragma: no cover - compiled
    ne = G.used[_EDGES]
    out = np.empty(ne, np.int64)
    k = 0
    for e in range(ne):
        if G.edge_alive[e]:
            out[k] = e
            k += 1
    return out[:k]


# --------------------------------------------------------------------------------------------- orientation


@njit(nogil=True)
def _direction(path, start, m, reverse, x0, y0, ox, oy, n_px):  # pragma: no cover - compiled
    """:func:`branch_direction` of a node at (x0, y0) along the ``m`` pixels ``path[start:start + m]`` (taken from the
    far end when ``reverse``); (ox, oy) is the other node, the target of an edge without pixels."""
    if m >= 1:
        k = min(n_px, m) - 1
        if reverse:
            k = m - 1 - k
        tx = float(path[start + k, 0])
        ty = float(path[start + k, 1])
    else:
        tx = ox
        ty = oy
    dx = tx - x0
    dy = ty - y0
    norm = _hypot(dx, dy)
    if norm == 0:
        return 0.0, 0.0, False
    return dx / norm, dy / norm, m + 1 >= max(n_px // 2, 2)


@njit(nogil=True)
def _edge_direction(G, node, edge, n_px):  # pragma: no cover - compiled
    a = G.edge_ab[edge, 0]
    other = G.edge_ab[edge, 1] if a == node else a
    return _direction(
        G.path, G.edge_span[edge, 0], G.edge_span[edge, 1], a != node, G.node_xy[node, 0], G.node_xy[node, 1],
        G.node_xy[other, 0], G.node_xy[other, 1], n_px,
    )  # fmt: skip


@njit(nogil=True)
def _orientation(d, ax, ay, aok, bx, by, bok, cx, cy, cok):  # pragma: no cover - compiled
    """:func:`node_orientation` of a node with ``d`` valleys from the directions of its first three (unused ones
    ignored)."""
    if d == 1:
        return _angle_deg(ax, ay) if aok else math.nan
    if d != 3 or not (aok and bok and cok):
        return math.nan
    # The pair with the largest cosine (the first one on ties), in the order (0, 1), (0, 2), (1, 2).
    best = ax * bx + ay * by
    sx = ax + bx
    sy = ay + by
    cos = ax * cx + ay * cy
    if cos > best:
        best = cos
        sx = ax + cx
        sy = ay + cy
    cos = bx * cx + by * cy
    if cos > best:
        sx = bx + cx
        sy = by + cy
    if _hypot(sx, sy) < 1e-9:
        return math.nan
    return _angle_deg(sx, sy)


@njit(nogil=True)
def _node_orientation(G, node, n_px):  # pragma: no cover - compiled
    d = G.node_deg[node]
    if d != 1 and d != 3:
        return math.nan
    ax, ay, aok = _edge_direction(G, node, G.node_adj[node, 0], n_px)
    if d == 1:
        return _orientation(d, ax, ay, aok, ax, ay, aok, ax, ay, aok)  # (no literals: one compiled version)
    bx, by, bok = _edge_direction(G, node, G.node_adj[node, 1], n_px)
    cx, cy, cok = _edge_direction(G, node, G.node_adj[node, 2], n_px)
    return _orientation(d, ax, ay, aok, bx, by, bok, cx, cy, cok)


@njit(nogil=True)
def _counts(G, out):  # pragma: no cover - compiled
    """Valley endings, valley bifurcations and pores alive, into ``out`` (3,)."""
    ends = 0
    bifs = 0
    for v in range(G.used[_NODES]):
        if G.node_alive[v]:
            d = G.node_deg[v]
            if d == 1:
                ends += 1
            elif d >= 3:
                bifs += 1
    pores = 0
    for q in range(G.used[_PORES]):
        if G.pore_alive[q]:
            pores += 1
    out[0] = ends
    out[1] = bifs
    out[2] = pores


@njit(nogil=True)
def _features(G, n_px):  # pragma: no cover - compiled
    n = 0
    for v in range(G.used[_NODES]):
        if G.node_alive[v] and G.node_deg[v] != 0 and G.node_deg[v] != 2:
            n += 1
    for q in range(G.used[_PORES]):
        if G.pore_alive[q]:
            n += 1
    x = np.empty(n)
    y = np.empty(n)
    kind = np.empty(n, np.int8)
    orient = np.empty(n)
    size = np.empty(n)
    k = 0
    for v in range(G.used[_NODES]):
        d = G.node_deg[v]
        if not G.node_alive[v] or d == 0 or d == 2:
            continue
        x[k] = G.node_xy[v, 0]
        y[k] = G.node_xy[v, 1]
        kind[k] = _ENDING if d == 1 else _BIFURCATION
        orient[k] = _node_orientation(G, v, n_px)
        size[k] = 0.0
        k += 1
    for q in range(G.used[_PORES]):
        if G.pore_alive[q]:
            x[k] = G.pore[q, 0]
            y[k] = G.pore[q, 1]
            kind[k] = _PORE
            orient[k] = math.nan
            size[k] = G.pore[q, 2]
            k += 1
    return x, y, kind, orient, size


# --------------------------------------------------------------------------------------------- editing rules
# Seed 4.8.1-4.8.4, documented with their public functions in skinstretch.processing.editing. The results depend on the order
# of the loops, which is part of the rules: edges and nodes in id order, a pass visiting the edges alive when it
# starts (an edge a merge creates waits for the next pass), sums in the order written.


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
    """:func:`skinstretch.processing.editing.line_pixels`."""
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
def _short_spurs(G, lo, hi, max_dev, n_px):  # pragma: no cover - compiled
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
        if not _bridge_end(G, bif, e, n_px, max_dev):
            continue
        tx = G.node_xy[end, 0]
        ty = G.node_xy[end, 1]
        _remove_edge(G, e)
        _remove_node(G, end)
        _settle(G, bif)
        if G.edge_length[e] > lo:
            _add_pore(G, tx, ty, 0.0)


@njit(nogil=True)
def _bridges(G, lo, hi, max_dev, n_px):  # pragma: no cover - compiled
    changed = True
    while changed:
        changed = False
        for e in _alive_edges(G):
            if not G.edge_alive[e]:
                continue
            a = G.edge_ab[e, 0]
            b = G.edge_ab[e, 1]
            length = G.edge_length[e]
            if a == b or not (lo <= length <= hi):
                continue
            if not (_bridge_end(G, a, e, n_px, max_dev) and _bridge_end(G, b, e, n_px, max_dev)):
                continue
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
    bridge_dev, n_px,
):  # pragma: no cover - compiled  # fmt: skip
    """Extraction's editing, second part: 4.8.2, 4.8.3, 4.8.4, each when its upper length is > 0, with counts."""
    if heal_px > 0:
        _heal_apply(G, ends, iu, ju, dist, acos, heal_px, heal_deg)
        _counts(G, counts[2])
    if spur_hi > 0:
        _short_spurs(G, spur_lo, spur_hi, spur_dev, n_px)
        _counts(G, counts[3])
    if bridge_hi > 0:
        _bridges(G, bridge_lo, bridge_hi, bridge_dev, n_px)
        _counts(G, counts[4])


# --------------------------------------------------------------------------------------------- Python side


@dataclass
class SkeletonGraph:
    """The valley skeleton as a graph, plus the pores. Mutable; editing steps work on copies (:meth:`copy`).

    The Python-list form of :class:`GraphArrays` (:meth:`to_arrays`, :meth:`from_arrays`).

    Attributes
    ----------
    node_x, node_y : list of float
        Node positions in pixels (endings: the end pixel; bifurcations: centre of mass of the pixel group).
    node_alive : list of bool
    node_edges : list of list of int
        Edge ids at each node (a self-loop appears twice).
    edge_a, edge_b : list of int
        End nodes of each edge; ``edge_path[e]`` runs from ``edge_a`` to ``edge_b``.
    edge_path : list of (K, 2) int arrays
        Interior pixels (x, y) of the valley, in order.
    edge_length : list of float
        Length in pixels from node to node along the valley.
    edge_alive : list of bool
    pore_x, pore_y : list of float
    pore_alive : list of bool
    pore_size : list of float
        Blob diameter in pixels (0 for pores found on the skeleton or by editing).
    skeleton : (H, W) uint8
        The skeleton raster, kept in step with the graph (healing draws into it, spur/bridge removal erase).
    """

    node_x: list
    node_y: list
    node_alive: list
    node_edges: list
    edge_a: list
    edge_b: list
    edge_path: list
    edge_length: list
    edge_alive: list
    pore_x: list
    pore_y: list
    pore_alive: list
    skeleton: np.ndarray
    pore_size: list = field(default_factory=list)

    def copy(self) -> "SkeletonGraph":
        return SkeletonGraph(
            node_x=list(self.node_x),
            node_y=list(self.node_y),
            node_alive=list(self.node_alive),
            node_edges=[list(e) for e in self.node_edges],
            edge_a=list(self.edge_a),
            edge_b=list(self.edge_b),
            edge_path=list(self.edge_path),
            edge_length=list(self.edge_length),
            edge_alive=list(self.edge_alive),
            pore_x=list(self.pore_x),
            pore_y=list(self.pore_y),
            pore_alive=list(self.pore_alive),
            skeleton=self.skeleton.copy(),
            pore_size=list(self.pore_size),
        )

    # -- arrays -----------------------------------------------------------------------------------------------
    def to_arrays(self, *, room: int = 1, copy_skeleton: bool = True) -> GraphArrays:
        """This graph as :class:`GraphArrays`, with the room editing needs (``room`` times; see
        :class:`GraphCapacityError`) and a uint8 copy of the skeleton (no copy when ``copy_skeleton`` is False and
        it is a C-ordered uint8 array already). Pores without a size get 0."""
        nn, ne, nq = len(self.node_x), len(self.edge_a), len(self.pore_x)
        node_xy = np.empty((nn, 2))
        node_xy[:, 0] = self.node_x
        node_xy[:, 1] = self.node_y
        degrees = [len(edges) for edges in self.node_edges]
        node_adj = np.zeros((nn, max([4, *degrees]) * room), np.int64)
        for v, edges in enumerate(self.node_edges):
            node_adj[v, : len(edges)] = edges
        cap_e = (2 * ne + nn + 16) * room
        edge_ab = np.zeros((cap_e, 2), np.int64)
        edge_ab[:ne, 0] = self.edge_a
        edge_ab[:ne, 1] = self.edge_b
        paths = [np.asarray(p, dtype=np.int64).reshape(-1, 2) for p in self.edge_path]
        lengths = np.array([len(p) for p in paths], dtype=np.int64)
        n_path = int(lengths.sum())
        path = np.zeros(((3 * n_path + 64) * room, 2), np.int64)
        if n_path:
            path[:n_path] = np.concatenate(paths)
        edge_span = np.zeros((cap_e, 2), np.int64)
        edge_span[:ne, 0] = np.cumsum(lengths) - lengths
        edge_span[:ne, 1] = lengths
        edge_length = np.zeros(cap_e)
        edge_length[:ne] = self.edge_length
        edge_alive = np.zeros(cap_e, bool)
        edge_alive[:ne] = self.edge_alive
        pore = np.zeros(((nq + 2 * ne + nn + 16) * room, 3))
        pore[:nq, 0] = self.pore_x
        pore[:nq, 1] = self.pore_y
        sizes = list(self.pore_size)[:nq]
        pore[: len(sizes), 2] = sizes
        pore_alive = np.zeros(pore.shape[0], bool)
        pore_alive[:nq] = self.pore_alive
        if copy_skeleton:
            skeleton = np.array(self.skeleton, dtype=np.uint8, order="C")
        else:
            skeleton = np.ascontiguousarray(self.skeleton, dtype=np.uint8)
        return GraphArrays(
            node_xy=node_xy,
            node_alive=np.array(self.node_alive, dtype=bool).reshape(nn),
            node_deg=np.array(degrees, dtype=np.int64).reshape(nn),
            node_adj=node_adj,
            edge_ab=edge_ab,
            edge_span=edge_span,
            edge_length=edge_length,
            edge_alive=edge_alive,
            path=path,
            pore=pore,
            pore_alive=pore_alive,
            skeleton=skeleton,
            used=np.array([nn, ne, n_path, nq], dtype=np.int64),
        )

    @classmethod
    def from_arrays(cls, arrays: GraphArrays) -> "SkeletonGraph":
        """The graph held by ``arrays`` (its paths are views of ``arrays.path``; its skeleton is
        ``arrays.skeleton``)."""
        G = arrays
        nn, ne, _, nq = G.used.tolist()
        path = G.path
        return cls(
            node_x=G.node_xy[:nn, 0].tolist(),
            node_y=G.node_xy[:nn, 1].tolist(),
            node_alive=G.node_alive[:nn].tolist(),
            node_edges=[row[:d].tolist() for row, d in zip(G.node_adj[:nn], G.node_deg[:nn].tolist())],
            edge_a=G.edge_ab[:ne, 0].tolist(),
            edge_b=G.edge_ab[:ne, 1].tolist(),
            edge_path=[path[s : s + k] for s, k in G.edge_span[:ne].tolist()],
            edge_length=G.edge_length[:ne].tolist(),
            edge_alive=G.edge_alive[:ne].tolist(),
            pore_x=G.pore[:nq, 0].tolist(),
            pore_y=G.pore[:nq, 1].tolist(),
            pore_alive=G.pore_alive[:nq].tolist(),
            skeleton=G.skeleton,
            pore_size=G.pore[:nq, 2].tolist(),
        )

    # -- queries ----------------------------------------------------------------------------------------------
    def degree(self, node: int) -> int:
        return len(self.node_edges[node])

    def other_end(self, edge: int, node: int) -> int:
        return self.edge_b[edge] if self.edge_a[edge] == node else self.edge_a[edge]

    def path_from(self, edge: int, node: int) -> np.ndarray:
        """Interior pixels of ``edge`` ordered away from ``node``."""
        p = self.edge_path[edge]
        return p if self.edge_a[edge] == node else p[::-1]

    def alive_nodes(self) -> list[int]:
        return [n for n, a in enumerate(self.node_alive) if a]

    def alive_edges(self) -> list[int]:
        return [e for e, a in enumerate(self.edge_alive) if a]

    # -- edits ------------------------------------------------------------------------------------------------
    def add_pore(self, x: float, y: float, size: float = 0.0) -> None:
        """Add a pore at (x, y); ``size`` is its blob diameter in pixels (0 when it comes from the skeleton)."""
        self.pore_x.append(float(x))
        self.pore_y.append(float(y))
        self.pore_alive.append(True)
        self.pore_size.append(float(size))

    def add_pores(self, x, y, sizes=None) -> None:
        """Add pores at arrays of positions ``x``, ``y`` with blob diameters ``sizes`` (default 0)."""
        x = np.asarray(x, dtype=np.float64).ravel()
        y = np.asarray(y, dtype=np.float64).ravel()
        sizes = np.zeros(x.size) if sizes is None else np.asarray(sizes, dtype=np.float64).ravel()
        if not x.size == y.size == sizes.size:
            raise InvalidInputError(f"x, y and sizes differ in length: {x.size}, {y.size}, {sizes.size}")
        self.pore_x.extend(x.tolist())
        self.pore_y.extend(y.tolist())
        self.pore_alive.extend([True] * x.size)
        self.pore_size.extend(sizes.tolist())

    def add_node(self, x: float, y: float) -> int:
        self.node_x.append(float(x))
        self.node_y.append(float(y))
        self.node_alive.append(True)
        self.node_edges.append([])
        return len(self.node_x) - 1

    def add_edge(self, a: int, b: int, path: np.ndarray, length: float) -> int:
        e = len(self.edge_a)
        self.edge_a.append(a)
        self.edge_b.append(b)
        self.edge_path.append(np.asarray(path, dtype=np.int64).reshape(-1, 2))
        self.edge_length.append(float(length))
        self.edge_alive.append(True)
        self.node_edges[a].append(e)
        self.node_edges[b].append(e)
        return e

    def remove_edge(self, edge: int, *, erase: bool = True) -> None:
        if not self.edge_alive[edge]:
            return
        self.edge_alive[edge] = False
        self.node_edges[self.edge_a[edge]].remove(edge)
        self.node_edges[self.edge_b[edge]].remove(edge)
        if erase and len(self.edge_path[edge]):
            p = self.edge_path[edge]
            self.skeleton[p[:, 1], p[:, 0]] = 0

    def remove_node(self, node: int, *, erase: bool = True) -> None:
        """Delete a node with no edges left; erase its pixel if asked (endings)."""
        self.node_alive[node] = False
        if erase:
            x, y = int(round(self.node_x[node])), int(round(self.node_y[node]))
            self.skeleton[y, x] = 0

    def settle(self, node: int) -> None:
        """Re-evaluate ``node`` after an edge was removed (seed 4.8.3): a node left with two valleys is no longer
        a bifurcation, so its two edges merge into one (their pixels joined through the node's pixel); a node left
        with none disappears. Runs the compiled rule (the lists are updated in place)."""
        if not self.node_alive[node]:
            return
        node = operator.index(node)
        arrays, _ = edit_with_room(lambda room: self.to_arrays(room=room, copy_skeleton=False),
                                   lambda arrays: _settle(arrays, node))
        new = SkeletonGraph.from_arrays(arrays)
        for name in ("node_x", "node_y", "node_alive", "edge_a", "edge_b", "edge_path", "edge_length", "edge_alive"):
            getattr(self, name)[:] = getattr(new, name)
        for edges, new_edges in zip(self.node_edges, new.node_edges):
            edges[:] = new_edges


def edit_with_room(make, edit):
    """``edit(make(room))`` with ``room`` 1, then 4, 16... while the arrays ``make`` gives run out of room
    (:class:`GraphCapacityError`); returns the edited arrays and what ``edit`` returned."""
    room = 1
    while True:
        arrays = make(room)
        try:
            return arrays, edit(arrays)
        except GraphCapacityError:
            if room >= 4**6:  # the rules add a bounded amount: this far means a bug, not a large skeleton
                raise
            room *= 4


def _skeleton_bytes(skeleton: np.ndarray) -> np.ndarray:
    if not isinstance(skeleton, np.ndarray) or skeleton.ndim != 2 or min(skeleton.shape) < 3:
        raise InvalidInputError(f"skeleton must be a 2-D image at least 3x3, got {getattr(skeleton, 'shape', skeleton)}")
    src = skeleton if skeleton.dtype == np.uint8 else (skeleton != 0).view(np.uint8)
    return np.ascontiguousarray(src)


def trace_arrays(skeleton: np.ndarray, pore_x=None, pore_y=None, pore_size=None, *, room: int = 1) -> GraphArrays:
    """:func:`trace_skeleton` as :class:`GraphArrays`, with extra pores (positions, blob diameters; default none)
    after the isolated skeleton pixels and ``room`` times the room editing needs (:class:`GraphCapacityError`)."""
    src = _skeleton_bytes(skeleton)
    px = np.zeros(0) if pore_x is None else np.ascontiguousarray(pore_x, dtype=np.float64).ravel()
    py = np.zeros(0) if pore_y is None else np.ascontiguousarray(pore_y, dtype=np.float64).ravel()
    ps = np.zeros(px.size) if pore_size is None else np.ascontiguousarray(pore_size, dtype=np.float64).ravel()
    if not px.size == py.size == ps.size:
        raise InvalidInputError(f"pore_x, pore_y and pore_size differ in length: {px.size}, {py.size}, {ps.size}")
    return _trace_graph(src, px, py, ps, operator.index(room))


def trace_skeleton(skeleton: np.ndarray) -> SkeletonGraph:
    """Build the :class:`SkeletonGraph` of a valley skeleton (seed 4.7, Figure 29).

    Parameters
    ----------
    skeleton : (H, W) uint8
        1 (non-zero) on the skeleton, 8-connected and near minimal (the output of :func:`skinstretch.processing.thinning.thin`).

    Returns
    -------
    SkeletonGraph
        Isolated skeleton pixels become pores; self-loops shorter than 4 pixels (a thick junction's inner corner)
        are dropped.

    Examples
    --------
    >>> import numpy as np
    >>> s = np.zeros((7, 12), np.uint8); s[3, 2:10] = 1
    >>> g = trace_skeleton(s)
    >>> [node_kind(g, n) for n in g.alive_nodes()], [round(l, 1) for l in g.edge_length]
    ([0, 0], [7.0])
    """
    return SkeletonGraph.from_arrays(trace_arrays(skeleton))


def graph_features(arrays: GraphArrays, *, n_px: int):
    """The features of ``arrays``: the nodes that are minutiae (in id order), then the pores alive.

    Returns x, y (float64), kind (int8 :class:`FeatureKind`), orientation (:func:`node_orientation`; NaN for pores)
    and size (blob diameter; 0 for minutiae).
    """
    return _features(arrays, _n_px(n_px))


def _n_px(n_px) -> int:
    try:
        n = operator.index(n_px)
    except TypeError:
        raise InvalidInputError(f"n_px must be an integer, got {n_px!r}") from None
    if n < 1:
        raise InvalidInputError(f"n_px must be >= 1, got {n_px!r}")
    return n


def node_kind(graph: SkeletonGraph, node: int) -> int:
    """:class:`FeatureKind` of a node from its number of valleys (1 ending, 3+ bifurcation), or -1 (plain valley)."""
    d = graph.degree(node)
    if d == 1:
        return int(FeatureKind.VALLEY_ENDING)
    if d >= 3:
        return int(FeatureKind.VALLEY_BIFURCATION)
    return -1


def branch_direction(graph: SkeletonGraph, node: int, edge: int, *, n_px: int) -> tuple[float, float, bool]:
    """Unit vector (dx, dy) from ``node`` to the ``n_px``-th pixel of ``edge`` (seed 4.7), and whether the valley
    was long enough (at least ``n_px // 2`` pixels) to trust it."""
    path = np.ascontiguousarray(graph.edge_path[edge], dtype=np.int64).reshape(-1, 2)
    other = graph.other_end(edge, node)
    return _direction(
        path, 0, path.shape[0], graph.edge_a[edge] != node, float(graph.node_x[node]), float(graph.node_y[node]),
        float(graph.node_x[other]), float(graph.node_y[other]), _n_px(n_px),
    )  # fmt: skip


def node_orientation(graph: SkeletonGraph, node: int, *, n_px: int) -> float:
    """Orientation in degrees of a minutia (feature-table convention), or NaN when it cannot be trusted.

    Endings: along their valley. Bifurcations with exactly three valleys: the bisector of the smallest angle between
    two of them (seed Figure 30(b)); more than three valleys is not coherent enough (seed 4.7).
    """
    edges = graph.node_edges[node]
    if len(edges) not in (1, 3):
        return math.nan
    dirs = [branch_direction(graph, node, e, n_px=n_px) for e in edges]
    if len(dirs) == 1:
        dirs += [(0.0, 0.0, False)] * 2
    return _orientation(len(edges), *dirs[0], *dirs[1], *dirs[2])

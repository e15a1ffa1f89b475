"""The valley skeleton as a compiled graph (seed 4.7): valley endings, valley bifurcations and pores.

Each skeleton pixel is classified by its number of 8-neighbours: 0 = pore, 1 = valley ending, 3 or more = valley
bifurcation pixel, 2 = plain valley. Connected groups of bifurcation pixels are one bifurcation, placed at their
centre of mass. The compiled tracer then walks every valley branch once, from node to node, which turns the skeleton
into a graph: nodes (endings and bifurcations) joined by edges (valleys, with their pixel paths). Orientations
(seed Figure 30) and every editing rule of seed 4.8 (:mod:`skinstretch.processing.skeleton_editing`) work on it.

Orientation convention (the feature table's): degrees counter-clockwise from +x with y up the image,
``atan2(-dy, dx)``, in [0, 360). A valley ending points along its valley, from the minutia to the N-th valley pixel;
a bifurcation bisects the smallest angle between its valleys.

The graph is compiled (numba, without the GIL): :class:`GraphArrays` holds it in flat arrays, and the tracer, the
orientations and the feature list run on those arrays. :class:`skinstretch.processing.skeleton_graph_lists.SkeletonGraph`
is the same graph in Python lists, for inspection and the public rule functions. Hand-written rather than
skimage/networkx: the seed's classification and editing rules need the valley paths between nodes, compiled,
bit-for-bit repeatable (a Python graph library cost ~2 ms a frame).
"""

from __future__ import annotations

import math
import operator
from collections import namedtuple

import numpy as np
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind
from skinstretch.processing.jit import njit

__all__ = ["GraphArrays", "GraphCapacityError", "trace_arrays", "edit_with_room", "graph_features"]

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



"""Skeleton analysis (seed 4.7): valley endings, valley bifurcations and pores from the valley skeleton.

Each skeleton pixel is classified by its number of 8-neighbours: 0 = pore, 1 = valley ending, 3 or more = valley
bifurcation pixel, 2 = plain valley. Connected groups of bifurcation pixels are one bifurcation, placed at their
centre of mass. The compiled tracer then walks every valley branch once, from node to node, which turns the skeleton
into a graph: nodes (endings and bifurcations) joined by edges (valleys, with their pixel paths). Orientations
(seed Figure 30) and every editing rule of seed 4.8 work on that graph.

Orientation convention (the feature table's): degrees counter-clockwise from +x with y up the image,
``atan2(-dy, dx)``, in [0, 360). A valley ending points along its valley, from the minutia to the N-th valley pixel;
a bifurcation bisects the smallest angle between its valleys.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from processing.errors import InvalidInputError
from processing.feature_table import FeatureKind
from processing.jit import njit

__all__ = ["SkeletonGraph", "trace_skeleton", "node_kind", "branch_direction", "node_orientation"]



@njit(nogil=True)
def _nonzero(f):  # pragma: no cover - compiled
    """Indices of the non-zero bytes of ``f`` (uint8, 1-D), ascending; skips zero bytes eight at a time (a
    skeleton covers ~3% of a frame). Unlike np.flatnonzero it runs without the GIL."""
    n = f.size
    n8 = n // 8
    words = f[: n8 * 8].view(np.uint64)
    count = 0
    for j in range(n8):
        if words[j] != 0:
            for i in range(8 * j, 8 * j + 8):
                if f[i]:
                    count += 1
    for i in range(n8 * 8, n):
        if f[i]:
            count += 1
    out = np.empty(count, np.int64)
    k = 0
    for j in range(n8):
        if words[j] != 0:
            for i in range(8 * j, 8 * j + 8):
                if f[i]:
                    out[k] = i
                    k += 1
    for i in range(n8 * 8, n):
        if f[i]:
            out[k] = i
            k += 1
    return out


@njit(nogil=True)
def _trace(f, h, w, pix):  # pragma: no cover - compiled
    """Trace the skeleton ``f`` (flat, zero outer ring) whose pixels, in raster order, are ``pix``."""
    offs = np.array([-w, -w + 1, 1, w + 1, w, w - 1, -1, -w - 1])
    steplen = np.array([1.0, math.sqrt(2.0), 1.0, math.sqrt(2.0), 1.0, math.sqrt(2.0), 1.0, math.sqrt(2.0)])
    n = h * w
    # Neighbour counts of the skeleton pixels.
    n_sk = pix.size
    deg = np.zeros(n, np.int8)
    n_node_px = 0
    for k in range(n_sk):
        i = pix[k]
        c = 0
        for j in range(8):
            if f[i + offs[j]]:
                c += 1
        deg[i] = c
        if c == 1 or c >= 3:
            n_node_px += 1
    # Nodes: endings (1 neighbour) and 8-connected groups of bifurcation pixels (3+ neighbours).
    node_of = np.full(n, -1, np.int32)
    node_sx = np.zeros(n_sk)
    node_sy = np.zeros(n_sk)
    node_np = np.zeros(n_sk, np.int64)
    node_is_end = np.zeros(n_sk, np.bool_)
    n_nodes = 0
    iso = np.empty(n_sk, np.int64)
    n_iso = 0
    stack = np.empty(n_sk, np.int64)
    for k in range(n_sk):
        i = pix[k]
        d = deg[i]
        if d == 0:
            iso[n_iso] = i
            n_iso += 1
        elif d == 1:
            node_of[i] = n_nodes
            node_sx[n_nodes] = i % w
            node_sy[n_nodes] = i // w
            node_np[n_nodes] = 1
            node_is_end[n_nodes] = True
            n_nodes += 1
        elif d >= 3 and node_of[i] < 0:
            top = 0
            stack[top] = i
            top += 1
            node_of[i] = n_nodes
            while top > 0:
                top -= 1
                p = stack[top]
                node_sx[n_nodes] += p % w
                node_sy[n_nodes] += p // w
                node_np[n_nodes] += 1
                for j in range(8):
                    q = p + offs[j]
                    if f[q] and deg[q] >= 3 and node_of[q] < 0:
                        node_of[q] = n_nodes
                        stack[top] = q
                        top += 1
            n_nodes += 1
    node_x = node_sx[:n_nodes] / np.maximum(node_np[:n_nodes], 1)
    node_y = node_sy[:n_nodes] / np.maximum(node_np[:n_nodes], 1)
    # Trace every branch once, from a node pixel to the next node pixel.
    # Every edge leaves a node pixel toward one of its 8 neighbours: at most 8 per node pixel. (Sized to that, not
    # to the skeleton: large scratch arrays cost more than the tracing itself.)
    cap = 8 * n_node_px + 8
    e_a = np.empty(cap, np.int64)
    e_b = np.empty(cap, np.int64)
    e_start = np.empty(cap, np.int64)
    e_len = np.empty(cap, np.int64)
    e_length = np.empty(cap)
    path = np.empty(n_sk + 1, np.int64)
    n_path = 0
    n_edges = 0
    visited = np.zeros(n, np.bool_)
    for k in range(n_sk):
        p = pix[k]
        a = node_of[p]
        if a < 0:
            continue
        for j in range(8):
            q = p + offs[j]
            if not f[q]:
                continue
            b = node_of[q]
            if b == a:
                continue
            if b >= 0:
                # Two node pixels touching: an edge without interior pixels, recorded once (from the ending side).
                if deg[p] == 1 and (deg[q] != 1 or p < q):
                    e_a[n_edges] = a
                    e_b[n_edges] = b
                    e_start[n_edges] = n_path
                    e_len[n_edges] = 0
                    e_length[n_edges] = steplen[j]
                    n_edges += 1
                continue
            if visited[q]:
                continue
            start = n_path
            length = steplen[j]
            prev = p
            cur = q
            end_node = -1
            while True:
                visited[cur] = True
                path[n_path] = cur
                n_path += 1
                # A plain valley pixel has exactly two neighbours: the one we came from and the next.
                nxt = -1
                nxt_j = 0
                for jj in range(8):
                    r = cur + offs[jj]
                    if f[r] and r != prev:
                        nxt = r
                        nxt_j = jj
                        break
                if nxt < 0:
                    break
                length += steplen[nxt_j]
                if node_of[nxt] >= 0:
                    end_node = node_of[nxt]
                    break
                prev = cur
                cur = nxt
            if end_node < 0:
                # A branch that dead-ends without reaching a node cannot happen on a valid skeleton; drop it.
                n_path = start
                continue
            e_a[n_edges] = a
            e_b[n_edges] = end_node
            e_start[n_edges] = start
            e_len[n_edges] = n_path - start
            e_length[n_edges] = length
            n_edges += 1
    return (
        node_x,
        node_y,
        node_is_end[:n_nodes].copy(),
        iso[:n_iso].copy(),
        e_a[:n_edges].copy(),
        e_b[:n_edges].copy(),
        e_start[:n_edges].copy(),
        e_len[:n_edges].copy(),
        e_length[:n_edges].copy(),
        path[:n_path].copy(),
    )


@dataclass
class SkeletonGraph:
    """The valley skeleton as a graph, plus the pores. Mutable; editing steps work on copies (:meth:`copy`).

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
        a bifurcation, so its two edges merge into one; a node left with none disappears."""
        if not self.node_alive[node]:
            return
        edges = self.node_edges[node]
        if len(edges) == 0:
            self.node_alive[node] = False
        elif len(edges) == 2 and edges[0] != edges[1]:
            e1, e2 = edges
            a = self.other_end(e1, node)
            b = self.other_end(e2, node)
            mid = np.array([[int(round(self.node_x[node])), int(round(self.node_y[node]))]], dtype=np.int64)
            path = np.concatenate([self.path_from(e1, a), mid, self.path_from(e2, node)])
            length = self.edge_length[e1] + self.edge_length[e2]
            self.remove_edge(e1, erase=False)
            self.remove_edge(e2, erase=False)
            self.node_alive[node] = False
            self.add_edge(a, b, path, length)


def trace_skeleton(skeleton: np.ndarray) -> SkeletonGraph:
    """Build the :class:`SkeletonGraph` of a valley skeleton (seed 4.7, Figure 29).

    Parameters
    ----------
    skeleton : (H, W) uint8
        1 (non-zero) on the skeleton, 8-connected and near minimal (the output of :func:`processing.thinning.thin`).

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
    if not isinstance(skeleton, np.ndarray) or skeleton.ndim != 2 or min(skeleton.shape) < 3:
        raise InvalidInputError(f"skeleton must be a 2-D image at least 3x3, got {getattr(skeleton, 'shape', skeleton)}")
    sk = (skeleton != 0).astype(np.uint8)
    sk[0, :] = 0
    sk[-1, :] = 0
    sk[:, 0] = 0
    sk[:, -1] = 0
    h, w = sk.shape
    flat = sk.ravel()
    node_x, node_y, _, iso, e_a, e_b, e_start, e_len, e_length, path = _trace(flat, h, w, _nonzero(flat))
    px = np.stack([path % w, path // w], axis=1)
    # Self-loops shorter than 4 px are a thick junction's inner corner, not a valley.
    keep = ~((e_a == e_b) & (e_length < 4))
    e_a, e_b, e_start, e_len, e_length = e_a[keep], e_b[keep], e_start[keep], e_len[keep], e_length[keep]
    edge_a = e_a.tolist()
    edge_b = e_b.tolist()
    node_edges = [[] for _ in range(len(node_x))]
    for e, (a, b) in enumerate(zip(edge_a, edge_b)):
        node_edges[a].append(e)
        node_edges[b].append(e)
    g = SkeletonGraph(
        node_x=node_x.tolist(),
        node_y=node_y.tolist(),
        node_alive=[len(edges) > 0 for edges in node_edges],
        node_edges=node_edges,
        edge_a=edge_a,
        edge_b=edge_b,
        edge_path=[px[s0 : s0 + n] for s0, n in zip(e_start.tolist(), e_len.tolist())],
        edge_length=e_length.tolist(),
        edge_alive=[True] * len(edge_a),
        pore_x=(iso % w).astype(float).tolist(),
        pore_y=(iso // w).astype(float).tolist(),
        pore_alive=[True] * len(iso),
        skeleton=sk,
        pore_size=[0.0] * len(iso),
    )
    return g


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
    path = graph.edge_path[edge]
    m = len(path)
    x0, y0 = graph.node_x[node], graph.node_y[node]
    if m >= 1:
        k = min(n_px, m) - 1
        if graph.edge_a[edge] != node:  # the path runs from the other end (path_from would reverse it)
            k = m - 1 - k
        tx, ty = path[k].tolist()
    else:
        other = graph.other_end(edge, node)
        tx, ty = graph.node_x[other], graph.node_y[other]
    dx, dy = float(tx) - x0, float(ty) - y0
    norm = math.hypot(dx, dy)
    if norm == 0:
        return 0.0, 0.0, False
    return dx / norm, dy / norm, m + 1 >= max(n_px // 2, 2)


def _angle_deg(dx: float, dy: float) -> float:
    return math.degrees(math.atan2(-dy, dx)) % 360.0


def node_orientation(graph: SkeletonGraph, node: int, *, n_px: int) -> float:
    """Orientation in degrees of a minutia (feature-table convention), or NaN when it cannot be trusted.

    Endings: along their valley. Bifurcations with exactly three valleys: the bisector of the smallest angle between
    two of them (seed Figure 30(b)); more than three valleys is not coherent enough (seed 4.7).
    """
    edges = graph.node_edges[node]
    if len(edges) == 1:
        dx, dy, ok = branch_direction(graph, node, edges[0], n_px=n_px)
        return _angle_deg(dx, dy) if ok else math.nan
    if len(edges) != 3:
        return math.nan
    dirs = [branch_direction(graph, node, e, n_px=n_px) for e in edges]
    if not all(d[2] for d in dirs):
        return math.nan
    best = None
    for i in range(3):
        for j in range(i + 1, 3):
            cos = dirs[i][0] * dirs[j][0] + dirs[i][1] * dirs[j][1]
            if best is None or cos > best[0]:
                best = (cos, i, j)
    _, i, j = best
    bx, by = dirs[i][0] + dirs[j][0], dirs[i][1] + dirs[j][1]
    if math.hypot(bx, by) < 1e-9:
        return math.nan
    return _angle_deg(bx, by)

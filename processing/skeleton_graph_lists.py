"""The skeleton graph in Python lists (:class:`SkeletonGraph`), for inspection, tests and the public rule functions.

The extraction works on the compiled form, :class:`skinstretch.processing.skeleton_graph.GraphArrays`;
:meth:`SkeletonGraph.to_arrays` and :meth:`SkeletonGraph.from_arrays` convert between the two.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass, field

import numpy as np
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind
from skinstretch.processing.skeleton_graph import (
    GraphArrays,
    _direction,
    _n_px,
    _orientation,
    _settle,
    edit_with_room,
    trace_arrays,
)

__all__ = ["SkeletonGraph", "trace_skeleton", "node_kind", "branch_direction", "node_orientation"]

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

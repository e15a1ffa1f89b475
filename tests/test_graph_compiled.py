"""The compiled skeleton graph (skinstretch.processing.skeleton_graph.GraphArrays) and the skeleton rules that run on it.

The rules were list-based Python; they now run compiled on flat arrays with the same results to the bit. These tests
cover what the port added: the numerics that must match Python's and numpy's, degenerate and large skeletons, the
capacity of the arrays (and starting again with more room), and the wrappers that convert SkeletonGraph.
"""

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind
from skinstretch.processing.skeleton_editing import (
    _stable_argsort,
    edit_graph,
    heal_broken_valleys,
    line_pixels,
    remove_bridges,
    remove_short_spurs,
    remove_short_valleys,
)
from skinstretch.processing.skeleton_graph import (
    GraphArrays,
    GraphCapacityError,
    _hypot,
    edit_with_room,
    graph_features,
    trace_arrays,
)
from skinstretch.processing.skeleton_graph_lists import (
    SkeletonGraph,
    branch_direction,
    node_kind,
    node_orientation,
    trace_skeleton,
)
from skinstretch.processing.thinning import thin
from tests.helpers import y_shaped_skeleton

N_PX = 10
HEAL = dict(max_distance_px=37.2, max_angle_deg=30.0, orientation_px=N_PX)
SPUR = dict(min_length_px=6.2, max_length_px=18.6, max_deviation_deg=60.0, orientation_px=N_PX)
BRIDGE = dict(min_length_px=6.2, max_length_px=62.0, max_deviation_deg=60.0, orientation_px=N_PX)
CHAIN = dict(
    orientation_px=N_PX,
    short_valley_px=12.4,
    heal=(HEAL["max_distance_px"], HEAL["max_angle_deg"]),
    spurs=(SPUR["min_length_px"], SPUR["max_length_px"], SPUR["max_deviation_deg"]),
    bridges=(BRIDGE["min_length_px"], BRIDGE["max_length_px"], BRIDGE["max_deviation_deg"]),
)
FIELDS = (
    "node_x", "node_y", "node_alive", "node_edges", "edge_a", "edge_b", "edge_length", "edge_alive", "pore_x",
    "pore_y", "pore_alive", "pore_size",
)  # fmt: skip


def _ridges(seed: int, shape=(120, 160)) -> np.ndarray:
    """The skeleton of a noisy, bent ridge pattern: endings, bifurcations, bridges, spurs and broken valleys."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    phase = 2 * np.pi * (xx * 0.8 + yy * 0.6) / 9.0 + 1.5 * np.sin(xx / 23.0)
    v = np.sin(phase) + rng.normal(0, 1.5, shape)
    return thin((cv2.GaussianBlur(v, (0, 0), 1.0) > 0.1).astype(np.uint8) * 255)


def _assert_same_graph(a: SkeletonGraph, b: SkeletonGraph) -> None:
    for name in FIELDS:
        assert getattr(a, name) == getattr(b, name), name
    assert len(a.edge_path) == len(b.edge_path)
    for p, q in zip(a.edge_path, b.edge_path):
        assert p.dtype == q.dtype == np.int64 and np.array_equal(p, q)
    assert a.skeleton.dtype == b.skeleton.dtype and np.array_equal(a.skeleton, b.skeleton)


def _assert_consistent(g: SkeletonGraph, *, traced: bool = False) -> None:
    """Each node lists exactly its alive edges (a self-loop twice). Traced edges have 8-connected paths on the
    skeleton (a merged one need not: it passes through the rounded centre of the merged bifurcation)."""
    listed = [sorted(edges) for edges in g.node_edges]
    expected = [[] for _ in g.node_x]
    for e, alive in enumerate(g.edge_alive):
        if alive:
            expected[g.edge_a[e]].append(e)
            expected[g.edge_b[e]].append(e)
    assert listed == [sorted(edges) for edges in expected]
    if traced:
        for p in g.edge_path:
            assert g.skeleton[p[:, 1], p[:, 0]].all()
            if len(p) > 1:
                assert np.abs(np.diff(p, axis=0)).max() == 1


def _counts_of(g: SkeletonGraph) -> list[int]:
    degrees = [len(edges) for edges, alive in zip(g.node_edges, g.node_alive) if alive]
    return [degrees.count(1), sum(d >= 3 for d in degrees), sum(g.pore_alive)]


def _tight(arrays: GraphArrays) -> GraphArrays:
    """The same graph with no room to spare."""
    nn, ne, npx, nq = arrays.used.tolist()
    width = max(1, int(arrays.node_deg[:nn].max(initial=0)))
    return GraphArrays(
        arrays.node_xy[:nn].copy(), arrays.node_alive[:nn].copy(), arrays.node_deg[:nn].copy(),
        np.ascontiguousarray(arrays.node_adj[:nn, :width]), arrays.edge_ab[:ne].copy(), arrays.edge_span[:ne].copy(),
        arrays.edge_length[:ne].copy(), arrays.edge_alive[:ne].copy(), arrays.path[:npx].copy(),
        arrays.pore[:nq].copy(), arrays.pore_alive[:nq].copy(), arrays.skeleton.copy(), arrays.used.copy(),
    )  # fmt: skip


# ----------------------------------------------------------------------------------------- numerics


def test_hypot_is_cpythons_to_the_bit():
    rng = np.random.default_rng(1)
    values = np.concatenate([
        rng.uniform(-50, 50, 20000), np.round(rng.uniform(-50, 50, 20000)), rng.normal(0, 1e-3, 2000),
        rng.uniform(-1, 1, 2000) * 1e300, [0.0, -0.0, 5e-324, -5e-324, 1e-310, math.inf, -math.inf],
    ])  # fmt: skip
    others = rng.permutation(values)
    for x, y in zip(values.tolist(), others.tolist()):
        assert _hypot(x, y) == math.hypot(x, y), (x, y)
    assert math.isnan(_hypot(math.nan, 1.0)) and _hypot(math.nan, math.inf) == math.inf


def test_stable_argsort_is_numpys_stable_sort():
    rng = np.random.default_rng(2)
    for n in (0, 1, 2, 3, 7, 8, 9, 31, 200):
        keys = rng.integers(0, 4, n) / 3.0  # many ties
        assert np.array_equal(_stable_argsort(keys), np.argsort(keys, kind="stable"))


def test_line_pixels_round_half_to_even_like_before():
    rng = np.random.default_rng(3)
    for x0, y0, x1, y1 in rng.integers(-40, 40, (300, 4)).tolist():
        n = max(abs(x1 - x0), abs(y1 - y0))
        t = np.arange(n + 1) / max(n, 1)
        expected = np.stack([np.rint(x0 + (x1 - x0) * t), np.rint(y0 + (y1 - y0) * t)], axis=1).astype(np.int64)
        p = line_pixels(x0, y0, x1, y1)
        assert p.dtype == np.int64 and np.array_equal(p, expected[: n + 1] if n else [[x0, y0]])
    assert line_pixels(np.int64(2), 1, 5, 1).tolist() == [[2, 1], [3, 1], [4, 1], [5, 1]]


def test_bifurcation_orientation_is_the_bisector_of_the_closest_pair():
    sk = np.zeros((60, 60), np.uint8)
    sk[30, 5:30] = 1
    for i in range(1, 22):
        sk[30 - i, 29 + i] = 1
        sk[30 + (i * 2) // 3, 29 + i] = 1
    g = trace_skeleton(sk)
    bif = next(n for n in g.alive_nodes() if node_kind(g, n) == FeatureKind.VALLEY_BIFURCATION)
    dirs = [branch_direction(g, bif, e, n_px=N_PX) for e in g.node_edges[bif]]
    pairs = [(dirs[i][0] * dirs[j][0] + dirs[i][1] * dirs[j][1], i, j) for i in range(3) for j in range(i + 1, 3)]
    _, i, j = max(pairs, key=lambda p: p[0])
    bx, by = dirs[i][0] + dirs[j][0], dirs[i][1] + dirs[j][1]
    assert node_orientation(g, bif, n_px=N_PX) == math.degrees(math.atan2(-by, bx)) % 360.0
    end = next(n for n in g.alive_nodes() if node_kind(g, n) == FeatureKind.VALLEY_ENDING)
    dx, dy, _ = branch_direction(g, end, g.node_edges[end][0], n_px=N_PX)
    assert node_orientation(g, end, n_px=N_PX) == math.degrees(math.atan2(-dy, dx)) % 360.0


@pytest.mark.parametrize("n_px", [0, -3, 2.5, "10"])
def test_orientation_distance_must_be_a_positive_integer(n_px):
    g = trace_skeleton(_ridges(0, (40, 50)))
    n = next(n for n in g.alive_nodes())
    with pytest.raises(InvalidInputError):
        branch_direction(g, n, g.node_edges[n][0], n_px=n_px)
    with pytest.raises(InvalidInputError):
        heal_broken_valleys(g, max_distance_px=30.0, max_angle_deg=30.0, orientation_px=n_px)


# ----------------------------------------------------------------------------------------- skeletons


def _blank(shape=(40, 50)):
    return np.zeros(shape, np.uint8)


def _dots():
    s = _blank()
    s[3:37:3, 3:47:4] = 1
    return s


def _border_only():
    s = _blank()
    s[0, :] = s[-1, :] = 1
    s[:, 0] = s[:, -1] = 1
    return s


def _block(size):
    s = _blank()
    s[10 : 10 + size, 10 : 10 + size] = 1
    return s


@pytest.mark.parametrize(
    "skeleton, n_pores",
    [(np.zeros((3, 3), np.uint8), 0), (_blank(), 0), (_dots(), 12 * 11), (_border_only(), 0), (_block(2), 0),
     (np.ones((12, 9), np.uint8), 0), (_block(6).astype(bool), 0)],
)  # fmt: skip
def test_degenerate_skeletons_give_pores_or_nothing(skeleton, n_pores):
    g = trace_skeleton(skeleton)
    assert not any(g.edge_alive) and not g.alive_nodes() and g.skeleton.dtype == np.uint8
    assert len(g.pore_x) == n_pores
    if n_pores:
        ys, xs = np.nonzero(skeleton)  # raster order
        assert g.pore_x == xs.astype(float).tolist() and g.pore_y == ys.astype(float).tolist()
    arrays = trace_arrays(skeleton)
    counts = edit_graph(arrays, **CHAIN)
    assert counts.tolist() == [[0, 0, n_pores]] * 5
    x, y, kind, orient, size = graph_features(arrays, n_px=N_PX)
    assert x.size == n_pores and kind.dtype == np.int8 and np.all(kind == FeatureKind.PORE) and np.isnan(orient).all()
    for rule, kw in ((heal_broken_valleys, HEAL), (remove_short_spurs, SPUR), (remove_bridges, BRIDGE)):
        _assert_same_graph(rule(g, **kw), g)


def test_a_junction_of_many_valleys_is_one_node():
    sk = np.zeros((121, 121), np.uint8)
    for k in range(24):
        t = 2 * np.pi * k / 24
        cv2.line(sk, (60, 60), (int(round(60 + 55 * np.cos(t))), int(round(60 + 55 * np.sin(t)))), 1, 1)
    g = trace_skeleton(sk)
    _assert_consistent(g, traced=True)
    hub = max(g.alive_nodes(), key=g.degree)
    assert g.degree(hub) == 24 and math.isnan(node_orientation(g, hub, n_px=N_PX))
    arrays = trace_arrays(sk)
    assert arrays.node_adj.shape[1] >= g.degree(hub)
    edit_graph(arrays, **CHAIN)
    edited = SkeletonGraph.from_arrays(arrays)
    _assert_consistent(edited)
    _assert_same_graph(edited, remove_bridges(remove_short_spurs(heal_broken_valleys(remove_short_valleys(
        g, max_length_px=12.4), **HEAL), **SPUR), **BRIDGE))


def test_a_long_valley_is_one_edge():
    th = np.linspace(0, 24 * np.pi, 100000)
    r = 3 + 1.5 * th
    x, y = np.round(200 + r * np.cos(th)).astype(int), np.round(200 + r * np.sin(th)).astype(int)
    img = np.zeros((401, 401), np.uint8)
    img[y, x] = 255
    sk = thin(img)
    g = trace_skeleton(sk)
    assert len(g.edge_a) == 1 and len(g.alive_nodes()) == 2
    p = g.edge_path[0]
    assert len(p) == int(sk.astype(bool).sum()) - 2 > 3000
    steps = np.abs(np.diff(np.vstack([[g.node_x[0], g.node_y[0]], p, [g.node_x[1], g.node_y[1]]]), axis=0)).sum(axis=1)
    assert g.edge_length[0] == pytest.approx(np.sum(np.where(steps == 2, math.sqrt(2.0), 1.0)))


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    density=st.floats(0.05, 0.7),
    shape=st.tuples(st.integers(3, 40), st.integers(3, 40)),
    thinned=st.booleans(),
)
def test_any_binary_image_traces_and_edits_consistently(seed, density, shape, thinned):
    """Random pixels (thinned or not, so with blobs of junction pixels, rings and nodes of many valleys)."""
    img = (np.random.default_rng(seed).random(shape) < density).astype(np.uint8)
    sk = thin(img * 255) if thinned else img
    g = trace_skeleton(sk)
    _assert_consistent(g, traced=True)
    arrays, counts = edit_with_room(lambda room: trace_arrays(sk, room=room), lambda a: edit_graph(a, **CHAIN))
    edited = SkeletonGraph.from_arrays(arrays)
    _assert_consistent(edited)
    assert counts[0].tolist() == _counts_of(g) and counts[4].tolist() == _counts_of(edited)
    x, y, kind, orient, size = graph_features(arrays, n_px=N_PX)
    assert np.isfinite(x).all() and np.isfinite(y).all() and (size == 0).all()
    finite = orient[np.isfinite(orient)]
    assert ((finite >= 0) & (finite < 360)).all()


# ----------------------------------------------------------------------------------------- rules


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_chain_is_the_rules_in_turn(seed):
    sk = _ridges(seed)
    rng = np.random.default_rng(seed)
    pores = rng.uniform(0, 150, 40), rng.uniform(0, 110, 40), rng.uniform(0, 4, 40)
    g = trace_skeleton(sk)
    g.add_pores(*pores)
    steps = [g, remove_short_valleys(g, max_length_px=12.4)]
    steps.append(heal_broken_valleys(steps[-1], **HEAL))
    steps.append(remove_short_spurs(steps[-1], **SPUR))
    steps.append(remove_bridges(steps[-1], **BRIDGE))
    for s in steps:
        _assert_consistent(s)
    counts = [_counts_of(s) for s in steps]
    assert all(a != b for a, b in zip(counts, counts[1:]))  # every rule did something
    arrays = trace_arrays(sk, *pores)
    assert edit_graph(arrays, **CHAIN).tolist() == counts
    _assert_same_graph(SkeletonGraph.from_arrays(arrays), steps[-1])
    # The feature list: minutiae in node order with their orientation, then the pores.
    final = steps[-1]
    minutiae = [n for n in final.alive_nodes() if final.degree(n) not in (0, 2)]
    x, y, kind, orient, size = graph_features(arrays, n_px=N_PX)
    n = len(minutiae)
    assert x[:n].tolist() == [final.node_x[v] for v in minutiae]
    assert kind[:n].tolist() == [node_kind(final, v) for v in minutiae]
    np.testing.assert_array_equal(orient[:n], [node_orientation(final, v, n_px=N_PX) for v in minutiae])
    alive = np.flatnonzero(final.pore_alive)
    assert x[n:].tolist() == [final.pore_x[k] for k in alive]
    assert size[n:].tolist() == [final.pore_size[k] for k in alive]


def test_rules_return_an_edited_copy_in_the_input_skeleton_dtype():
    g = trace_skeleton(_ridges(4))
    g.skeleton = g.skeleton.astype(bool)
    before = g.copy()
    for rule, kw in ((remove_short_valleys, dict(max_length_px=12.4)), (heal_broken_valleys, HEAL),
                     (remove_short_spurs, SPUR), (remove_bridges, BRIDGE)):  # fmt: skip
        out = rule(g, **kw)
        assert out is not g and out.skeleton is not g.skeleton and out.skeleton.dtype == bool
        _assert_same_graph(g, before)


def test_running_out_of_room_starts_again_with_more():
    sk = _ridges(5)
    arrays = trace_arrays(sk)
    with pytest.raises(GraphCapacityError):
        edit_graph(_tight(arrays), **CHAIN)
    rooms = []

    def make(room):
        rooms.append(room)
        return _tight(trace_arrays(sk)) if room == 1 else trace_arrays(sk, room=room)

    edited, counts = edit_with_room(make, lambda a: edit_graph(a, **CHAIN))
    assert rooms == [1, 4]
    reference = trace_arrays(sk)
    assert counts.tolist() == edit_graph(reference, **CHAIN).tolist()
    _assert_same_graph(SkeletonGraph.from_arrays(edited), SkeletonGraph.from_arrays(reference))


def test_merging_a_long_valley_many_times_needs_and_gets_more_room():
    # One long valley with 60 short spurs: each spur removal merges the valley's two halves into a new edge, copying
    # the pixels again (far more than the room the arrays start with).
    img = np.zeros((40, 1600), np.uint8)
    img[10, 5:1595] = 255
    for x in range(30, 1575, 26):
        img[11:20, x] = 255
    sk = thin(img)
    g = trace_skeleton(sk)
    arrays = g.to_arrays()
    with pytest.raises(GraphCapacityError):
        edit_graph(arrays, orientation_px=N_PX, spurs=(6.2, 18.6, 60.0))
    out = remove_short_spurs(g, **SPUR)
    _assert_consistent(out)
    assert sorted(out.degree(n) for n in out.alive_nodes()) == [1, 1] and sum(out.pore_alive) == 60
    (e,) = out.alive_edges()
    p = out.edge_path[e]
    assert (p[:, 1] == 10).all() and len(set(np.sign(np.diff(p[:, 0])))) == 1 and out.skeleton[p[:, 1], p[:, 0]].all()
    assert not out.skeleton[13:].any()  # the spurs are erased (all but the pixel next to the valley)


def test_settle_merges_the_two_valleys_left_at_a_node():
    sk = y_shaped_skeleton()
    g = trace_skeleton(sk)
    bif = next(n for n in g.alive_nodes() if g.degree(n) == 3)
    lists = (g.node_x, g.node_edges, g.edge_path, g.node_edges[bif])
    spur = g.node_edges[bif][2]
    g.remove_edge(spur)
    e1, e2 = g.node_edges[bif]
    a, b = g.other_end(e1, bif), g.other_end(e2, bif)
    mid = [[int(round(g.node_x[bif])), int(round(g.node_y[bif]))]]
    expected = np.vstack([g.path_from(e1, a), mid, g.path_from(e2, bif)])
    length = g.edge_length[e1] + g.edge_length[e2]
    n_edges = len(g.edge_a)
    g.settle(bif)
    assert all(x is y for x, y in zip((g.node_x, g.node_edges, g.edge_path, g.node_edges[bif]), lists))  # in place
    assert len(g.edge_a) == n_edges + 1 and not g.node_alive[bif] and g.node_edges[bif] == []
    assert not g.edge_alive[e1] and not g.edge_alive[e2] and (g.edge_a[-1], g.edge_b[-1]) == (a, b)
    assert np.array_equal(g.edge_path[-1], expected) and g.edge_length[-1] == length
    assert g.node_edges[a][-1] == n_edges and g.node_edges[b][-1] == n_edges
    _assert_consistent(g)


def test_an_edit_that_never_fits_raises_instead_of_looping():
    from skinstretch.processing.skeleton_graph import GraphCapacityError

    rooms = []

    def never(arrays):
        raise GraphCapacityError("test: never enough")

    with pytest.raises(GraphCapacityError):
        edit_with_room(lambda room: rooms.append(room) or room, never)
    assert rooms == [4**k for k in range(7)]

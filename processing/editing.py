"""Feature editing (seed 4.8): syntactic rules that repair the valley skeleton, then two feature filters.

The skeleton rules work on the :class:`processing.minutiae.SkeletonGraph` and each returns an edited copy:

- :func:`remove_short_valleys` (4.8.1): a valley bounded by two endings and shorter than ~0.2 mm is a pore.
- :func:`heal_broken_valleys` (4.8.2): join facing endings closer than ~0.6 mm, best confidence (eq. 4.4) first.
- :func:`remove_short_spurs` (4.8.3): a short branch roughly perpendicular to its valley is deleted (a pore is
  left at its tip when it was long enough to be one).
- :func:`remove_bridges` (4.8.4): a short valley between two bifurcations, roughly perpendicular to both valleys,
  is a pore joining two valleys.

The filters work on feature columns (x, y, kind) and return a keep mask:

- :func:`feature_density_mask` (4.8.5): every feature in a 0.25 mm circle holding more than 3 features of its
  kind is deleted, for all features in parallel and each kind separately.
- :func:`border_mask` / :func:`outside_border` (4.8.6): features under the dilated background + image-edge mask
  are deleted.

All lengths here are pixels: :mod:`processing.extraction` converts the seed's millimetres once.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from processing.errors import InvalidInputError
from processing.jit import njit
from processing.minutiae import SkeletonGraph, branch_direction

__all__ = [
    "remove_short_valleys",
    "heal_broken_valleys",
    "remove_short_spurs",
    "remove_bridges",
    "feature_density_mask",
    "border_mask",
    "outside_border",
    "line_pixels",
]


def _positive(value: float, name: str) -> float:
    if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value > 0):
        raise InvalidInputError(f"{name} must be a positive number, got {value!r}")
    return float(value)


def _angle_limit(value: float, name: str) -> float:
    if not (isinstance(value, (int, float, np.number)) and 0 < value <= 90):
        raise InvalidInputError(f"{name} must be an angle in (0, 90] degrees, got {value!r}")
    return float(value)


def line_pixels(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """Pixels (x, y) of the 8-connected straight line from (x0, y0) to (x1, y1), both ends included."""
    n = max(abs(x1 - x0), abs(y1 - y0))
    if n == 0:
        return np.array([[x0, y0]], dtype=np.int64)
    t = np.arange(n + 1) / n
    xs = np.rint(x0 + (x1 - x0) * t).astype(np.int64)
    ys = np.rint(y0 + (y1 - y0) * t).astype(np.int64)
    return np.stack([xs, ys], axis=1)


# ------------------------------------------------------------------------------------------------- 4.8.1


def remove_short_valleys(graph: SkeletonGraph, *, max_length_px: float) -> SkeletonGraph:
    """Replace every valley bounded by two endings and shorter than ``max_length_px`` by a pore (seed 4.8.1).

    The pore is placed at the centre of mass of the valley's pixels. Returns an edited copy.
    """
    max_length_px = _positive(max_length_px, "max_length_px")
    g = graph.copy()
    for e in g.alive_edges():
        a, b = g.edge_a[e], g.edge_b[e]
        if a == b or g.degree(a) != 1 or g.degree(b) != 1 or g.edge_length[e] >= max_length_px:
            continue
        pts = [(g.node_x[a], g.node_y[a]), (g.node_x[b], g.node_y[b])] + [tuple(p) for p in g.edge_path[e]]
        cx = sum(p[0] for p in pts) / len(pts)
        cy = sum(p[1] for p in pts) / len(pts)
        g.remove_edge(e)
        g.remove_node(a)
        g.remove_node(b)
        g.add_pore(cx, cy)
    return g


# ------------------------------------------------------------------------------------------------- 4.8.2


def heal_broken_valleys(
    graph: SkeletonGraph,
    *,
    max_distance_px: float,
    max_angle_deg: float,
    orientation_px: int,
) -> SkeletonGraph:
    """Bridge the gaps of broken valleys (seed 4.8.2, Figures 36-38).

    Candidate pairs of valley endings are closer than ``max_distance_px`` and the bridging line deviates by less
    than ``max_angle_deg`` from the continuation of both valleys. They are healed in decreasing order of the
    confidence of eq. 4.4, each ending at most once, and only if the bridging line touches no skeleton pixel other
    than the two endings (so healing never crosses or joins a third valley). Pores in the 8-neighbourhood of the
    bridging line are deleted (they belong to the healed valley). Returns an edited copy.
    """
    d_max = _positive(max_distance_px, "max_distance_px")
    t_max = _angle_limit(max_angle_deg, "max_angle_deg")
    g = graph.copy()
    ends, dirs = [], []
    for n in g.alive_nodes():
        if g.degree(n) != 1:
            continue
        dx, dy, ok = branch_direction(g, n, g.node_edges[n][0], n_px=orientation_px)
        if ok:
            ends.append(n)
            dirs.append((dx, dy))
    if len(ends) < 2:
        return g
    ends_a = np.array(ends)
    xy = np.array([[g.node_x[n], g.node_y[n]] for n in ends])
    inward = np.array(dirs)  # from the ending into its own valley
    edge_of = np.array([g.node_edges[n][0] for n in ends])
    diff = xy[None, :, :] - xy[:, None, :]  # diff[i, j] = E_j - E_i
    dist = np.hypot(diff[..., 0], diff[..., 1])
    iu, ju = np.nonzero(np.triu((dist < d_max) & (dist > 0), 1))
    # Not the two ends of one valley (joining them would make a loop).
    other = edge_of[iu] != edge_of[ju]
    iu, ju = iu[other], ju[other]
    u = diff[iu, ju] / dist[iu, ju][:, None]
    # The gap must continue each valley: compare the bridging line with the outward (= -inward) directions.
    c1 = np.clip(-np.einsum("ij,ij->i", u, inward[iu]), -1, 1)
    c2 = np.clip(np.einsum("ij,ij->i", u, inward[ju]), -1, 1)
    t1, t2 = np.degrees(np.arccos(c1)), np.degrees(np.arccos(c2))
    ok = (t1 < t_max) & (t2 < t_max)
    iu, ju, t1, t2 = iu[ok], ju[ok], t1[ok], t2[ok]
    conf = (d_max - dist[iu, ju]) / d_max * (t_max - t1) / t_max * (t_max - t2) / t_max  # eq. 4.4
    order = np.argsort(-conf, kind="stable")  # best first; ties keep the (i, j) order
    candidates = zip(iu[order].tolist(), ju[order].tolist())
    healed = np.zeros(len(ends), dtype=bool)
    h, w = g.skeleton.shape
    for i, j in candidates:
        if healed[i] or healed[j]:
            continue
        n1, n2 = int(ends_a[i]), int(ends_a[j])
        x1, y1 = int(round(g.node_x[n1])), int(round(g.node_y[n1]))
        x2, y2 = int(round(g.node_x[n2])), int(round(g.node_y[n2]))
        line = line_pixels(x1, y1, x2, y2)
        inner = line[1:-1]
        if _touches_other_skeleton(g.skeleton, inner, (x1, y1), (x2, y2)):
            continue
        healed[i] = healed[j] = True
        e1, e2 = g.node_edges[n1][0], g.node_edges[n2][0]
        a, b = g.other_end(e1, n1), g.other_end(e2, n2)
        path = np.concatenate(
            [g.path_from(e1, a), np.array([[x1, y1]]), inner.reshape(-1, 2), np.array([[x2, y2]]), g.path_from(e2, n2)]
        )
        length = g.edge_length[e1] + g.edge_length[e2] + float(np.hypot(x2 - x1, y2 - y1))
        g.remove_edge(e1, erase=False)
        g.remove_edge(e2, erase=False)
        g.node_alive[n1] = g.node_alive[n2] = False
        g.skeleton[line[:, 1], line[:, 0]] = 1
        g.add_edge(a, b, path, length)
        _delete_pores_near_segment(g, (x1, y1), (x2, y2), radius=1.5)
    return g


def _touches_other_skeleton(skeleton: np.ndarray, inner: np.ndarray, p1, p2) -> bool:
    """Whether any skeleton pixel other than the two endings and their own valley neighbours lies in the
    8-neighbourhood of the bridging line's inner pixels."""
    if len(inner) == 0:
        return False
    return _touches(skeleton, np.ascontiguousarray(inner, dtype=np.int64), int(p1[0]), int(p1[1]), int(p2[0]), int(p2[1]))


@njit(nogil=True)
def _touches(skeleton, inner, x1, y1, x2, y2):  # pragma: no cover - compiled
    h, w = skeleton.shape
    for k in range(inner.shape[0]):
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                x = inner[k, 0] + dx
                y = inner[k, 1] + dy
                if x < 0 or x >= w or y < 0 or y >= h or skeleton[y, x] == 0:
                    continue
                near1 = max(abs(x - x1), abs(y - y1)) <= 1
                near2 = max(abs(x - x2), abs(y - y2)) <= 1
                if not (near1 or near2):
                    return True
    return False


def _delete_pores_near_segment(g: SkeletonGraph, p1, p2, *, radius: float) -> None:
    if not g.pore_x:
        return
    px = np.asarray(g.pore_x)
    py = np.asarray(g.pore_y)
    ax, ay = p1
    bx, by = p2
    vx, vy = bx - ax, by - ay
    L2 = vx * vx + vy * vy
    t = np.clip(((px - ax) * vx + (py - ay) * vy) / L2, 0, 1) if L2 > 0 else np.zeros_like(px)
    d = np.hypot(px - (ax + t * vx), py - (ay + t * vy))
    for k in np.flatnonzero(d <= radius).tolist():
        g.pore_alive[k] = False


# ------------------------------------------------------------------------------------------------- 4.8.3 / 4.8.4


def _perpendicular(g: SkeletonGraph, node: int, edge: int, *, orientation_px: int, max_dev: float) -> bool:
    """Whether ``edge`` leaves ``node`` within ``max_dev`` degrees of perpendicular to each of the node's other
    valleys (the seed's angles theta_1..theta_4)."""
    sx, sy, _ = branch_direction(g, node, edge, n_px=orientation_px)
    if sx == 0 and sy == 0:
        return False
    for other in g.node_edges[node]:
        if other == edge:
            continue
        ox, oy, _ = branch_direction(g, node, other, n_px=orientation_px)
        theta = math.degrees(math.acos(max(-1.0, min(1.0, sx * ox + sy * oy))))
        if abs(theta - 90.0) > max_dev:
            return False
    return True


def remove_short_spurs(
    graph: SkeletonGraph,
    *,
    min_length_px: float,
    max_length_px: float,
    max_deviation_deg: float,
    orientation_px: int,
) -> SkeletonGraph:
    """Delete short spurs roughly perpendicular to their valley (seed 4.8.3, Figures 40-41).

    A spur is a valley from a bifurcation with three valleys to an ending, shorter than ``max_length_px``, whose
    angles with the two other valleys at the bifurcation are within ``max_deviation_deg`` of 90 degrees. The spur
    and its ending are deleted and the bifurcation re-evaluated (it becomes a plain valley point). When the spur is
    longer than ``min_length_px``, a pore is added at its tip. Returns an edited copy.

    Beyond the seed: the spur may also leave a crossing of four valleys where a bridge (4.8.4) continues it
    straight on, the last pore of a row of pores across the ridges (see :func:`remove_bridges`).
    """
    lo = _positive(min_length_px, "min_length_px")
    hi = _positive(max_length_px, "max_length_px")
    if lo >= hi:
        raise InvalidInputError(f"min_length_px ({lo}) must be below max_length_px ({hi})")
    dev = _angle_limit(max_deviation_deg, "max_deviation_deg")
    g = graph.copy()
    for e in g.alive_edges():
        if not g.edge_alive[e] or g.edge_length[e] >= hi:
            continue
        a, b = g.edge_a[e], g.edge_b[e]
        if g.degree(a) == 1 and g.degree(b) in (3, 4):
            end, bif = a, b
        elif g.degree(b) == 1 and g.degree(a) in (3, 4):
            end, bif = b, a
        else:
            continue
        if not _bridge_end(g, bif, e, orientation_px=orientation_px, max_dev=dev):
            continue
        tip = (g.node_x[end], g.node_y[end])
        g.remove_edge(e)
        g.remove_node(end)
        g.settle(bif)
        if g.edge_length[e] > lo:
            g.add_pore(*tip)
    return g


def remove_bridges(
    graph: SkeletonGraph,
    *,
    min_length_px: float,
    max_length_px: float,
    max_deviation_deg: float,
    orientation_px: int,
) -> SkeletonGraph:
    """Replace bridges between adjacent valleys by pores (seed 4.8.4, Figures 43-44).

    A bridge is a valley between two distinct bifurcations of three valleys each, with a length in
    [``min_length_px``, ``max_length_px``] and all four angles with the neighbouring valleys within
    ``max_deviation_deg`` of 90 degrees. It is deleted, a pore is added at its centre of mass and both
    bifurcations are re-evaluated. Returns an edited copy.

    Beyond the seed: a row of pores across several ridges, each wide enough to join its two valleys in the binary
    image, makes a chain of bridges that cross each valley at one point, i.e. nodes of four valleys. A bridge may
    also end at such a crossing when one of the crossing's valleys continues it straight on (within
    ``max_deviation_deg``) and the other two are perpendicular to it; the crossing keeps three valleys and the
    next bridge of the chain is taken on the next pass. Passes repeat until nothing changes.
    """
    lo = _positive(min_length_px, "min_length_px")
    hi = _positive(max_length_px, "max_length_px")
    if lo >= hi:
        raise InvalidInputError(f"min_length_px ({lo}) must be below max_length_px ({hi})")
    dev = _angle_limit(max_deviation_deg, "max_deviation_deg")
    g = graph.copy()
    changed = True
    while changed:
        changed = False
        for e in g.alive_edges():
            if not g.edge_alive[e]:
                continue
            a, b = g.edge_a[e], g.edge_b[e]
            length = g.edge_length[e]
            if a == b or not (lo <= length <= hi):
                continue
            if not (
                _bridge_end(g, a, e, orientation_px=orientation_px, max_dev=dev)
                and _bridge_end(g, b, e, orientation_px=orientation_px, max_dev=dev)
            ):
                continue
            path = g.edge_path[e]
            if len(path):
                cx, cy = path[:, 0].mean(), path[:, 1].mean()
            else:
                cx, cy = (g.node_x[a] + g.node_x[b]) / 2, (g.node_y[a] + g.node_y[b]) / 2
            g.remove_edge(e)
            g.settle(a)
            g.settle(b)
            g.add_pore(cx, cy)
            changed = True
    return g


def _bridge_end(g: SkeletonGraph, node: int, edge: int, *, orientation_px: int, max_dev: float) -> bool:
    """Whether ``node`` can end the bridge ``edge``: a bifurcation of three valleys with the bridge perpendicular to
    the other two, or a crossing of four where one valley continues the bridge straight on (within ``max_dev``)
    and the bridge is perpendicular to the other two."""
    d = g.degree(node)
    if d == 3:
        return _perpendicular(g, node, edge, orientation_px=orientation_px, max_dev=max_dev)
    if d != 4:
        return False
    sx, sy, _ = branch_direction(g, node, edge, n_px=orientation_px)
    if sx == 0 and sy == 0:
        return False
    angles = []
    for other in g.node_edges[node]:
        if other == edge:
            continue
        ox, oy, _ = branch_direction(g, node, other, n_px=orientation_px)
        if ox == 0 and oy == 0:
            return False
        angles.append(math.degrees(math.acos(max(-1.0, min(1.0, sx * ox + sy * oy)))))
    angles.sort()
    return angles[2] >= 180.0 - max_dev and all(abs(t - 90.0) <= max_dev for t in angles[:2])


# ------------------------------------------------------------------------------------------------- 4.8.5 / 4.8.6


def feature_density_mask(x: np.ndarray, y: np.ndarray, kind: np.ndarray, *, radius_px: float, max_count: int) -> np.ndarray:
    """Keep mask of the feature density filter (seed 4.8.5).

    For every feature, the features of the same kind within ``radius_px`` (itself included) are counted; when the
    count exceeds ``max_count`` all of them are deleted. Counts are taken before any deletion (in parallel).
    """
    radius_px = _positive(radius_px, "radius_px")
    if not (isinstance(max_count, (int, np.integer)) and max_count >= 1):
        raise InvalidInputError(f"max_count must be a positive integer, got {max_count!r}")
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    kind = np.ascontiguousarray(kind, dtype=np.int64)
    if not x.shape == y.shape == kind.shape or x.ndim != 1:
        raise InvalidInputError(f"x, y and kind must be 1-D arrays of one length, got {x.shape}, {y.shape}, {kind.shape}")
    return _density_keep(x, y, kind, radius_px, int(max_count))


@njit(nogil=True)
def _density_keep(x, y, kind, radius, max_count):  # pragma: no cover - compiled
    """Keep mask of :func:`feature_density_mask`: pairwise distances within each kind (a frame holds a few hundred
    features), neighbours counted with the feature itself, at distance <= radius."""
    n = x.size
    r2 = radius * radius
    count = np.zeros(n, np.int64)
    for i in range(n):
        for j in range(i, n):
            if kind[j] != kind[i]:
                continue
            dx = x[j] - x[i]
            dy = y[j] - y[i]
            if dx * dx + dy * dy <= r2:
                count[i] += 1
                if j != i:
                    count[j] += 1
    keep = np.ones(n, np.bool_)
    for i in range(n):
        if count[i] <= max_count:
            continue
        for j in range(n):
            if kind[j] == kind[i]:
                dx = x[j] - x[i]
                dy = y[j] - y[i]
                if dx * dx + dy * dy <= r2:
                    keep[j] = False
    return keep


def border_mask(background: np.ndarray, *, dilation_px: int) -> np.ndarray:
    """Deletion mask of seed 4.8.6: the background plus a 1-pixel image border, dilated (square) by ``dilation_px``."""
    if background.ndim != 2:
        raise InvalidInputError(f"background must be 2-D, got shape {background.shape}")
    if dilation_px < 0:
        raise InvalidInputError(f"dilation_px must be >= 0, got {dilation_px!r}")
    m = background.astype(np.uint8)
    m[0, :] = m[-1, :] = 1
    m[:, 0] = m[:, -1] = 1
    if dilation_px > 0:
        d = 2 * int(dilation_px) + 1
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_RECT, (d, d)))
    return m.astype(bool)


def outside_border(x: np.ndarray, y: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Keep mask: True for features whose (rounded) position is not under ``mask``."""
    h, w = mask.shape
    xi = np.clip(np.rint(np.asarray(x)).astype(np.int64), 0, w - 1)
    yi = np.clip(np.rint(np.asarray(y)).astype(np.int64), 0, h - 1)
    return ~mask[yi, xi]

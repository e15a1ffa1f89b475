"""Feature editing (seed 4.8): syntactic rules that repair the valley skeleton, then two feature filters.

The skeleton rules work on the :class:`skinstretch.processing.minutiae.SkeletonGraph` and each returns an edited copy (they
run compiled on the graph's arrays, :class:`skinstretch.processing.minutiae.GraphArrays`, where they are implemented next to the
graph primitives; :func:`edit_graph` runs the chain of them on the arrays, as the extraction does):

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

All lengths here are pixels: :mod:`skinstretch.processing.extraction` converts the seed's millimetres once.
"""

from __future__ import annotations

import math
import operator

import cv2
import numpy as np

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit
from skinstretch.processing.minutiae import (
    GraphArrays,
    SkeletonGraph,
    _edit_from_healing,
    _edit_to_healing,
    _line,
    _n_px,
    edit_with_room,
)

__all__ = [
    "remove_short_valleys",
    "heal_broken_valleys",
    "remove_short_spurs",
    "remove_bridges",
    "edit_graph",
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


def _length_range(lo: float, hi: float) -> tuple[float, float]:
    lo = _positive(lo, "min_length_px")
    hi = _positive(hi, "max_length_px")
    if lo >= hi:
        raise InvalidInputError(f"min_length_px ({lo}) must be below max_length_px ({hi})")
    return lo, hi


def line_pixels(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """Pixels (x, y) of the 8-connected straight line from (x0, y0) to (x1, y1), both ends included."""
    return _line(operator.index(x0), operator.index(y0), operator.index(x1), operator.index(y1))


# The rules run compiled on the graph's arrays (skinstretch.processing.minutiae, next to the graph primitives they are built
# from), all through the two calls of _run_rules; the functions here check their arguments and convert the graph.


def _run_rules(arrays, n_px, sv=0.0, heal=(0.0, 0.0), spurs=(0.0, 0.0, 0.0), bridges=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Run the rules whose first length is > 0, in the order of seed 4.8, on ``arrays`` (in place); (5, 3) counts."""
    counts, ends, iu, ju, dist, cos = _edit_to_healing(arrays, sv, heal[0], n_px)
    # numpy's arccos (vectorised: it can differ from the C library's acos in the last bit), as the rule always had.
    acos = np.arccos(cos)
    _edit_from_healing(arrays, counts, ends, iu, ju, dist, acos, *heal, *spurs, *bridges, n_px)
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
    return _edited(graph, 1, sv=_positive(max_length_px, "max_length_px"))


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
    heal = (_positive(max_distance_px, "max_distance_px"), _angle_limit(max_angle_deg, "max_angle_deg"))
    return _edited(graph, _n_px(orientation_px), heal=heal)


# ------------------------------------------------------------------------------------------------- 4.8.3 / 4.8.4


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
    spurs = (*_length_range(min_length_px, max_length_px), _angle_limit(max_deviation_deg, "max_deviation_deg"))
    return _edited(graph, _n_px(orientation_px), spurs=spurs)


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
    bridges = (*_length_range(min_length_px, max_length_px), _angle_limit(max_deviation_deg, "max_deviation_deg"))
    return _edited(graph, _n_px(orientation_px), bridges=bridges)


def edit_graph(
    arrays: GraphArrays,
    *,
    orientation_px: int,
    short_valley_px: float | None = None,
    heal: tuple[float, float] | None = None,
    spurs: tuple[float, float, float] | None = None,
    bridges: tuple[float, float, float] | None = None,
) -> np.ndarray:
    """The skeleton rules of seed 4.8.1-4.8.4 in order, on graph arrays edited in place (the extraction's chain).

    Each rule runs when its parameters are given: ``short_valley_px`` (:func:`remove_short_valleys`), ``heal`` =
    (max distance px, max angle deg), ``spurs`` and ``bridges`` = (min length px, max length px, max deviation deg).
    The same result as the public functions in turn, in two compiled calls.

    Returns (5, 3) int64 counts of valley endings, valley bifurcations and pores, initially and after each rule (0
    for rules that did not run). Raises :class:`skinstretch.processing.minutiae.GraphCapacityError` when the arrays run out of
    room, leaving them half-edited (see :func:`skinstretch.processing.minutiae.edit_with_room`).
    """
    rules = {}
    if short_valley_px is not None:
        rules["sv"] = _positive(short_valley_px, "short_valley_px")
    if heal is not None:
        rules["heal"] = (_positive(heal[0], "max_distance_px"), _angle_limit(heal[1], "max_angle_deg"))
    if spurs is not None:
        rules["spurs"] = (*_length_range(*spurs[:2]), _angle_limit(spurs[2], "max_deviation_deg"))
    if bridges is not None:
        rules["bridges"] = (*_length_range(*bridges[:2]), _angle_limit(bridges[2], "max_deviation_deg"))
    return _run_rules(arrays, _n_px(orientation_px), **rules)


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

"""The compiled Delaunay triangulation (skinstretch.processing.delaunay) against Qhull."""

import numpy as np
import pytest
from scipy.spatial import Delaunay

from skinstretch.processing.delaunay import delaunay_triangles
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError


def _set(tri):
    return set(map(tuple, np.sort(np.asarray(tri), axis=1).tolist()))


@pytest.mark.parametrize("seed", range(6))
def test_same_triangles_as_qhull_in_general_position(seed):
    rng = np.random.default_rng(seed)
    for n in (3, 4, 10, 57, 250, 600):
        p = rng.random((n, 2)) * [640, 484]
        if seed % 2:
            p = np.round(p) + rng.random(p.shape) * 1e-3  # nearly on a pixel grid: near-cocircular quads
        assert _set(delaunay_triangles(p)) == _set(Delaunay(p).simplices)


def test_every_point_is_used_and_triangles_are_not_degenerate(rng):
    g = np.stack(np.meshgrid(np.arange(12.0), np.arange(9.0)), -1).reshape(-1, 2)  # exactly cocircular squares
    tri = delaunay_triangles(g)
    assert len(tri) == 2 * 11 * 8
    assert set(np.unique(tri)) == set(range(len(g)))
    a, b, c = g[tri[:, 0]], g[tri[:, 1]], g[tri[:, 2]]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    assert np.all(np.abs(area) > 0.5)


@pytest.mark.parametrize("points", [
    [[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]],
    [[0.1, 0.7], [0.1 + 1e-9, 0.7 + 3e-9], [0.1 + 2e-9, 0.7 + 6e-9]],  # collinear up to rounding
    [[0.0, 0.0], [1.0, 0.0]],
])
def test_collinear_or_too_few_points_raise(points):
    with pytest.raises(InsufficientDataError):
        delaunay_triangles(np.array(points))


def test_bad_input_is_named():
    with pytest.raises(InvalidInputError, match="shape"):
        delaunay_triangles(np.zeros((4, 3)))
    with pytest.raises(InvalidInputError, match="finite"):
        delaunay_triangles(np.array([[0.0, 0.0], [1.0, np.nan], [0.0, 1.0]]))

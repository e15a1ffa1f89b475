"""Chapter-6 figures render from plain arrays and reject malformed input by name."""

import numpy as np
import pytest
from scipy.spatial import Delaunay

from skinstretch.experiments.figures.chapter6 import (
    contactor_positions_figure,
    edge_change_series_figure,
    figure_to_png,
    measurements_figure,
    PlaybackTrace,
    playback_figure,
    strain_limit,
    stretch_fields_figure,
    stretch_profile_figure,
    trajectory_length_figure,
)
from skinstretch.processing.errors import InvalidInputError

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def triangulation(rng):
    pts = rng.uniform([10, 10], [150, 110], (40, 2))
    tri = Delaunay(pts).simplices
    edges = np.unique(np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1), axis=0)
    return pts, tri, edges


def test_measurements_figure_has_six_panels(triangulation, rng):
    pts, tri, edges = triangulation
    frame = rng.integers(0, 255, (120, 160), dtype=np.uint8)
    centers = np.stack(np.meshgrid(np.arange(20, 160, 20.0), np.arange(20, 120, 20.0)), -1)
    fig = measurements_figure(
        frame, frame, index_a=3, index_b=4, points_a=pts, points_b=pts + 1.0, edges=edges,
        edge_change=rng.normal(0, 0.03, len(edges)), triangles=tri, area_change=rng.normal(0, 0.03, len(tri)),
        flipped=np.zeros(len(tri), bool), patch_centers=centers,
        patch_change=rng.normal(0, 0.03, (centers.shape[0] - 1, centers.shape[1] - 1)), shape_x_px=[50, 110],
    )
    assert len(fig.axes) == 6 + 3 and "frame 3" in fig.axes[0].get_title()  # six panels, three colorbars
    assert figure_to_png(fig).startswith(PNG)


def test_other_figures_render(triangulation, rng):
    pts, tri, edges = triangulation
    panels = [{"points": pts, "edges": edges, "edge_change": rng.normal(0, 0.1, len(edges)), "frame_a": k,
               "frame_b": k + 11} for k in (0, 25, 50, 75)]
    assert len(edge_change_series_figure(panels, shape=(120, 160)).axes) == 6 + 1  # one shared colorbar
    assert figure_to_png(trajectory_length_figure(rng.integers(2, 60, 200), n_frames=60)).startswith(PNG)
    x = np.linspace(-5, 5, 41)
    fig = stretch_profile_figure({"flatL": (x, 0.01 * x), "ridgeL": (x, -0.01 * x)},
                                 true_profiles={"ridgeL": (x, -0.012 * x)})
    assert len([a for a in fig.axes if a.get_visible() and a.lines]) == 2
    movie = rng.normal(0, 20, (30, 10, 10))
    assert figure_to_png(contactor_positions_figure(movie, frames=[0, 10, 20])).startswith(PNG)
    assert figure_to_png(stretch_fields_figure(rng.normal(0, 0.2, (30, 10, 9)), frames=[5, 15])).startswith(PNG)
    runs = {"open loop": PlaybackTrace(movie, movie + 3, 5, 3.0), "closed loop": PlaybackTrace(movie, movie + 0.2, 5, 0.2)}
    fig = playback_figure(runs, rate_hz=700)
    assert "RMS 3 um" in fig.axes[1].get_title()


def test_strain_maps_are_scaled_to_their_data_with_a_colorbar_in_percent(triangulation, rng):
    """0.3 % strain fills the colour scale instead of vanishing on a fixed +/-5 % one (issue 17)."""
    pts, tri, edges = triangulation
    change = rng.normal(0, 0.003, len(edges))
    fig = edge_change_series_figure([{"points": pts, "edges": edges, "edge_change": change, "frame_a": 0,
                                      "frame_b": 11}], shape=(120, 160))
    collection = fig.axes[0].collections[0]
    lo, hi = collection.norm.vmin, collection.norm.vmax
    assert lo == -hi and hi == pytest.approx(np.percentile(np.abs(change), 99) * 100)
    assert collection.get_cmap().name == "RdBu_r"
    colorbars = [a for a in fig.axes if a.get_ylabel().endswith("(%)")]
    assert [a.get_ylabel() for a in colorbars] == ["edge length change (%)"]
    # mostly-white would mean the map is invisible: most edges use at least a fifth of the scale
    assert np.mean(np.abs(change * 100) > 0.2 * hi) > 0.5
    fig = measurements_figure(
        rng.integers(0, 255, (120, 160), dtype=np.uint8), rng.integers(0, 255, (120, 160), dtype=np.uint8),
        index_a=0, index_b=1, points_a=pts, points_b=pts, edges=edges, edge_change=change, triangles=tri,
        area_change=rng.normal(0, 0.006, len(tri)))
    labels = sorted(a.get_ylabel() for a in fig.axes if a.get_ylabel().endswith("(%)"))
    assert labels == ["area change (%)", "edge length change (%)"]
    assert strain_limit(np.zeros(4)) == pytest.approx(1e-4)  # an all-zero map still has a scale


def test_playback_figure_shows_the_runs_own_error_over_the_same_frames(rng):
    """The figure's RMS is the run's (settle frames left out), and each contactor's map uses the same frames."""
    target = rng.normal(0, 20, (50, 10, 10))
    measured = target + rng.normal(0, 0.2, target.shape)
    measured[:10] += 30  # a start-up transient the table's number leaves out
    from skinstretch.experiments.playback import rms_tracking_error

    run = PlaybackTrace(target, measured, 10, rms_tracking_error(target, measured, settle=10))
    fig = playback_figure({"closed loop": run})
    assert f"RMS {run.rms_error_um:.3g} um" in fig.axes[1].get_title()
    per_contactor = run.contactor_rms_um()
    assert np.sqrt(np.mean(per_contactor**2)) == pytest.approx(run.rms_error_um)


def test_bad_inputs_are_named(rng):
    with pytest.raises(InvalidInputError, match="frames"):
        contactor_positions_figure(np.zeros((5, 10, 10)), frames=[9])
    with pytest.raises(InvalidInputError, match="profiles"):
        stretch_profile_figure({})
    with pytest.raises(InvalidInputError, match="limit"):
        stretch_fields_figure(np.zeros((3, 10, 9)), frames=[0], limit=0)

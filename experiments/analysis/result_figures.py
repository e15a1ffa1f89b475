"""Figures of one analysis' results as PNG files (seed chapter 6), for users of the Python API.

Drawn with :mod:`skinstretch.experiments.figures.chapter6` from a :class:`~skinstretch.experiments.results_file.Results`
(never inside the analysis): the stretch profile (Figure 94), trajectory lengths (Figure 70, feature method), and the
tactile movie's contactor positions and stretch fields (Figures 96, 97) when the analysis made one.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["save_figures"]


def save_figures(results, outdir: str | os.PathLike, *, dpi: int = 90) -> list[Path]:
    """Write the figures of ``results`` into ``outdir`` (created) and return their paths."""
    from skinstretch.experiments.figures import chapter6 as fig6  # noqa: PLC0415 - matplotlib only when asked

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    r = results
    figures = {
        "stretch_profile.png": fig6.stretch_profile_figure(
            {Path(r.session_path).stem or "session": (r.profile.x / r.px_per_mm, r.profile.change)},
            title=f"Change in stretch along {r.profile_axis} (seed Figure 94)"),
    }
    if r.tracks is not None:
        figures["trajectory_lengths.png"] = fig6.trajectory_length_figure(r.tracks["n_frames"], n_frames=r.n_frames)
    if r.movie is not None:
        n = r.movie.positions_um.shape[0]
        frames = sorted(set(np.linspace(0, n - 1, min(6, n)).round().astype(int).tolist()))
        figures["contactor_positions.png"] = fig6.contactor_positions_figure(r.movie.positions_um, frames=frames,
                                                                             reset=r.movie.reset)
        figures["stretch_fields.png"] = fig6.stretch_fields_figure(r.movie.stretch_change, frames=frames)
    paths = []
    for name, fig in figures.items():
        path = outdir / name
        fig.savefig(path, dpi=dpi, bbox_inches="tight")
        paths.append(path)
    return paths

"""Figure: one simulated frame with its true features overlaid, in the seed's symbols (seed 4.7, Figure 31):
circle = valley ending, square = valley bifurcation, triangle = pore."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind

_MARKERS = {
    FeatureKind.VALLEY_ENDING: ("o", "#ff3b30", "valley ending"),
    FeatureKind.VALLEY_BIFURCATION: ("s", "#34c759", "valley bifurcation"),
    FeatureKind.PORE: ("^", "#0a84ff", "pore"),
}


def draw_truth(ax, frame: np.ndarray, xy: np.ndarray, kinds: np.ndarray, visible: np.ndarray, *, title: str = ""):
    """Draw ``frame`` (grey) on ``ax`` with the visible true features ``xy`` (F, 2 px) marked by kind."""
    frame = np.asarray(frame)
    if frame.ndim != 2:
        raise InvalidInputError(f"frame must be a 2-D image, got shape {frame.shape}")
    ax.imshow(frame, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    for kind, (marker, colour, label) in _MARKERS.items():
        sel = visible & (kinds == kind)
        size = 30 if kind == FeatureKind.PORE else 60
        ax.scatter(xy[sel, 0], xy[sel, 1], s=size, marker=marker, facecolors="none", edgecolors=colour,
                   linewidths=1.1, label=f"{label} ({int(sel.sum())})")
    ax.set_xlim(-0.5, frame.shape[1] - 0.5)
    ax.set_ylim(frame.shape[0] - 0.5, -0.5)
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=9)
    ax.legend(loc="lower right", fontsize=7, framealpha=0.8)
    return ax


def truth_figure(scene: str = "ridgeL", frame: int = 90, *, seed: int = 0, noise: float | None = None,
                 path: str | os.PathLike | None = None):
    """Render ``frame`` of ``scene`` with its true features; save to ``path`` (PNG) if given. Returns the figure."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from skinstretch.simulators.scene import SceneRenderer, load_scene

    sc = load_scene(scene)
    if not 0 <= frame < sc.n_frames:
        raise InvalidInputError(f"frame must be in [0, {sc.n_frames}), got {frame}")
    r = SceneRenderer(sc.model_copy(update={"n_frames": max(frame + 1, 1)}), seed=seed, noise=noise)
    img = r.render_frame(frame)
    xy, vis = r.feature_positions(frame)
    _, kinds, _ = r.fingerprint.features()
    h, w = img.shape
    fig, ax = plt.subplots(figsize=(w / 80, h / 80), dpi=100)
    draw_truth(ax, img, xy, kinds, vis, title=f"{sc.name} frame {frame} (seed {seed}): true features")
    fig.tight_layout()
    if path is not None:
        fig.savefig(Path(path), dpi=100)
    return fig


if __name__ == "__main__":  # pragma: no cover
    import sys

    out = sys.argv[1] if len(sys.argv) > 1 else "/tmp/truth_ridgeL_90.png"
    truth_figure("ridgeL", 90, path=out)
    print(out)

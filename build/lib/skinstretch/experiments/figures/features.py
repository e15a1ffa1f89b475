"""Feature overlays (seed Figures 31, 48-49 and 67): extracted features on the grey image, from the public API.

Notation of the seed (4.7): circle = valley ending, square = valley bifurcation, triangle = pore; minutia
orientations as short lines. Figures are returned as :class:`matplotlib.figure.Figure` objects (no pyplot state).
"""

from __future__ import annotations

from typing import Mapping

import matplotlib

matplotlib.use("Agg")  # noqa: E402 - figures are files, never windows
import numpy as np
from matplotlib.figure import Figure

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind, validate_features

__all__ = ["feature_overlay_figure", "step_counts_figure"]

_STYLE = {
    FeatureKind.VALLEY_ENDING: dict(marker="o", color="tab:red", label="valley ending"),
    FeatureKind.VALLEY_BIFURCATION: dict(marker="s", color="tab:blue", label="valley bifurcation"),
    FeatureKind.PORE: dict(marker="^", color="gold", label="pore"),
}


def feature_overlay_figure(
    image: np.ndarray,
    features: np.ndarray,
    *,
    skeleton: np.ndarray | None = None,
    binary: np.ndarray | None = None,
    truth_xy: np.ndarray | None = None,
    window: tuple[int, int, int, int] | None = None,
    orientation_length_px: float = 12.0,
    title: str = "",
) -> Figure:
    """Seed Figure 31 / 67: features over the grey image (optionally the binary image and the skeleton).

    Parameters
    ----------
    image : (H, W) uint8
        The grey frame.
    features : FEATURE_DTYPE array
        Features of that frame (:func:`skinstretch.processing.extraction.extract_features`).
    skeleton, binary : (H, W) arrays, optional
        Drawn in red (skeleton) and as a translucent overlay (binary), like seed Figure 67(b).
    truth_xy : (T, 2) array, optional
        True feature positions (simulated sessions), drawn as small crosses.
    window : (x0, y0, x1, y1), optional
        Crop, in pixels.
    orientation_length_px : float
        Length of the minutia orientation lines.
    """
    if not isinstance(image, np.ndarray) or image.ndim != 2:
        raise InvalidInputError(f"image must be a 2-D array, got {getattr(image, 'shape', type(image))}")
    validate_features(features)
    h, w = image.shape
    x0, y0, x1, y1 = window if window is not None else (0, 0, w, h)
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
        raise InvalidInputError(f"window {window} is outside the {w}x{h} image")
    fig = Figure(figsize=(7.5, 7.5 * (y1 - y0) / (x1 - x0) + 0.6), dpi=100)
    ax = fig.add_subplot(1, 1, 1)
    extent = (x0 - 0.5, x1 - 0.5, y1 - 0.5, y0 - 0.5)
    ax.imshow(image[y0:y1, x0:x1], cmap="gray", vmin=0, vmax=255, extent=extent, interpolation="nearest")
    if binary is not None:
        ax.imshow(
            np.ma.masked_equal(binary[y0:y1, x0:x1] > 0, False), cmap="summer", alpha=0.25, extent=extent, interpolation="nearest"
        )
    if skeleton is not None:
        ys, xs = np.nonzero(skeleton[y0:y1, x0:x1])
        ax.plot(xs + x0, ys + y0, ",", color="red")
    inside = (features["x"] >= x0) & (features["x"] < x1) & (features["y"] >= y0) & (features["y"] < y1)
    f = features[inside]
    for kind, style in _STYLE.items():
        sel = f[f["kind"] == kind]
        ax.scatter(sel["x"], sel["y"], s=40, facecolors="none", edgecolors=style["color"], marker=style["marker"],
                   linewidths=1.3, label=f"{style['label']} ({sel.size})")
        known = sel[sel["orientation_known"]]
        if known.size:
            a = np.radians(known["orientation"].astype(np.float64))
            L = orientation_length_px
            for x, y, ca, sa in zip(known["x"], known["y"], np.cos(a), np.sin(a)):
                ax.plot([x, x + L * ca], [y, y - L * sa], color=style["color"], linewidth=1.0)
    if truth_xy is not None and len(truth_xy):
        t = np.asarray(truth_xy, dtype=np.float64).reshape(-1, 2)
        ax.scatter(t[:, 0], t[:, 1], s=12, marker="+", color="magenta", linewidths=0.8, label="truth")
    ax.set_xlim(x0 - 0.5, x1 - 0.5)
    ax.set_ylim(y1 - 0.5, y0 - 0.5)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig


def step_counts_figure(step_counts: Mapping[str, Mapping[str, int]], *, title: str = "") -> Figure:
    """Seed Figure 48: feature count per kind after each editing step."""
    if not step_counts:
        raise InvalidInputError("step_counts is empty (a flagged frame has no editing steps)")
    steps = list(step_counts)
    fig = Figure(figsize=(7, 3.5), dpi=100)
    ax = fig.add_subplot(1, 1, 1)
    for kind, style in _STYLE.items():
        name = kind.label
        ax.plot(range(len(steps)), [step_counts[s].get(name, 0) for s in steps], marker=style["marker"],
                color=style["color"], label=style["label"])
    ax.set_xticks(range(len(steps)))
    ax.set_xticklabels(steps, rotation=20)
    ax.set_ylabel("features")
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig

"""The figures of the seed's chapter 6, drawn from results (never inside processing). Matplotlib, Agg backend.

Every function takes plain arrays or the typed results of :mod:`skinstretch.processing.stretch` /
:mod:`skinstretch.processing.display_mapping` and returns a :class:`matplotlib.figure.Figure` (no pyplot state, so figures
can be made from worker threads). Strain maps use a diverging colormap symmetric about 0 (blue = compression,
white = no change, red = stretch; the seed drew black and white), scaled to the data (``limit=None``: the 99th
percentile of the magnitudes shown, so 0.3 % strain is as visible as 30 %) or to a fixed ``limit``, with a
colorbar in %.

* :func:`measurements_figure` — seed Figures 76-93 (a)-(f): the two frames, feature flow, edge-length change,
  triangle-area change, skin-patch area change.
* :func:`edge_change_series_figure` — Figures 78, 81, ...: edge-length change at several positions in a sequence.
* :func:`trajectory_length_figure` — Figure 70: distribution of trajectory lengths.
* :func:`stretch_profile_figure` — Figure 94: horizontal stretch profile averaged over a sequence, per sequence.
* :func:`tensor_maps_figure` — no seed equivalent: exx, eyy, exy, e1, e2 of the triangles at several frames, as DIC
  tools show them, one colour scale per quantity across its frames.
* :func:`contactor_positions_figure` — Figure 96; :func:`stretch_fields_figure` — Figure 97.
* :func:`playback_figure` — target vs measured contactor positions, open vs closed loop (no seed equivalent), its
  RMS errors those of the runs' own :class:`PlaybackTrace` (one computation for table and figure).
* :func:`figure_to_png` — PNG bytes for the HTML report.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")  # noqa: E402 - figures are files, never windows
import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from skinstretch.experiments.number_format import format_number
from skinstretch.processing.errors import InvalidInputError

__all__ = [
    "measurements_figure",
    "edge_change_series_figure",
    "trajectory_length_figure",
    "stretch_profile_figure",
    "tensor_maps_figure",
    "grouped_profiles_figure",
    "contactor_positions_figure",
    "stretch_fields_figure",
    "playback_figure",
    "PlaybackTrace",
    "figure_to_png",
    "strain_limit",
    "draw_feature_flow",
    "draw_edge_change",
    "draw_area_change",
    "draw_patch_change",
]

_CMAP = "RdBu_r"  # diverging: blue = compression, white = no change, red = stretch
_SMALLEST_LIMIT = 1e-4  # 0.01 %: an all-zero map still gets a scale


def figure_to_png(fig: Figure, *, dpi: int = 90) -> bytes:
    """Render a figure to PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return buf.getvalue()


def strain_limit(*changes: np.ndarray, percentile: float = 99.0) -> float:
    """The colour limit (a fraction) that fits relative changes: the ``percentile`` of their magnitudes, so a few
    outliers saturate instead of washing out the rest; 0.01 % at least."""
    values = [np.abs(np.asarray(c, float)).ravel() for c in changes if c is not None]
    flat = np.concatenate(values) if values else np.zeros(0)
    flat = flat[np.isfinite(flat)]
    if flat.size == 0:
        return _SMALLEST_LIMIT
    return max(float(np.percentile(flat, percentile)), _SMALLEST_LIMIT)


def _limit(limit: float | None, *changes: np.ndarray) -> float:
    if limit is None:
        return strain_limit(*changes)
    if not (np.isfinite(limit) and limit > 0):
        raise InvalidInputError(f"limit must be a positive fraction or None (scaled to the data), got {limit!r}")
    return float(limit)


def _norm(limit: float) -> Normalize:
    """Symmetric about 0, in percent (the arrays drawn are changes x 100)."""
    return Normalize(vmin=-limit * 100, vmax=limit * 100, clip=False)


def _colorbar(fig, mappable, ax, label: str, changes: np.ndarray, limit: float) -> None:
    """A colorbar in %, with arrows when some values lie beyond the limit."""
    c = np.abs(np.asarray(changes, float))
    beyond = bool(np.any(c[np.isfinite(c)] > limit))
    fig.colorbar(mappable, ax=ax, shrink=0.8, label=label, extend="both" if beyond else "neither")


def _frame_axes(ax, shape: tuple[int, int], title: str) -> None:
    ax.set_xlim(-0.5, shape[1] - 0.5)
    ax.set_ylim(shape[0] - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=9)


def _shape_lines(ax, shape_x_px: Sequence[float] | None, shape: tuple[int, int]) -> None:
    """The seed's two dotted lines 3 mm apart marking the ridge or valley (seed 6.3.2)."""
    if shape_x_px is None:
        return
    for x in shape_x_px:
        ax.axvline(x, color="tab:orange", linestyle=":", linewidth=1.0)


def draw_feature_flow(ax, image: np.ndarray | None, points_a: np.ndarray, points_b: np.ndarray, *,
                      shape: tuple[int, int], title: str = "feature movement", scale: float = 1.0) -> None:
    """Arrows from each tracked feature's position in frame a to frame b (seed Figures 76-93 (c))."""
    pa = np.asarray(points_a, float).reshape(-1, 2)
    pb = np.asarray(points_b, float).reshape(-1, 2)
    if pa.shape != pb.shape:
        raise InvalidInputError(f"points_a {pa.shape} and points_b {pb.shape} must match")
    if image is not None:
        ax.imshow(image, cmap="gray", vmin=0, vmax=255, alpha=0.35)
    d = (pb - pa) * scale
    ax.quiver(pa[:, 0], pa[:, 1], d[:, 0], -d[:, 1], angles="xy", scale_units="xy", scale=1.0, color="k",
              width=0.003, headwidth=3)
    ax.plot(pa[:, 0], pa[:, 1], ".", color="tab:blue", markersize=2)
    _frame_axes(ax, shape, title + (f" (x{scale:g})" if scale != 1 else ""))


def draw_edge_change(ax, points: np.ndarray, edges: np.ndarray, change: np.ndarray, *, shape: tuple[int, int],
                     limit: float | None = None, title: str = "edge length change", colorbar: bool = True):
    """Triangulation edges coloured by their relative length change (seed 5.3.1, Figure 58 (c)); returns the
    collection (a colorbar in % is added unless ``colorbar=False``)."""
    p = np.asarray(points, float)
    e = np.asarray(edges, int)
    change = np.asarray(change, float)
    limit = _limit(limit, change)
    segs = p[e] if len(e) else np.zeros((0, 2, 2))
    ax.set_facecolor("0.85")
    lc = LineCollection(segs, cmap=_CMAP, norm=_norm(limit), linewidths=2.0)
    lc.set_array(change * 100)
    ax.add_collection(lc)
    _frame_axes(ax, shape, title)
    if colorbar:
        _colorbar(ax.figure, lc, ax, "edge length change (%)", change, limit)
    return lc


def draw_area_change(ax, points: np.ndarray, triangles: np.ndarray, change: np.ndarray, *, shape: tuple[int, int],
                     limit: float | None = None, flipped: np.ndarray | None = None,
                     title: str = "triangle area change", colorbar: bool = True):
    """Triangles coloured by their relative area change (seed 5.3.1, Figure 58 (a)); flipped ones black."""
    p = np.asarray(points, float)
    t = np.asarray(triangles, int)
    ch = np.asarray(change, float)
    ok = np.ones(len(t), bool) if flipped is None else ~np.asarray(flipped, bool)
    limit = _limit(limit, ch[ok] if len(t) else ch)
    ax.set_facecolor("0.85")
    pc = PolyCollection(p[t[ok]] if len(t) else np.zeros((0, 3, 2)), cmap=_CMAP, norm=_norm(limit),
                        edgecolors="none")
    pc.set_array(ch[ok] * 100 if len(t) else np.zeros(0))
    ax.add_collection(pc)
    if len(t) and np.any(~ok):
        ax.add_collection(PolyCollection(p[t[~ok]], facecolors="k", edgecolors="none"))
        title += f", {int(np.sum(~ok))} flipped (black)"
    _frame_axes(ax, shape, title)
    if colorbar:
        _colorbar(ax.figure, pc, ax, "area change (%)", ch[ok] if len(t) else ch, limit)
    return pc


def draw_patch_change(ax, centers: np.ndarray, change: np.ndarray, *, shape: tuple[int, int],
                      limit: float | None = None, title: str = "skin patch area change", colorbar: bool = True):
    """Tetragons between neighbouring patch centres coloured by their area change (seed Figure 61)."""
    c = np.asarray(centers, float)
    ch = np.asarray(change, float)
    if c.ndim != 3 or ch.shape != (c.shape[0] - 1, c.shape[1] - 1):
        raise InvalidInputError(f"centers {c.shape} must be (GY, GX, 2) and change (GY-1, GX-1), got {ch.shape}")
    limit = _limit(limit, ch)
    ax.set_facecolor("0.85")
    quads = np.stack([c[:-1, :-1], c[:-1, 1:], c[1:, 1:], c[1:, :-1]], axis=2).reshape(-1, 4, 2)
    flat = ch.reshape(-1)
    ok = np.isfinite(flat)
    pc = PolyCollection(quads[ok], cmap=_CMAP, norm=_norm(limit), edgecolors="none")
    pc.set_array(flat[ok] * 100)
    ax.add_collection(pc)
    _frame_axes(ax, shape, title)
    if colorbar:
        _colorbar(ax.figure, pc, ax, "patch area change (%)", flat[ok], limit)
    return pc


def _arrow_scale(points_a: np.ndarray, points_b: np.ndarray, shape: tuple[int, int]) -> float:
    """A whole-number magnification making the median arrow ~4 % of the image width (motions of a pixel or two
    between frames are otherwise dots); 1 when they are already that long."""
    d = np.hypot(*(np.asarray(points_b, float).reshape(-1, 2) - np.asarray(points_a, float).reshape(-1, 2)).T)
    d = d[np.isfinite(d)]
    if d.size == 0 or np.median(d) <= 0:
        return 1.0
    return float(max(1, int(0.04 * shape[1] / np.median(d))))


def measurements_figure(
    frame_a: np.ndarray,
    frame_b: np.ndarray,
    *,
    index_a: int,
    index_b: int,
    points_a: np.ndarray,
    points_b: np.ndarray,
    edges: np.ndarray,
    edge_change: np.ndarray,
    triangles: np.ndarray,
    area_change: np.ndarray,
    flipped: np.ndarray | None = None,
    patch_centers: np.ndarray | None = None,
    patch_change: np.ndarray | None = None,
    limit: float | None = None,
    shape_x_px: Sequence[float] | None = None,
    title: str = "",
) -> Figure:
    """Seed Figures 76-93: (a) frame a, (b) frame b, (c) feature movement, (d) edge length change,
    (e) triangle area change, (f) skin patch area change, each map with its colorbar in % (scaled to its data
    when ``limit`` is None)."""
    shape = np.asarray(frame_a).shape
    fig = Figure(figsize=(12.5, 6.6))
    axes = fig.subplots(2, 3)
    for ax, img, k, tag in ((axes[0, 0], frame_a, index_a, "a"), (axes[0, 1], frame_b, index_b, "b")):
        ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        _shape_lines(ax, shape_x_px, shape)
        _frame_axes(ax, shape, f"({tag}) frame {k}")
    draw_feature_flow(axes[0, 2], None, points_a, points_b, shape=shape, title="(c) feature movement",
                      scale=_arrow_scale(points_a, points_b, shape))
    draw_edge_change(axes[1, 0], points_a, edges, edge_change, shape=shape, limit=limit, title="(d) edge length")
    draw_area_change(axes[1, 1], points_a, triangles, area_change, shape=shape, limit=limit, flipped=flipped,
                     title="(e) triangle area")
    if patch_centers is not None and patch_change is not None:
        draw_patch_change(axes[1, 2], patch_centers, patch_change, shape=shape, limit=limit, title="(f) patch area")
    else:
        axes[1, 2].set_axis_off()
        axes[1, 2].text(0.5, 0.5, "no skin patch measurement", ha="center", va="center", fontsize=9)
    for ax in axes[:, 0]:
        _shape_lines(ax, shape_x_px, shape)
    fig.suptitle(title or f"Measurements from frame {index_a} to {index_b} (blue = compression, red = stretch)",
                 fontsize=10)
    return fig


def edge_change_series_figure(
    panels: Sequence[Mapping[str, np.ndarray]], *, shape: tuple[int, int], limit: float | None = None,
    title: str = ""
) -> Figure:
    """Seed Figures 78, 81, ...: edge-length change over a span at several positions of a sequence, on one colour
    scale (scaled to all panels' data when ``limit`` is None) with one colorbar in %.

    ``panels``: mappings with ``points``, ``edges``, ``edge_change``, ``frame_a``, ``frame_b``.
    """
    if not panels:
        raise InvalidInputError("panels must hold at least one measurement")
    limit = _limit(limit, *(p["edge_change"] for p in panels))
    cols = min(3, len(panels))
    rows = int(np.ceil(len(panels) / cols))
    fig = Figure(figsize=(3.6 * cols + 1.0, 2.9 * rows))
    axes = np.atleast_1d(fig.subplots(rows, cols)).reshape(-1)
    mappable = None
    for k, (ax, p) in enumerate(zip(axes, panels)):
        mappable = draw_edge_change(ax, p["points"], p["edges"], p["edge_change"], shape=shape, limit=limit,
                                    title=f"({chr(97 + k)}) frames {int(p['frame_a'])}-{int(p['frame_b'])}",
                                    colorbar=False)
    for ax in axes[len(panels):]:
        ax.set_axis_off()
    _colorbar(fig, mappable, list(axes), "edge length change (%)",
              np.concatenate([np.asarray(p["edge_change"], float).ravel() for p in panels]), limit)
    fig.suptitle(title or "Edge length change (blue = compression, red = stretch)", fontsize=10)
    return fig


def grouped_profiles_figure(groups: Mapping[str, Sequence[tuple[str, np.ndarray, np.ndarray]]], *,
                            xlabel: str = "position along the sliding direction (mm)", title: str = "") -> Figure:
    """Seed Figure 94 of many trials on one plot: ``groups`` maps a surface to its trials' (label, x, change as a
    fraction); one colour per surface (Okabe-Ito), one line per trial, the legend counting each surface's trials."""
    if not groups:
        raise InvalidInputError("groups must hold at least one surface")
    colors = ["#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000"]
    fig = Figure(figsize=(9.0, 3.6))
    ax = fig.subplots()
    ax.axhline(0, color="0.6", linewidth=0.8)
    for k, (surface, trials) in enumerate(groups.items()):
        color = colors[k % len(colors)]
        for i, (_, x, ch) in enumerate(trials):
            ax.plot(np.asarray(x, float), np.asarray(ch, float) * 100, "-", color=color, linewidth=1.2, alpha=0.85,
                    label=f"{surface} ({len(trials)} trials)" if i == 0 else None)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("stretch change (%)")
    ax.legend(fontsize=8)
    ax.set_title(title or "Relative change in stretch with position, every trial (seed Figure 94)", fontsize=10)
    fig.tight_layout()
    return fig


#: The quantities of :func:`tensor_maps_figure`, each with its colour-bar label.
TENSOR_MAP_LABELS = {"exx": "exx (%)", "eyy": "eyy (%)", "exy": "exy, tensor shear (%)", "e1": "e1, major (%)",
                     "e2": "e2, minor (%)"}


def tensor_maps_figure(panels: Sequence[Mapping[str, np.ndarray]], *, shape: tuple[int, int],
                       quantities: Sequence[str] = tuple(TENSOR_MAP_LABELS), title: str = "") -> Figure:
    """The Green-Lagrange components and principal strains of the triangles at several frames: one row per
    quantity, one column per frame, one colour scale (and colorbar, in %) per quantity across its frames, so a
    colour means the same strain in every panel of a row (scaled to the row's data, :func:`strain_limit`).

    ``panels``: mappings with ``corners`` (T, 3, 2) px, ``flipped`` (T,) bool (drawn black), one (T,) array per
    quantity (fractions) and ``label`` (the panel's frames).
    """
    if not panels:
        raise InvalidInputError("panels must hold at least one measurement")
    quantities = list(quantities)
    cols, rows = len(panels), len(quantities)
    fig = Figure(figsize=(2.9 * cols + 1.2, 2.3 * rows))
    axes = np.asarray(fig.subplots(rows, cols, squeeze=False))
    for r, q in enumerate(quantities):
        ok_values = [np.asarray(p[q], float)[~np.asarray(p["flipped"], bool)] for p in panels]
        limit = strain_limit(*ok_values)
        mappable = None
        for c, p in enumerate(panels):
            ax = axes[r, c]
            corners = np.asarray(p["corners"], float).reshape(-1, 3, 2)
            flipped = np.asarray(p["flipped"], bool)
            ax.set_facecolor("0.85")
            mappable = PolyCollection(corners[~flipped], cmap=_CMAP, norm=_norm(limit), edgecolors="none")
            mappable.set_array(np.asarray(p[q], float)[~flipped] * 100)
            ax.add_collection(mappable)
            if np.any(flipped):
                ax.add_collection(PolyCollection(corners[flipped], facecolors="k", edgecolors="none"))
            _frame_axes(ax, shape, f"{q}, {p['label']}" if r == 0 or cols == 1 else q)
        _colorbar(fig, mappable, list(axes[r]), TENSOR_MAP_LABELS.get(q, f"{q} (%)"), np.concatenate(ok_values),
                  limit)
    fig.suptitle(title or "Green-Lagrange strain and principal strains (image axes; blue = compression, red = "
                 "stretch; one scale per row)", fontsize=10)
    return fig


def trajectory_length_figure(lengths: np.ndarray, *, n_frames: int | None = None, title: str = "") -> Figure:
    """Seed Figure 70: how many trajectories span how many frames."""
    lengths = np.asarray(lengths, int).reshape(-1)
    fig = Figure(figsize=(5.5, 3.2))
    ax = fig.subplots()
    if lengths.size:
        top = int(max(lengths.max(), n_frames or 0))
        bins = np.arange(1, top + 2) - 0.5 if top <= 60 else np.linspace(0.5, top + 0.5, 41)
        ax.hist(lengths, bins=bins, color="0.3")
        ax.axvline(np.median(lengths), color="tab:red", linestyle="--", label=f"median {np.median(lengths):.0f}")
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no trajectories", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("trajectory length (frames)")
    ax.set_ylabel("trajectories")
    ax.set_title(title or "Trajectory length distribution (seed Figure 70)", fontsize=10)
    return fig


def stretch_profile_figure(profiles: Mapping[str, tuple[np.ndarray, np.ndarray]], *, true_profiles: Mapping[str,
                           tuple[np.ndarray, np.ndarray]] | None = None,
                           xlabel: str = "position along the sliding direction (mm)", title: str = "",
                           band: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
                           amplitudes: Mapping[str, float] | None = None) -> Figure:
    """Seed Figure 94: relative change in horizontal stretch with position, averaged over a sequence.

    ``profiles``: label -> (x, change as a fraction); ``true_profiles`` (optional, simulated sessions) are drawn
    dashed; ``band``: label -> (low, high) spread across sessions. All panels share one stretch scale and each
    title gives the RMS of its measured profile, so a flat surface's lack of pattern reads as a small amplitude
    beside a ridge's or a valley's (seed 6.3.2), not as a shape of its own. ``amplitudes``: label -> that RMS
    (a fraction) as computed elsewhere, so that a report shows one number (the amplitude of
    :func:`skinstretch.experiments.evaluation.tracking.measured_profile_pattern`, which leaves out the profile's
    end strips); without it, the RMS of every finite value drawn.
    """
    if not profiles:
        raise InvalidInputError("profiles must hold at least one sequence")
    n = len(profiles)
    cols = min(3, n)
    rows = int(np.ceil(n / cols))
    fig = Figure(figsize=(3.8 * cols, 2.8 * rows))
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False, sharey=True)).reshape(-1)
    for k, (ax, (label, (x, ch))) in enumerate(zip(axes, profiles.items())):
        x = np.asarray(x, float)
        ch = np.asarray(ch, float)
        ax.axhline(0, color="0.6", linewidth=0.8)
        if band and label in band:
            lo, hi = band[label]
            ax.fill_between(x, np.asarray(lo) * 100, np.asarray(hi) * 100, color="tab:blue", alpha=0.2, linewidth=0)
        ax.plot(x, ch * 100, "-", color="tab:blue", label="measured")
        if true_profiles and label in true_profiles:
            tx, tch = true_profiles[label]
            ax.plot(np.asarray(tx, float), np.asarray(tch, float) * 100, "--", color="k", label="true")
            ax.legend(fontsize=7)
        finite = ch[np.isfinite(ch)]
        value = amplitudes.get(label) if amplitudes else (np.sqrt(np.mean(finite**2)) if finite.size else None)
        rms = f", RMS {format_number(value * 100)} %" if value is not None and np.isfinite(value) else ""
        ax.set_title(f"({chr(97 + k)}) {label}{rms}", fontsize=9)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel("stretch change (%)")
        ax.yaxis.set_tick_params(labelleft=True)
    for ax in axes[n:]:
        ax.set_axis_off()
    fig.suptitle(title or "Relative change in stretch with position, averaged over the sequence (seed Figure 94)",
                 fontsize=10)
    fig.tight_layout()
    return fig


def contactor_positions_figure(positions_um: np.ndarray, *, frames: Sequence[int], range_um: float = 50.0,
                               reset: np.ndarray | None = None, title: str = "") -> Figure:
    """Seed Figure 96: contactor positions (horizontal bars from each contactor's rest position) at some frames.

    ``positions_um``: (N, 10, 10); contactors pitched 1 mm; a bar of ``range_um`` spans half a pitch.
    """
    pos = np.asarray(positions_um, float)
    if pos.ndim != 3:
        raise InvalidInputError(f"positions_um must be (N, R, C), got {pos.shape}")
    frames = [int(f) for f in frames if 0 <= int(f) < pos.shape[0]]
    if not frames:
        raise InvalidInputError("frames must name at least one frame of the movie")
    cols = min(3, len(frames))
    rows = int(np.ceil(len(frames) / cols))
    fig = Figure(figsize=(3.2 * cols, 3.2 * rows))
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).reshape(-1)
    r, c = pos.shape[1:]
    yy, xx = np.mgrid[0:r, 0:c]
    for k, (ax, f) in enumerate(zip(axes, frames)):
        d = pos[f] / range_um * 0.5
        segs = np.stack([np.stack([xx, yy], -1), np.stack([xx + d, yy], -1)], axis=2).reshape(-1, 2, 2)
        ax.add_collection(LineCollection(segs, colors="k", linewidths=2.5))
        ax.plot(xx.ravel(), yy.ravel(), "o", color="0.6", markersize=2)
        if reset is not None:
            rs = np.asarray(reset, bool)[f]
            ax.plot(xx[rs], yy[rs], "x", color="tab:red", markersize=4)
        ax.set_xlim(-1, c)
        ax.set_ylim(r, -1)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"({chr(97 + k)}) frame {f}", fontsize=9)
    for ax in axes[len(frames):]:
        ax.set_axis_off()
    fig.suptitle(title or f"Contactor positions (bar of half a pitch = {range_um:g} um; x = reset) (seed Figure 96)",
                 fontsize=10)
    return fig


def stretch_fields_figure(stretch_change: np.ndarray, *, frames: Sequence[int], limit: float | None = None,
                          title: str = "") -> Figure:
    """Seed Figure 97: stretch applied between horizontally neighbouring contactors, on one colour scale for the
    frames shown (scaled to them when ``limit`` is None) with a colorbar in %; grey where none is applied."""
    sc = np.asarray(stretch_change, float)
    if sc.ndim != 3:
        raise InvalidInputError(f"stretch_change must be (N, R, C-1), got {sc.shape}")
    frames = [int(f) for f in frames if 0 <= int(f) < sc.shape[0]]
    if not frames:
        raise InvalidInputError("frames must name at least one frame of the movie")
    limit = _limit(limit, sc[frames])
    cols = min(3, len(frames))
    rows = int(np.ceil(len(frames) / cols))
    fig = Figure(figsize=(3.2 * cols + 1.0, 3.2 * rows))
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).reshape(-1)
    image = None
    for k, (ax, f) in enumerate(zip(axes, frames)):
        ax.set_facecolor("0.6")
        image = ax.imshow(np.ma.masked_invalid(sc[f] * 100), cmap=_CMAP, norm=_norm(limit), interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"({chr(97 + k)}) frame {f}", fontsize=9)
    for ax in axes[len(frames):]:
        ax.set_axis_off()
    _colorbar(fig, image, list(axes), "stretch between contactors (%)", sc[frames], limit)
    fig.suptitle(title or "Stretch fields applied by the display (seed Figure 97)", fontsize=10)
    return fig


@dataclass(frozen=True)
class PlaybackTrace:
    """One played movie as the playback figure draws it.

    Attributes
    ----------
    target_um, measured_um : (k, 10, 10)
        Target and measured contactor positions (NaN: no measurement).
    settle : int
        Start-up frames left out of the errors.
    rms_error_um : float
        The run's RMS error, as the playback computed it (the number the report's table shows).
    """

    target_um: np.ndarray
    measured_um: np.ndarray
    settle: int
    rms_error_um: float

    @classmethod
    def of(cls, result) -> "PlaybackTrace":
        """From a :class:`skinstretch.experiments.playback.PlaybackResult`."""
        return cls(result.target_um, result.measured_um, int(result.extra.get("settle", 0)), result.rms_error_um)

    def contactor_rms_um(self) -> np.ndarray:
        """(10, 10) RMS error of each contactor over the same frames as :attr:`rms_error_um` (after ``settle``)."""
        from skinstretch.experiments.playback import rms_tracking_error  # noqa: PLC0415

        t = np.asarray(self.target_um, float)
        m = np.asarray(self.measured_um, float)
        out = np.full(t.shape[1:], np.nan)
        for idx in np.ndindex(*t.shape[1:]):
            out[idx] = rms_tracking_error(t[(slice(None), *idx)], m[(slice(None), *idx)], settle=self.settle)
        return out


def playback_figure(runs: Mapping[str, PlaybackTrace], *, rate_hz: float | None = None,
                    contactor: tuple[int, int] | None = None, title: str = "") -> Figure:
    """Target vs measured position of one contactor (the one moving most) for each run (open / closed loop),
    and the RMS error of every contactor after the start-up frames, titled with the run's own RMS error.

    ``runs``: label -> :class:`PlaybackTrace` (``PlaybackTrace.of(result)``).
    """
    if not runs:
        raise InvalidInputError("runs must hold at least one playback")
    first = np.asarray(next(iter(runs.values())).target_um, float)
    if contactor is None:
        contactor = np.unravel_index(np.argmax(np.ptp(first, axis=0)), first.shape[1:])
    i, j = contactor
    fig = Figure(figsize=(10, 3.2 + 2.6))
    gs = fig.add_gridspec(2, len(runs), height_ratios=[1.2, 1])
    top = fig.add_subplot(gs[0, :])
    scale = 1.0 / rate_hz if rate_hz else 1.0
    settle = 0
    for label, run in runs.items():
        measured = np.asarray(run.measured_um, float)
        top.plot(np.arange(measured.shape[0]) * scale, measured[:, i, j], label=f"measured, {label}", linewidth=1)
        settle = max(settle, run.settle)
    top.plot(np.arange(first.shape[0]) * scale, first[:, i, j], "k--", label="target", linewidth=1)
    if settle:
        top.axvspan(0, settle * scale, color="0.9", label="start-up (not in the errors)")
    top.set_xlabel("time (s)" if rate_hz else "frame")
    top.set_ylabel(f"contactor ({i}, {j}) position (um)")
    top.legend(fontsize=7, ncol=4)
    for k, (label, run) in enumerate(runs.items()):
        ax = fig.add_subplot(gs[1, k])
        im = ax.imshow(run.contactor_rms_um(), cmap="viridis", vmin=0)
        fig.colorbar(im, ax=ax, shrink=0.8, label="RMS error (um)")
        ax.set_title(f"{label}: RMS {run.rms_error_um:.3g} um", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(title or "Tactile movie playback: target vs measured contactor positions", fontsize=10)
    return fig

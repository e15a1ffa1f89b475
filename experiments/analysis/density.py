"""How dense the measured motion is, for the summary of an analysis: features per frame, trajectories kept, the
fraction of found features that ended up in a trajectory, and the size of the strain mesh (median Delaunay edge).

A mesh too sparse to map strain is said, in the summary and in the log, never left to be discovered in an empty
strain map. It is too sparse when fewer than half of the consecutive frame pairs give a strain triangulation, when
fewer than :data:`MIN_POINTS_PER_PAIR` points are measured in a typical pair, or when the typical Delaunay edge is
longer than :data:`MAX_MEDIAN_EDGE_MM` (the STReSS display's contactors are 1 mm apart: a mesh much coarser than that
maps nothing under most of them).

Everything is read from the results file as it is being written (column by column, in blocks), so a long session
costs no more memory than a short one.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Any

import h5py
import numpy as np

from skinstretch.experiments.results_file import PairStatus

__all__ = ["MeshDensity", "mesh_density", "MIN_POINTS_PER_PAIR", "MAX_MEDIAN_EDGE_MM", "MIN_OK_PAIR_FRACTION"]

log = logging.getLogger(__name__)

#: Fewer measured points than this in the median consecutive pair: too sparse to map strain.
MIN_POINTS_PER_PAIR = 10
#: A median Delaunay edge longer than this (mm): too coarse to map strain under a 1 mm display.
MAX_MEDIAN_EDGE_MM = 1.5
#: Fewer consecutive pairs with a strain triangulation than this fraction: too sparse.
MIN_OK_PAIR_FRACTION = 0.5

_BLOCK = 1 << 20  # rows read at a time
_EDGE_BIN_PX = 0.25


@dataclass(frozen=True)
class MeshDensity:
    """Density of an analysis' measurement (``summary["density"]``).

    Attributes
    ----------
    features_per_frame : float or None
        Features found per frame (mean; None for the flow method).
    trajectories_kept : int or None
        Trajectories at least the minimum length (None for the flow method).
    fraction_kept : float or None
        Of all features found, the fraction that belongs to a kept trajectory (None for the flow method). Features
        that enter or leave the view during the session count too; ``skinstretch evaluate`` gives the fraction of
        those that stay in view, against a simulated session's truth.
    points_per_pair : float
        Points measured between consecutive frames (median over pairs).
    mesh_edge_mm : float or None
        Median edge length of the consecutive pairs' Delaunay triangulations (None: no triangulation).
    strain_pairs, strain_pairs_ok : dict
        Frame pairs and pairs with a strain triangulation, per span.
    warning : str or None
        Why the mesh is too sparse to map strain, when it is.
    """

    method: str
    features_per_frame: float | None
    trajectories_kept: int | None
    fraction_kept: float | None
    points_per_pair: float
    mesh_edge_mm: float | None
    strain_pairs: dict[int, int] = field(default_factory=dict)
    strain_pairs_ok: dict[int, int] = field(default_factory=dict)
    warning: str | None = None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["strain_pairs"] = {str(k): v for k, v in self.strain_pairs.items()}
        d["strain_pairs_ok"] = {str(k): v for k, v in self.strain_pairs_ok.items()}
        return d


def _count_in_blocks(dset: h5py.Dataset, name: str, predicate) -> int:
    total = 0
    for a in range(0, dset.shape[0], _BLOCK):
        total += int(np.count_nonzero(predicate(dset.fields(name)[a : a + _BLOCK])))
    return total


def _median_in_blocks(dset: h5py.Dataset, name: str, upper: float) -> float | None:
    """Median of a non-negative column, to a quarter pixel, from a histogram filled a block at a time."""
    n = dset.shape[0]
    if n == 0:
        return None
    edges = np.arange(0.0, upper + 2 * _EDGE_BIN_PX, _EDGE_BIN_PX)
    counts = np.zeros(edges.size - 1, np.int64)
    for a in range(0, n, _BLOCK):
        v = np.asarray(dset.fields(name)[a : a + _BLOCK], dtype=np.float64)
        counts += np.histogram(np.clip(v, 0.0, edges[-1] - 1e-9), bins=edges)[0]
    i = int(np.searchsorted(np.cumsum(counts), (n + 1) / 2))
    return float(edges[i] + _EDGE_BIN_PX / 2)


def mesh_density(f: h5py.File, *, method: str, n_frames: int, px_per_mm: float, spans, max_edge_px: float
                 ) -> MeshDensity:
    """The :class:`MeshDensity` of the results file ``f`` (open, complete up to its derived parts); logs the warning
    when the mesh is too sparse to map strain."""
    features_per_frame = trajectories_kept = fraction_kept = None
    if method == "features" and "features" in f:
        n_features = int(f["features"].shape[0])
        features_per_frame = n_features / max(int(n_frames), 1)
        trajectories_kept = int(f["tracks"].shape[0]) if "tracks" in f else 0
        kept = _count_in_blocks(f["trajectories"], "feature_index", lambda v: v >= 0) if "trajectories" in f else 0
        fraction_kept = kept / n_features if n_features else 0.0
    points = np.asarray(f["motion_pairs"].fields("n_points")[()], dtype=np.float64) if "motion_pairs" in f else \
        np.zeros(0)
    points_per_pair = float(np.median(points)) if points.size else 0.0
    pairs, pairs_ok = {}, {}
    for span in spans:
        g = f"strain/span_{int(span)}/pairs"
        status = np.asarray(f[g].fields("status")[()]) if g in f else np.zeros(0, np.int8)
        pairs[int(span)] = int(status.size)
        pairs_ok[int(span)] = int(np.count_nonzero(status == PairStatus.OK))
    edge_px = None
    if "strain/span_1/edges" in f:
        edge_px = _median_in_blocks(f["strain/span_1/edges"], "length", max_edge_px)
    edge_mm = edge_px / px_per_mm if edge_px is not None else None
    reasons = []
    n_pairs, n_ok = pairs.get(1, max(n_frames - 1, 0)), pairs_ok.get(1, 0)
    if n_pairs and n_ok < MIN_OK_PAIR_FRACTION * n_pairs:
        reasons.append(f"only {n_ok} of {n_pairs} consecutive frame pairs give a strain triangulation")
    if points_per_pair < MIN_POINTS_PER_PAIR:
        reasons.append(f"{points_per_pair:g} points measured per frame pair (median; at least {MIN_POINTS_PER_PAIR} "
                       "needed)")
    if edge_mm is not None and edge_mm > MAX_MEDIAN_EDGE_MM:
        reasons.append(f"median mesh edge {edge_mm:.2f} mm (coarser than {MAX_MEDIAN_EDGE_MM} mm)")
    warning = None
    if reasons:
        found = ""
        if features_per_frame is not None:
            found = (f" ({features_per_frame:.1f} features per frame, {trajectories_kept} trajectories kept, "
                     f"{100 * fraction_kept:.0f} % of the features found)")
        warning = "the strain mesh is too sparse to map strain: " + "; ".join(reasons) + found
        log.warning("%s", warning)
    return MeshDensity(method, features_per_frame, trajectories_kept, fraction_kept, points_per_pair, edge_mm,
                       pairs, pairs_ok, warning)

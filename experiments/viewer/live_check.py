"""Measure the live view while a recording runs (:func:`skinstretch.experiments.recorder.record_from_camera`):
what a page received and showed, and how the live analysis' motion and strain compare with a simulated session's
truth. Used by the ``live`` bench section and the browser tests; nothing here runs during a real experiment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LiveAccuracy", "live_accuracy", "latency_percentiles"]


def latency_percentiles(shown: list[dict]) -> tuple[float, float, float]:
    """(p50, p95, max) in ms of ``shown - exposure`` over the page's live entries."""
    lat = np.array([e["shown"] - e["exposure"] for e in shown if e.get("exposure")], dtype=np.float64) * 1e3
    if lat.size == 0:
        return float("nan"), float("nan"), float("nan")
    return float(np.percentile(lat, 50)), float(np.percentile(lat, 95)), float(lat.max())


@dataclass(frozen=True)
class LiveAccuracy:
    """Live analysis against the truth: displacement RMSE (px) of matched features, and RMSE of the triangles'
    area change (fraction) against the same triangles of true features, over ``pairs`` analysed pairs."""

    pairs: int
    displacements: int
    displacement_rmse_px: float
    triangles: int
    area_change_rmse: float


def live_accuracy(overlays: list[dict], truth, truth_rows: np.ndarray, *, px_per_mm: float) -> LiveAccuracy:
    """Score live overlays (``FrameOverlays.to_json`` of analysed frames) against a simulated session's truth.

    ``truth_rows[k]`` is the truth row of recorded frame k (a looping camera repeats its source). A measured point
    is the true feature of the same frame nearest to it within 0.1 mm; pairs across a loop are left out.
    """
    fx, fy = np.asarray(truth.feature_x), np.asarray(truth.feature_y)
    vis = np.asarray(truth.feature_visible)
    radius = 0.1 * px_per_mm
    d_err, a_err, pairs = [], [], 0
    for ov in overlays:
        mesh = ov.get("mesh")
        if not mesh:
            continue
        ka, kb = int(mesh["frame_a"]), int(mesh["frame_b"])
        ra, rb = int(truth_rows[ka]), int(truth_rows[kb])
        if rb <= ra:
            continue
        pairs += 1
        tree_x, tree_y = fx[rb], fy[rb]
        ok_b = vis[rb] & vis[ra]

        def true_index(x: float, y: float) -> int:
            if not ok_b.any():  # no true feature in view (a print texture's truth lists none)
                return -1
            d2 = np.where(ok_b, (tree_x - x) ** 2 + (tree_y - y) ** 2, np.inf)
            j = int(np.argmin(d2))
            return j if d2[j] <= radius**2 else -1

        for x, y, dx, dy in ov["arrows"]:
            j = true_index(x, y)
            if j >= 0:
                d_err.append(np.hypot(dx - (fx[rb, j] - fx[ra, j]), dy - (fy[rb, j] - fy[ra, j])))
        xy = np.asarray(mesh["xy"], dtype=np.float64).reshape(-1, 6)
        for tri, change, flipped in zip(xy, mesh["change"], mesh["flipped"]):
            if flipped:
                continue
            js = [true_index(tri[2 * v], tri[2 * v + 1]) for v in range(3)]
            if min(js) < 0 or len(set(js)) < 3:
                continue
            area_a = _area(fx[ra, js], fy[ra, js])
            area_b = _area(fx[rb, js], fy[rb, js])
            if abs(area_a) > 1.0:
                a_err.append(change - (area_b / area_a - 1.0))
    d = np.asarray(d_err)
    a = np.asarray(a_err)
    return LiveAccuracy(
        pairs=pairs, displacements=int(d.size),
        displacement_rmse_px=float(np.sqrt(np.mean(d**2))) if d.size else float("nan"),
        triangles=int(a.size), area_change_rmse=float(np.sqrt(np.mean(a**2))) if a.size else float("nan"),
    )


def _area(x: np.ndarray, y: np.ndarray) -> float:
    return 0.5 * float((x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0]))

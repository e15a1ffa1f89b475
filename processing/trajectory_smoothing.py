"""Gaussian smoothing of feature trajectories along time, within each linked run (seed 5.1.2, eq. 5.2-5.3): on
(frames, tracks) arrays (:func:`smooth_positions`) and, compiled, on the long trajectory table's rows
(:func:`smooth_track_rows`), with the same numbers. Kept apart from :mod:`skinstretch.processing.tracking` so that
module stays under 900 lines.
"""

from __future__ import annotations

import numpy as np

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit

__all__ = ["smooth_positions", "smooth_track_rows"]


@njit(nogil=True)
def smooth_track_rows(track, frame, run, pos, offsets, weights):
    """Gaussian smoothing along time within each linked run (see :func:`smooth_positions`) of rows sorted by
    frame then track (``offsets``: first row of each frame); ``weights`` are the kernel's 2R + 1 values. Each sum
    runs over the kernel in the order of :func:`smooth_positions`, so the numbers are the same."""
    m = track.shape[0]
    n = offsets.shape[0] - 1
    radius = (weights.shape[0] - 1) // 2
    out = np.empty((m, 2))
    for i in range(m):
        ox = 0.0
        oy = 0.0
        w = 0.0
        for j in range(-radius, radius + 1):
            f = frame[i] + j
            if f < 0 or f >= n:
                continue
            lo, hi = offsets[f], offsets[f + 1]
            q = lo + np.searchsorted(track[lo:hi], track[i])
            if q >= hi or track[q] != track[i] or run[q] != run[i]:
                continue
            k = weights[j + radius]
            ox += pos[q, 0] * k
            oy += pos[q, 1] * k
            w += k
        out[i, 0] = ox / w
        out[i, 1] = oy / w
    return out


def smooth_positions(
    positions: np.ndarray,
    present: np.ndarray,
    linked: np.ndarray,
    *,
    radius_frames: int = 1,
    sigma_frames: float = 1.0,
) -> np.ndarray:
    """Gaussian smoothing of trajectories along time (seed eq. 5.2, 5.3), within each linked run.

    The kernel ``K(i) = exp(-i^2 / (2 sigma^2))``, ``|i| <= R`` is normalised over the samples that exist, so
    the ends of a run are not pulled toward zero (eq. 5.3 as printed is unnormalised).

    Parameters
    ----------
    positions : (N, T, 2) array
    present, linked : (N, T) bool arrays
        Where a position exists, and where it is linked to the previous frame's (runs are not smoothed across).
    radius_frames, sigma_frames
        R and sigma of eq. 5.2-5.3; ``radius_frames=0`` returns the positions unchanged.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[2] != 2 or positions.shape[:2] != present.shape:
        raise InvalidInputError(f"positions must have shape (N, T, 2) matching present, got {positions.shape}")
    if radius_frames < 0:
        raise InvalidInputError(f"radius_frames must be >= 0, got {radius_frames!r}")
    if radius_frames == 0 or positions.shape[0] < 2:
        return positions.copy()
    if not sigma_frames > 0:
        raise InvalidInputError(f"sigma_frames must be positive, got {sigma_frames!r}")
    n = positions.shape[0]
    # Run label per sample: a new run begins wherever a present sample is not linked to the previous frame.
    start = present & ~linked
    run_id = np.cumsum(start, axis=0)
    out = np.zeros_like(positions)
    weight = np.zeros(present.shape)
    filled = np.where(present[..., None], positions, 0.0)
    for i in range(-radius_frames, radius_frames + 1):
        k = float(np.exp(-(i * i) / (2.0 * sigma_frames**2)))
        lo, hi = max(0, -i), min(n, n - i)  # target frames t with t + i in range
        src = slice(lo + i, hi + i)
        tgt = slice(lo, hi)
        ok = present[src] & present[tgt] & (run_id[src] == run_id[tgt])
        out[tgt] += np.where(ok[..., None], filled[src] * k, 0.0)
        weight[tgt] += np.where(ok, k, 0.0)
    result = np.full_like(positions, np.nan)
    has = present & (weight > 0)
    result[has] = out[has] / weight[has][:, None]
    return result

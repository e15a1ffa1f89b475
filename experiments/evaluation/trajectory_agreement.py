"""How closely two analyses of the same scene agree on their feature trajectories (no truth needed).

Used to check that a session imported from a video, TIFF stack or image folder analyses like the session it was
made from (``skinstretch import``, its tests and its bench section). Each trajectory of the reference is paired
with the trajectory of the other analysis that starts within ``max_start_px`` of it in the reference's first
frame and shares the most frames with it; the agreement is the distance between paired positions over the
frames both hold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skinstretch.processing.errors import InsufficientDataError

__all__ = ["TrajectoryAgreement", "trajectory_agreement"]


@dataclass(frozen=True)
class TrajectoryAgreement:
    """Distances (px) between paired positions of two sets of trajectories.

    Attributes
    ----------
    reference_tracks, other_tracks : int
        Trajectories in each analysis.
    paired : int
        Reference trajectories that found a partner.
    positions : int
        Paired positions compared.
    mean_px, p99_px, max_px : float
        Mean, 99th percentile and largest distance between paired positions.
    """

    reference_tracks: int
    other_tracks: int
    paired: int
    positions: int
    mean_px: float
    p99_px: float
    max_px: float

    @property
    def paired_fraction(self) -> float:
        return self.paired / self.reference_tracks if self.reference_tracks else 0.0


def trajectory_agreement(reference: dict[str, np.ndarray], other: dict[str, np.ndarray], *,
                         max_start_px: float = 1.0) -> TrajectoryAgreement:
    """Compare two trajectory tables (``x``, ``y``: (frames, tracks), NaN where absent) of the same frames.

    Raises :class:`InsufficientDataError` when no trajectory of ``reference`` finds a partner.
    """
    xa, ya = np.asarray(reference["x"], float), np.asarray(reference["y"], float)
    xb, yb = np.asarray(other["x"], float), np.asarray(other["y"], float)
    if xa.shape[0] != xb.shape[0]:
        raise InsufficientDataError(f"the analyses hold {xa.shape[0]} and {xb.shape[0]} frames: not the same frames")
    present_b = np.isfinite(xb)
    distances = []
    for j in range(xa.shape[1]):
        present = np.isfinite(xa[:, j])
        if not present.any():
            continue
        k0 = int(np.argmax(present))
        start = np.hypot(xb[k0] - xa[k0, j], yb[k0] - ya[k0, j])
        candidates = np.nonzero(np.isfinite(start) & (start <= max_start_px))[0]
        if candidates.size == 0:
            continue
        overlap = (present_b[:, candidates] & present[:, None]).sum(axis=0)
        i = int(candidates[np.argmax(overlap)])
        both = present & present_b[:, i]
        distances.append(np.hypot(xa[both, j] - xb[both, i], ya[both, j] - yb[both, i]))
    if not distances:
        raise InsufficientDataError("no trajectory of the reference has a partner in the other analysis")
    d = np.concatenate(distances)
    return TrajectoryAgreement(
        reference_tracks=int(xa.shape[1]), other_tracks=int(xb.shape[1]), paired=len(distances),
        positions=int(d.size), mean_px=float(d.mean()), p99_px=float(np.percentile(d, 99)), max_px=float(d.max()),
    )

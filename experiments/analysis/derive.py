"""What is derived from the measured motion (seed 5.2-5.4), in pixels: strain tables, fingertip motion, visibility
window, stretch profile and tactile movie.

Every function takes per-pair :class:`~skinstretch.processing.tracking.MotionSample` s in pixels (rectified to the
skin when the session has a geometric mapping: that is done once, where the motion leaves the measurement) and
lengths already converted to pixels by :class:`PixelScales`. Samples may be a lazy sequence read back from the
results file, and what is derived per pair is consumed as it is computed (the stretch profile's running mean, the
tactile movie a block of frames at a time), so nothing here holds the whole session's motion.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from skinstretch.experiments.results_file import (
    AXIS_NAMES, EDGE_DTYPE, MOTION_DTYPE, TENSOR_COLUMNS, TRIANGLE_DTYPE, PairStatus, SpanStrain, pair_rows,
)
from skinstretch.processing.display_mapping import TactileMovie, TactileMovieBuilder
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.fingertip import FingertipMotion, VisibilityWindow, fingertip_motion, visibility_window
from skinstretch.processing.measurement_uncertainty import Regularisation, area_change_sigma, edge_change_sigma
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.stretch import (
    COLLINEAR, STRAIN_OK, TOO_FEW_POINTS, StretchProfile, horizontal_stretch_profile, mean_profile,
    triangulation_strains,
)
from skinstretch.processing.strain_tensor import triangle_strain_tensors
from skinstretch.processing.tracking import MotionSample

__all__ = ["PixelScales", "Derived", "span_strain", "motion_rows", "derive", "stretch_profile", "sliding_axis",
           "chain_flows", "rectified_sample", "tactile_movie_blocks", "MOVIE_BLOCK_FRAMES"]

#: Frames of the tactile movie built and handed on at a time.
MOVIE_BLOCK_FRAMES = 256

#: A self-check: a pair whose typical edge changes length by more than this per frame of its span is doubted (no
#: fingerpad stretches 5 % in 1/60 s; a registration locked onto wrong ridges reads tens of per cent).
MAX_STRAIN_PER_FRAME = 0.05
_STATUS_OF_STRAIN = {STRAIN_OK: PairStatus.OK, TOO_FEW_POINTS: PairStatus.TOO_FEW_POINTS,
                     COLLINEAR: PairStatus.COLLINEAR}


@dataclass(frozen=True)
class PixelScales:
    """The analysis' lengths in pixels, converted once from the parameters' millimetres."""

    max_edge_px: float
    profile_strip_px: float
    profile_step_px: float
    min_spacing_px: float = 0.0

    @classmethod
    def of(cls, calibration: Calibration, strain_params) -> "PixelScales":
        return cls(calibration.px(strain_params.max_edge_mm), calibration.px(strain_params.profile_strip_mm),
                   calibration.px(strain_params.profile_step_mm), calibration.px(strain_params.min_spacing_mm))


def span_strain(samples: Sequence[MotionSample], *, span: int, max_edge_px: float, first_pair: int = 0,
                min_spacing_px: float = 0.0, regularisation: Regularisation | None = None,
                shared_sigma_px: float = 0.0) -> SpanStrain:
    """Triangulation strain of a run of pairs of one span (one compiled call for all of them, see
    :func:`~skinstretch.processing.stretch.triangulation_strains`); pair ``i`` of the run is pair ``first_pair + i``
    of the span. Pairs that cannot give one carry the status and the reason. ``regularisation``: the points' errors
    are correlated as a dense registration's (None: independent, as features'); ``shared_sigma_px``: a part of
    every point's error (px per axis, e.g. a lossy codec's) that neighbours share, which cancels in strain."""
    b = triangulation_strains(samples, max_edge_px=max_edge_px, min_spacing_px=min_spacing_px)
    n = len(samples)
    reasons = [b.failure(i) or "" for i in range(n)]
    status = [_STATUS_OF_STRAIN.get(int(c), PairStatus.NO_USABLE_TRIANGLE) for c in b.status]
    for i, smp in enumerate(samples):
        if status[i] != PairStatus.OK:
            continue
        # Self-checks: a pair whose registration failed, or whose strain no skin makes that fast.
        change = b.edge_change[b.edge_offsets[i]:b.edge_offsets[i + 1]]
        typical = float(np.median(np.abs(change))) if change.size else 0.0
        if smp.doubt:
            status[i], reasons[i] = PairStatus.DOUBTED, smp.doubt
        elif typical > MAX_STRAIN_PER_FRAME * (frames := int(b.frame_b[i] - b.frame_a[i])):
            status[i], reasons[i] = PairStatus.DOUBTED, (
                f"strain no skin makes in {frames} frame{'s' if frames > 1 else ''} (median |edge change| "
                f"{100 * typical:.1f} % > {100 * MAX_STRAIN_PER_FRAME * frames:.0f} %)")
    pairs = pair_rows(b.frame_a, b.frame_b, b.n_points, status, reasons)
    where = np.arange(first_pair, first_pair + n, dtype=np.int64)
    # The edge and triangle tables are filled field by field over the batch's flat arrays.
    edges = np.zeros(b.edges.shape[0], dtype=EDGE_DTYPE)
    edges["pair"] = np.repeat(where, np.diff(b.edge_offsets))
    edges["id_a"], edges["id_b"] = b.ids[b.edges].T
    edges["xa"], edges["ya"], edges["xb"], edges["yb"] = b.points[b.edges].reshape(-1, 4).T
    edges["length"], edges["change"] = b.edge_length, b.edge_change
    sigma = np.concatenate([np.full(len(smp), np.inf) if smp.sigma is None else np.asarray(smp.sigma, np.float64)
                            for smp in samples]) if samples else np.zeros(0)
    if shared_sigma_px > 0.0:
        sigma = np.sqrt(np.maximum(sigma**2 - shared_sigma_px**2, 0.0))  # inf stays inf
        if regularisation is not None:
            regularisation = dataclasses.replace(regularisation, independent_px=math.sqrt(max(
                regularisation.independent_px**2 - shared_sigma_px**2, 0.0)))
    ea, eb = b.edges[:, 0], b.edges[:, 1]
    rho = 0.0 if regularisation is None else regularisation.correlation(b.points[eb] - b.points[ea], sigma[ea],
                                                                        sigma[eb])
    edges["change_sigma"] = edge_change_sigma(sigma[ea], sigma[eb], b.edge_length, rho)
    tris = np.zeros(b.triangles.shape[0], dtype=TRIANGLE_DTYPE)
    tris["pair"] = np.repeat(where, np.diff(b.triangle_offsets))
    tris["id_a"], tris["id_b"], tris["id_c"] = b.ids[b.triangles].T
    xy = b.points[b.triangles].reshape(-1, 6)  # x0, y0, x1, y1, x2, y2
    for j in range(3):
        tris[f"x{j}"], tris[f"y{j}"] = xy[:, 2 * j], xy[:, 2 * j + 1]
    tris["area"], tris["change"], tris["flipped"] = b.area, b.area_change, b.flipped
    tris["change_sigma"] = area_change_sigma(b.points[b.triangles], sigma[b.triangles], b.area, regularisation)
    corners_a = b.points[b.triangles]  # (T, 3, 2)
    tensors = triangle_strain_tensors(corners_a, corners_a + b.displacement[b.triangles])
    for name in TENSOR_COLUMNS:
        tris[name] = getattr(tensors, name)
    tris["tensor_status"] = tensors.status
    return SpanStrain(span, pairs, edges, tris)


def motion_rows(samples: Sequence[MotionSample], *, first_pair: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The ``motion_pairs`` and ``motion`` rows of a run of consecutive pairs."""
    pairs = pair_rows([s.frame_a for s in samples], [s.frame_b for s in samples], [len(s) for s in samples],
                      [PairStatus.NO_MOTION if not len(s) else PairStatus.DOUBTED if s.doubt else PairStatus.OK
                       for s in samples],
                      ["no motion measured" if not len(s) else s.doubt for s in samples])
    parts = []
    for i, s in enumerate(samples):
        t = np.zeros(len(s), dtype=MOTION_DTYPE)
        t["pair"] = first_pair + i
        t["id"] = s.ids
        t["x"], t["y"] = s.points.T
        t["dx"], t["dy"] = s.displacement.T
        t["sigma"] = np.inf if s.sigma is None else s.sigma  # not estimated: no bound
        t["match"] = 0.0 if s.match is None else s.match
        parts.append(t)
    return pairs, (np.concatenate(parts) if parts else np.zeros(0, MOTION_DTYPE))


def rectified_sample(s: MotionSample, mapping, px_per_mm: float) -> MotionSample:
    """Image px -> skin px (the mapping's mm times px_per_mm), so strains are on the skin (seed 3.4)."""
    if mapping is None or len(s) == 0:
        return s
    pa = np.asarray(mapping.image_to_surface(s.points), dtype=np.float64) * px_per_mm
    pb = np.asarray(mapping.image_to_surface(s.points + s.displacement), dtype=np.float64) * px_per_mm
    return dataclasses.replace(s, points=pa, displacement=pb - pa)


def chain_flows(fields: Sequence, *, stride: int = 1) -> MotionSample:
    """Displacement from the first field's frame to the last field's second frame, following skin points
    (every ``stride``-th node of the first grid) through each field in turn; points lost on the way drop out."""
    if not fields:
        raise InvalidInputError("chain_flows needs at least one field")
    first = fields[0].motion(stride=stride)
    p0 = first.points
    p = p0 + first.displacement
    ids = first.ids
    var = None if first.sigma is None else first.sigma**2  # the steps' errors add up (independent)
    doubt = first.doubt
    for f in fields[1:]:
        d, ok = f.sample(p)
        step = None if var is None or f.sigma is None else f.sigma_at(p)
        var = None if step is None else var[ok] + step[ok] ** 2
        p, p0, ids = p[ok] + d[ok], p0[ok], ids[ok]
        doubt = doubt or (f.status.removeprefix("doubted: ") if f.status.startswith("doubted: ") else "")
    return MotionSample(fields[0].frame_a, fields[-1].frame_b, p0, p - p0, ids, None if var is None else np.sqrt(var),
                        doubt=doubt)


def sliding_axis(fingertip_position: np.ndarray) -> int:
    """0 (x) or 1 (y): the axis along which the fingertip travelled furthest (the profile's axis)."""
    travel = np.ptp(fingertip_position, axis=0) if fingertip_position.shape[0] else np.zeros(2)
    return int(np.argmax(travel))


class _PairProfiles(Sequence):
    """Each consecutive pair's stretch profile, computed when it is read: :func:`mean_profile` reads them once, in
    order, so a session's profiles are never all held."""

    def __init__(self, samples: Sequence[MotionSample], fingertip_displacement: np.ndarray, *, axis: int,
                 positions: np.ndarray, strip_px: float) -> None:
        self._samples, self._ft = samples, fingertip_displacement
        self._axis, self._positions, self._strip_px = axis, positions, strip_px

    def __len__(self) -> int:
        return len(self._samples)

    def __getitem__(self, k: int) -> StretchProfile:
        s, ft = self._samples[k], self._ft[k]
        if self._axis == 1:
            s = MotionSample(s.frame_a, s.frame_b, s.points[:, ::-1], s.displacement[:, ::-1], s.ids)
            ft = ft[::-1]
        return horizontal_stretch_profile(s, fingertip_displacement=ft, x_positions=self._positions,
                                          strip_width_px=self._strip_px)

    def __iter__(self) -> Iterator[StretchProfile]:
        return (self[k] for k in range(len(self)))


def stretch_profile(samples: Sequence[MotionSample], fingertip_displacement: np.ndarray, *, axis: int,
                    positions: np.ndarray, strip_px: float) -> StretchProfile:
    """Seed Figure 94: the change in stretch along ``axis`` averaged over every consecutive pair.

    A position is kept when at least a quarter of the pairs measured it, so a few pairs cannot make the average
    where the skin is seldom seen (the edge of the contact area, a dark band without features).
    """
    profiles = _PairProfiles(samples, fingertip_displacement, axis=axis, positions=positions, strip_px=strip_px)
    return mean_profile(profiles, min_pairs=max(1, len(profiles) // 4))


@dataclass(frozen=True)
class Derived:
    """What is computed from the consecutive pairs' motion and kept whole (seed 5.2, 5.3.2); the tactile movie
    (5.4) follows from it a block of frames at a time (:func:`tactile_movie_blocks`)."""

    fingertip: FingertipMotion
    window: VisibilityWindow | None
    window_status: str  # "ok" or why there is no visibility window (and so no movie)
    profile_axis: str  # "x" or "y"
    profile: StretchProfile


def derive(samples: Sequence[MotionSample], *, n_frames: int, image_shape: tuple[int, int], scales: PixelScales,
           profile_axis: int | None = None) -> Derived:
    """Fingertip motion and visibility window (seed 5.2) and stretch profile (5.3.2, Figure 94) from the
    consecutive pairs' samples (iterated once for each)."""
    ft = fingertip_motion(samples, n_frames=n_frames)
    try:
        win, status = visibility_window(ft, image_shape=image_shape), "ok"
    except InsufficientDataError as exc:
        win, status = None, str(exc)
    axis = sliding_axis(ft.position) if profile_axis is None else int(profile_axis)
    length = image_shape[1] if axis == 0 else image_shape[0]
    step = scales.profile_step_px
    positions = np.arange(step, length - step / 2, step)
    profile = stretch_profile(samples, ft.displacement, axis=axis, positions=positions, strip_px=scales.profile_strip_px)
    return Derived(ft, win, status, AXIS_NAMES[axis], profile)


def tactile_movie_blocks(samples: Sequence[MotionSample], derived: Derived, *, calibration: Calibration,
                         image_shape: tuple[int, int], display_params, block_frames: int | None = None
                         ) -> Iterator[TactileMovie]:
    """The tactile movie (seed 5.4) of every frame, ``block_frames`` consecutive frames at a time (None:
    :data:`MOVIE_BLOCK_FRAMES`; the frames of :func:`~skinstretch.processing.display_mapping.tactile_movie`); none
    without a visibility window."""
    if derived.window is None:
        return
    block_frames = MOVIE_BLOCK_FRAMES if block_frames is None else int(block_frames)
    axis = AXIS_NAMES.index(derived.profile_axis)
    n = derived.fingertip.n_frames
    if len(samples) != n - 1:
        raise InvalidInputError(f"expected {n - 1} consecutive-pair samples, got {len(samples)}")
    builder = TactileMovieBuilder(fingertip=derived.fingertip, window=derived.window, calibration=calibration,
                                  image_shape=image_shape, params=display_params, motion_axis=axis)
    frames = [builder.first_frame()]
    for s in samples:
        if len(frames) == block_frames:
            yield TactileMovie.of_frames(frames, motion_axis=axis)
            frames = []
        frames.append(builder.add(s))
    yield TactileMovie.of_frames(frames, motion_axis=axis)

"""From measured skin movement to a tactile movie for the STReSS 10x10 display (seed 5.4).

The display's 10 x 10 mm active area is associated with a 10 x 10 mm patch of skin centred on the visibility
window (which follows the fingertip). The patch is divided into 10 x 10 squares; the movement of each square is
the average movement, relative to the fingertip, of the points inside it (seed 5.3.2). A contactor's ideal
position is the cumulated movement since the first frame (Figure 63(b)). The display moves its contactors along one
axis only, which the seed aligns with the sliding direction (its images show the finger sliding along x). Here the
image axis the contactors follow is ``motion_axis`` (analysis passes the fingertip's sliding axis), and the
"horizontal" position is either the projection of the ideal vector on that axis (Figure 63(d)) or the vector
rotated onto it (Figure 63(c)). The movie is laid out in display terms: its last axis (the display's columns) always
runs along ``motion_axis``, so when the finger slides along image y the contactor grid is the image's transpose.
A contactor whose square leaves the field of view, or holds no measured point, is reset to
rest (seed 5.4). Positions are in micrometres, clipped to the display's +/-50 um range.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Sequence

import numpy as np
from pydantic import Field

from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.parameters import parameters
from skinstretch.processing.fingertip import FingertipMotion, VisibilityWindow
from skinstretch.processing.tracking import MotionSample


class HorizontalMapping(Enum):
    """How the 2-D ideal contactor position becomes a horizontal one (seed Figure 63(c), (d))."""

    PROJECTION = "projection"
    ROTATION = "rotation"


@parameters
class DisplayMappingParams:
    """Geometry and range of the display, in mm and um (seed 5.4: 10 x 10 contactors at 1 mm, +/-50 um)."""

    contactors: int = Field(10, ge=2)
    pitch_mm: float = Field(1.0, gt=0)
    range_um: float = Field(50.0, gt=0)
    horizontal: HorizontalMapping = HorizontalMapping.PROJECTION


@dataclass(frozen=True)
class TactileMovie:
    """Contactor positions over time and how they were obtained.

    Attributes
    ----------
    positions_um : (N, C, C) float32
        Contactor position (um) along the motion axis, positive towards increasing image coordinate. Index
        ``[frame, row, col]``: columns run along the motion axis, rows across it (for ``motion_axis=0``, image rows
        top to bottom and columns left to right; for ``motion_axis=1`` the transpose).
    reset : (N, C, C) bool
        The contactor was reset to 0 in that frame (square out of view, or no movement measured in it).
    clipped : (N, C, C) bool
        The position reached the display's range and was clipped.
    ideal_um : (N, C, C, 2) float32
        Cumulated 2-D movement (um) before the mapping and clipping; the vector's components are (along the motion
        axis, across it), in the same grid layout as ``positions_um``.
    stretch_change : (N, C, C-1) float32
        Change in stretch between contactors neighbouring along the motion axis (fraction of the pitch, Figure 66).
    motion_axis : int
        The image axis (0 = x, 1 = y) the contactors move along.
    """

    positions_um: np.ndarray
    reset: np.ndarray
    clipped: np.ndarray
    ideal_um: np.ndarray
    stretch_change: np.ndarray
    motion_axis: int = 0

    @classmethod
    def of_frames(cls, frames: Sequence["TactileMovieFrame"], *, motion_axis: int) -> "TactileMovie":
        """The movie of consecutive frames (from :class:`TactileMovieBuilder`), stacked along a frame axis."""
        if not frames:
            raise InvalidInputError("a tactile movie needs at least one frame")
        return cls(
            positions_um=np.stack([f.positions_um for f in frames]),
            reset=np.stack([f.reset for f in frames]),
            clipped=np.stack([f.clipped for f in frames]),
            ideal_um=np.stack([f.ideal_um for f in frames]),
            stretch_change=np.stack([f.stretch_change for f in frames]),
            motion_axis=int(motion_axis),
        )


def tactile_movie(
    samples: Sequence[MotionSample],
    *,
    fingertip: FingertipMotion,
    window: VisibilityWindow,
    calibration: Calibration,
    image_shape: tuple[int, int],
    params: DisplayMappingParams | None = None,
    motion_axis: int = 0,
) -> TactileMovie:
    """Map per-pair movements (``samples[k]``: frame k -> k+1) to contactor positions for every frame.

    ``motion_axis`` is the image axis (0 = x, 1 = y) the contactors' motion stands for: the sliding direction.
    :class:`TactileMovieBuilder` gives the same frames one at a time (a long session's movie need not be held).

    Examples
    --------
    >>> import numpy as np
    >>> from skinstretch.processing.fingertip import fingertip_motion, visibility_window
    >>> cal = Calibration(px_per_mm=20.0)
    >>> g = np.stack(np.meshgrid(np.arange(20.0, 380, 5), np.arange(20.0, 380, 5)), -1).reshape(-1, 2)
    >>> d = np.zeros_like(g); d[:, 0] = 0.01 * (g[:, 0] - 200)  # 1 % horizontal stretch about x=200
    >>> s = [MotionSample(0, 1, g, d, np.arange(len(g)))]
    >>> ft = fingertip_motion(s, n_frames=2)
    >>> movie = tactile_movie(s, fingertip=ft, window=visibility_window(ft, image_shape=(400, 400)),
    ...                       calibration=cal, image_shape=(400, 400))
    >>> movie.positions_um.shape, bool(movie.positions_um[1, 0, -1] > 0 > movie.positions_um[1, 0, 0])
    ((2, 10, 10), True)
    """
    builder = TactileMovieBuilder(fingertip=fingertip, window=window, calibration=calibration,
                                  image_shape=image_shape, params=params, motion_axis=motion_axis)
    n = fingertip.n_frames
    if len(samples) != n - 1:
        raise InvalidInputError(f"expected {n - 1} consecutive-pair samples, got {len(samples)}")
    return TactileMovie.of_frames([builder.first_frame()] + [builder.add(s) for s in samples], motion_axis=motion_axis)


@dataclass(frozen=True)
class TactileMovieFrame:
    """One frame of a :class:`TactileMovie` (its arrays without the leading frame axis)."""

    positions_um: np.ndarray  # (C, C) float32
    reset: np.ndarray  # (C, C) bool
    clipped: np.ndarray  # (C, C) bool
    ideal_um: np.ndarray  # (C, C, 2) float32
    stretch_change: np.ndarray  # (C, C-1) float32


class TactileMovieBuilder:
    """The tactile movie of :func:`tactile_movie` a frame at a time: :meth:`first_frame` (all contactors at rest),
    then :meth:`add` with each consecutive pair's sample in order gives the next frame. Only the previous frame's
    ideal positions are kept, so a session of any length streams through it."""

    def __init__(
        self,
        *,
        fingertip: FingertipMotion,
        window: VisibilityWindow,
        calibration: Calibration,
        image_shape: tuple[int, int],
        params: DisplayMappingParams | None = None,
        motion_axis: int = 0,
    ) -> None:
        self.params = params or DisplayMappingParams()
        if motion_axis not in (0, 1):
            raise InvalidInputError(f"motion_axis must be 0 (x) or 1 (y), got {motion_axis!r}")
        n = fingertip.n_frames
        if window.centers.shape != (n, 2):
            raise InvalidInputError(f"window has {window.centers.shape[0]} frames, fingertip motion {n}")
        self.fingertip, self.window, self.motion_axis = fingertip, window, int(motion_axis)
        c = int(self.params.contactors)
        self._c = c
        self._pitch = calibration.px(self.params.pitch_mm)
        self._um_per_px = 1000.0 / calibration.px_per_mm
        self._shape = image_shape
        self._offsets = (np.arange(c) - (c - 1) / 2.0) * self._pitch
        self._ideal = np.zeros((c, c, 2))  # of the last frame given, in image layout
        self._k = 0  # the next sample's frame_a

    def first_frame(self) -> TactileMovieFrame:
        """Frame 0: every contactor at rest."""
        return self._frame(np.zeros((self._c, self._c, 2)), np.zeros((self._c, self._c), bool))

    def add(self, s: MotionSample) -> TactileMovieFrame:
        """The frame after ``s`` (frames k -> k+1, k counting the samples given so far)."""
        k, c, pitch, offsets = self._k, self._c, self._pitch, self._offsets
        if k + 1 >= self.fingertip.n_frames:
            raise InvalidInputError(f"more samples than the {self.fingertip.n_frames - 1} pairs of the fingertip motion")
        if s.frame_a != k or s.frame_b != k + 1:
            raise InvalidInputError(f"samples[{k}] is frames {s.frame_a}->{s.frame_b}, expected {k}->{k + 1}")
        centers = self.window.centers
        h, w = self._shape
        cx, cy = centers[k]
        # Square (row, col) spans [c - pitch/2, c + pitch/2) around its centre.
        cols = np.floor((np.asarray(s.points)[:, 0] - (cx + offsets[0] - pitch / 2)) / pitch).astype(np.int64)
        rows = np.floor((np.asarray(s.points)[:, 1] - (cy + offsets[0] - pitch / 2)) / pitch).astype(np.int64)
        inside = (cols >= 0) & (cols < c) & (rows >= 0) & (rows < c)
        rel = (np.asarray(s.displacement, dtype=np.float64) - self.fingertip.displacement[k]) * self._um_per_px
        sums = np.zeros((c, c, 2))
        count = np.zeros((c, c), np.int64)
        np.add.at(sums, (rows[inside], cols[inside]), rel[inside])
        np.add.at(count, (rows[inside], cols[inside]), 1)
        # Squares must be in view in both frames of the pair (seed 5.4: occluded contactors are reset).
        in_view = np.ones((c, c), bool)
        for centre in (centers[k], centers[k + 1]):
            xs = centre[0] + offsets
            ys = centre[1] + offsets
            okx = (xs - pitch / 2 >= 0) & (xs + pitch / 2 <= w - 1)
            oky = (ys - pitch / 2 >= 0) & (ys + pitch / 2 <= h - 1)
            in_view &= oky[:, None] & okx[None, :]
        measured = (count > 0) & in_view
        step = np.zeros((c, c, 2))
        step[measured] = sums[measured] / count[measured][:, None]
        self._ideal = np.where(measured[..., None], self._ideal + step, 0.0)
        self._k = k + 1
        return self._frame(self._ideal, ~measured)

    def _frame(self, ideal: np.ndarray, reset: np.ndarray) -> TactileMovieFrame:
        p = self.params
        if self.motion_axis == 1:
            # Display layout: columns along the motion axis, vector components (along, across).
            ideal = ideal.transpose(1, 0, 2)[..., ::-1]
            reset = reset.transpose(1, 0)
        if p.horizontal is HorizontalMapping.PROJECTION:
            horizontal = ideal[..., 0]
        else:
            # Rotate the ideal vector onto the motion axis, keeping the side it points to.
            horizontal = np.sign(ideal[..., 0]) * np.hypot(ideal[..., 0], ideal[..., 1])
        clipped = np.abs(horizontal) > p.range_um
        positions = np.clip(horizontal, -p.range_um, p.range_um)
        stretch = np.diff(positions, axis=1) / (p.pitch_mm * 1000.0)
        return TactileMovieFrame(
            positions_um=positions.astype(np.float32),
            reset=np.ascontiguousarray(reset),
            clipped=clipped,
            ideal_um=np.ascontiguousarray(ideal, dtype=np.float32),
            stretch_change=stretch.astype(np.float32),
        )

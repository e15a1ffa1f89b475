"""Where the analysis gets its frames: a session file read frame by frame, or frames already in memory.

A :class:`FrameSource` is a sequence of 2-D uint8 frames that can be sent to a worker process cheaply: a
:class:`SessionFrames` travels as its path (each process opens the file itself and reads only its chunk), an
:class:`ArrayFrames` as the frames of the chunk asked for (:meth:`FrameSource.part`). Nothing holds the whole
session in memory. Glass-fixed shading (:mod:`skinstretch.processing.glass_shading`) is estimated in one streaming
pass here and removed from each frame as the motion measurement reads it (:class:`FrameReader`); feature
extraction reads the frames as recorded (:meth:`FrameReader.pair`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skinstretch.drivers.session_file import open_session
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.pixel_scale import Calibration

__all__ = ["FrameSource", "SessionFrames", "ArrayFrames", "Shading", "FrameReader", "estimate_shading"]

log = logging.getLogger(__name__)


class FrameSource(Sequence):
    """Frames numbered 0..N-1 (2-D uint8). ``source[k]`` reads frame k; :meth:`part` is what a worker needs."""

    shape: tuple[int, int]

    def part(self, first: int, last: int) -> "FrameSource":
        """A source that can read frames ``first..last`` (inclusive; numbering unchanged), cheap to pickle."""
        return self

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        k = int(k)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(f"frame {k} out of range for {len(self)} frames")
        return self._frame(k)

    def _frame(self, k: int) -> np.ndarray:
        raise NotImplementedError


class SessionFrames(FrameSource):
    """The frames of a session file, read one at a time (each process opens the file itself)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        with open_session(self.path) as s:
            self._n, height, width = s.shape
        self.shape = (int(height), int(width))
        self._session = None

    def __len__(self) -> int:
        return self._n

    def _frame(self, k: int) -> np.ndarray:
        if self._session is None:
            self._session = open_session(self.path)
        return self._session.frame(k)

    def close(self) -> None:
        if self._session is not None:
            self._session.close()
            self._session = None

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_session": None}  # the other process opens its own


class ArrayFrames(FrameSource):
    """Frames in memory (an (N, H, W) array or a list of 2-D arrays); a :meth:`part` sent to another process carries
    only its chunk's frames (read in this process, it copies nothing)."""

    def __init__(self, frames: Sequence[np.ndarray] | np.ndarray, *, first: int = 0, n_frames: int | None = None) -> None:
        self._frames = frames
        self._first = int(first)
        self._n = int(n_frames) if n_frames is not None else len(frames)
        self._part: tuple[int, int] | None = None  # (first, last) frame a part may read
        if len(frames) == 0:
            raise InsufficientDataError("no frames to analyse")
        f0 = np.asarray(frames[0])
        if f0.ndim != 2:
            raise InvalidInputError(f"frames must be 2-D grey images, got shape {f0.shape}")
        self.shape = (int(f0.shape[0]), int(f0.shape[1]))

    def __len__(self) -> int:
        return self._n

    def _frame(self, k: int) -> np.ndarray:
        i = k - self._first
        if not 0 <= i < len(self._frames):
            raise IndexError(f"frame {k} is not in this part (frames {self._first}..{self._first + len(self._frames) - 1})")
        return np.asarray(self._frames[i])

    def part(self, first: int, last: int) -> "ArrayFrames":
        out = ArrayFrames(self._frames, first=self._first, n_frames=self._n)
        out._part = (int(first), int(last))
        return out

    def __getstate__(self) -> dict:
        if self._part is None:
            return dict(self.__dict__)
        first, last = self._part
        frames = [np.asarray(self._frames[k - self._first]) for k in range(first, last + 1)]
        return {**self.__dict__, "_frames": frames, "_first": first, "_part": None}


@dataclass(frozen=True)
class Shading:
    """Glass-fixed shading to remove (:class:`skinstretch.processing.glass_shading.GlassShading`) and the frames it
    applies to (the others, all black or saturated, are passed on untouched)."""

    shading: object  # GlassShading
    good: np.ndarray  # (N,) bool


class FrameReader:
    """Frame k as the motion measurement sees it: read from the source, glass-fixed shading removed where it
    applies (``reader(k)``); :meth:`pair` also gives the frame as recorded, which feature extraction sees."""

    def __init__(self, source: FrameSource, shading: Shading | None = None) -> None:
        self.source = source
        self.shading = shading

    def __call__(self, k: int) -> np.ndarray:
        return self.pair(k)[1]

    def pair(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame k as recorded and as the motion measurement sees it (the same array when no shading applies), from
        one read.

        Features are extracted from the frame as recorded: where the skin touches the glass is told by the FTIR
        contrast, which the shading removal equalises on purpose (partial contact gets full contrast, the bare
        glass's noise is amplified up to the gain's limit), and the glass-fixed statistics it subtracts keep a
        trace of the print, which moves the minutiae and pores found in it (tuning log "Moved from docstrings").
        Their motion is registered on the corrected frames, where the glass-fixed patterns no longer pull it
        towards zero.
        """
        frame = self.source[k]
        if self.shading is not None and self.shading.good[k]:
            from skinstretch.processing.glass_shading import remove_glass_shading  # noqa: PLC0415

            return frame, remove_glass_shading(frame, self.shading.shading)
        return frame, frame

    def part(self, first: int, last: int) -> "FrameReader":
        return FrameReader(self.source.part(first, last), self.shading)


def estimate_shading(source: FrameSource, *, calibration: Calibration, params, surface: str | None
                     ) -> tuple[Shading | None, str]:
    """The glass-fixed shading of ``source`` when ``params`` (:class:`AnalysisParams`) ask for it, and what was
    done (the results' ``glass_shading_status``). One streaming pass finds the frames to leave out (all black,
    saturated: extraction flags them), one more takes the statistics."""
    from skinstretch.processing.extraction import frame_flags  # noqa: PLC0415
    from skinstretch.processing.glass_shading import glass_shading  # noqa: PLC0415
    from skinstretch.experiments.analysis.plan import shading_min_motion, wants_glass_shading  # noqa: PLC0415

    gs = params.glass_shading
    if not wants_glass_shading(gs, surface):
        return None, "off" if gs.enabled is False else f"off (surface {surface or 'unknown'})"
    good = np.array([not frame_flags(source[k], params.extraction) for k in range(len(source))], dtype=bool)
    try:  # InsufficientDataError: fewer than 2 usable frames, or skin that barely moved
        shading = glass_shading(
            source,
            use=np.flatnonzero(good),
            smooth_px=calibration.px(gs.smooth_mm),
            along_shape_px=calibration.px(gs.along_shape_mm),
            min_motion_ratio=shading_min_motion(gs, surface),
        )
    except InsufficientDataError as exc:
        return None, f"not applied: {exc}"
    return Shading(shading, good), f"applied (motion ratio {shading.motion_ratio:.2f})"

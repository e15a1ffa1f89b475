"""What every file of frames offers (a video, a TIFF stack, a folder of images), and the rule that makes it grey.

One reader per format lives beside this module; the replay camera (:mod:`skinstretch.drivers.camera.replay`) and
``skinstretch import`` (:mod:`skinstretch.experiments.frame_import`) both use them, so a file replays exactly as it
imports.

Grey rule
---------
Readers return one grey image per frame at the file's own bit depth (uint8, uint16, or the TIFF's own type):

* colour (RGB, BGR, with or without alpha) becomes its ITU-R BT.601 luma, ``Y = 0.299 R + 0.587 G + 0.114 B``
  rounded to the nearest integer, as OpenCV, Pillow and FFmpeg compute it; alpha is ignored;
* a YUV video gives its luma plane, rescaled to full range by FFmpeg when the video is limited-range;
* a video of more than 8 bits per sample is read as 16-bit grey.

How a deeper image becomes the 8 bits of a session is the import's rule (one linear map for the whole file,
:mod:`skinstretch.experiments.frame_import`); the replay camera passes 16-bit frames on unchanged.
"""

from __future__ import annotations

import math
import os
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from skinstretch.drivers.errors import FrameFileError

__all__ = ["FrameReader", "SourceFrame", "LUMA_WEIGHTS_RGB", "is_colour", "to_grey"]

#: BT.601 luma weights of R, G, B (the colour rule above).
LUMA_WEIGHTS_RGB = (0.299, 0.587, 0.114)


@dataclass(frozen=True)
class SourceFrame:
    """One frame of a file.

    Attributes
    ----------
    index : int
        Position in the file, from 0.
    image : (H, W) array
        Grey pixels (see the grey rule), rows first.
    time_s : float
        Time the file gives the frame, in seconds after its first frame (container time stamps, OME plane times);
        NaN when the file gives none.
    """

    index: int
    image: np.ndarray
    time_s: float


def is_colour(image: np.ndarray) -> bool:
    """Whether a decoded image has colour channels (3 or 4: RGB or BGR, with or without alpha)."""
    return image.ndim == 3 and image.shape[2] >= 3


def to_grey(image: np.ndarray, *, channel_order: str, where: str) -> np.ndarray:
    """A 2-D grey image from a grey or colour one, by the grey rule of this module.

    Parameters
    ----------
    image : (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) array
        The pixels as read.
    channel_order : {"rgb", "bgr"}
        Order of the colour channels (OpenCV reads BGR, tifffile RGB).
    where : str
        The file (and frame) named in an error.
    """
    if channel_order not in ("rgb", "bgr"):
        raise ValueError(f"channel_order must be 'rgb' or 'bgr', got {channel_order!r}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] in (3, 4):
        colour = image[:, :, :3]
        if channel_order == "bgr":
            colour = colour[:, :, ::-1]
        if image.dtype == np.uint8:  # OpenCV's fixed-point luma: exact to the rounding for 8 bits, and fast
            image = cv2.cvtColor(np.ascontiguousarray(colour), cv2.COLOR_RGB2GRAY)
        else:
            luma = colour.astype(np.float64) @ np.asarray(LUMA_WEIGHTS_RGB)
            image = np.rint(luma).astype(image.dtype) if np.issubdtype(image.dtype, np.integer) else luma
    if image.ndim != 2:
        raise FrameFileError(f"{where}: expected a grey or colour image, got an array of shape {image.shape}")
    if not (np.issubdtype(image.dtype, np.integer) or np.issubdtype(image.dtype, np.floating)):
        raise FrameFileError(f"{where}: pixels of type {image.dtype} are not supported")
    return np.ascontiguousarray(image)


class FrameReader(ABC):
    """A file of frames read one frame at a time (the whole file is never held in memory).

    Attributes set by every reader: ``path``, ``shape`` (H, W), ``dtype`` (of the grey frames), ``n_frames``
    (None while unknown: a video whose container does not say), ``fps`` and ``px_per_mm`` (None when the file
    does not declare them), ``colour`` (the file's pixels are colour: its frames are their luma by the grey rule),
    ``lossy`` (the file's compression changed the pixels: True for a lossy codec such as H.264 or JPEG, False for
    raw or lossless storage, None when the codec has both modes and the file does not say which) and
    ``compression`` (the codec or compression, by name). Use as a context manager or call :meth:`close`.
    """

    #: What kind of file this reader reads, for messages and the session's record of its source.
    kind: str = "frames"

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.shape: tuple[int, int] = (0, 0)
        self.dtype: np.dtype = np.dtype(np.uint8)
        self.n_frames: int | None = None
        self.fps: float | None = None
        self.px_per_mm: float | None = None
        self.colour = False
        self.lossy: bool | None = False
        self.compression = "none"
        self._cursor: Iterator[SourceFrame] | None = None
        self._next_index = 0

    @property
    def name(self) -> str:
        return str(self.path)

    @abstractmethod
    def frames(self) -> Iterator[SourceFrame]:
        """Every frame in order, from the first, read as it is needed; a new iterator starts again."""

    def read(self, index: int) -> SourceFrame:
        """Frame ``index``; IndexError past the last one. Reading in order is fast; going back restarts."""
        if index < 0:
            raise IndexError(f"frame index must be >= 0, got {index}")
        if self._cursor is None or index < self._next_index:
            self._drop_cursor()
            self._cursor = self.frames()
            self._next_index = 0
        for frame in self._cursor:
            self._next_index = frame.index + 1
            if frame.index == index:
                return frame
        self._drop_cursor()
        raise IndexError(f"{self.name}: no frame {index} (the file holds {self._next_index})")

    def describe(self) -> dict[str, Any]:
        """What the session records about its source: the file, its kind, and what the file itself declared."""
        return {
            "path": str(self.path.resolve()),
            "kind": self.kind,
            "frames_declared": self.n_frames,
            "width": self.shape[1],
            "height": self.shape[0],
            "dtype": str(self.dtype),
            "colour": self.colour,
            "compression": self.compression,
            "lossy": self.lossy,
            "fps_declared": self.fps,
            "px_per_mm_declared": self.px_per_mm,
        }

    def _drop_cursor(self) -> None:
        cursor, self._cursor = self._cursor, None
        close = getattr(cursor, "close", None)
        if close is not None:
            close()  # a generator's finally releases what it holds (an open container) now, not when collected

    def close(self) -> None:
        """Release the file (idempotent)."""
        self._drop_cursor()

    def __enter__(self) -> "FrameReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        n = "?" if self.n_frames is None else self.n_frames
        return f"{type(self).__name__}({self.name!r}, {n} frames of {self.shape[1]}x{self.shape[0]} {self.dtype})"


def positive_or_none(value: Any) -> float | None:
    """A declared rate or scale when it is a finite positive number, else None (files often hold 0 or junk)."""
    try:
        v = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return v if math.isfinite(v) and v > 0 else None

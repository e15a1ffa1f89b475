"""Readers of frames stored in files that are not sessions: videos, TIFF stacks, folders of images.

One reader per format (:class:`VideoFile`, :class:`TiffStack`, :class:`ImageFolder`), all :class:`FrameReader` s,
shared by the replay camera and ``skinstretch import``. :func:`open_frame_reader` picks one from a path.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from skinstretch.drivers.errors import FrameFileError
from skinstretch.drivers.frame_readers.base import FrameReader, SourceFrame, to_grey
from skinstretch.drivers.frame_readers.image_folder import IMAGE_SUFFIXES, ImageFolder
from skinstretch.drivers.frame_readers.tiff_stack import TiffStack
from skinstretch.drivers.frame_readers.video import VideoFile

__all__ = [
    "FrameReader",
    "ImageFolder",
    "SourceFrame",
    "TiffStack",
    "VideoFile",
    "open_frame_reader",
    "to_grey",
]

_TIFF_SUFFIXES = {".tif", ".tiff"}


def open_frame_reader(source: str | os.PathLike | Sequence[str | os.PathLike]) -> FrameReader:
    """The reader for ``source``: a list of images, a folder or glob pattern of images (PNG, TIFF, BMP, JPEG), a TIFF
    file (a stack, OME or ImageJ; one page is a one-frame stack), a single PNG, BMP or JPEG, or anything else as a
    video.

    Raises :class:`FrameFileError` naming the source when it does not exist or cannot be read.
    """
    if isinstance(source, (list, tuple)):
        return ImageFolder(source)
    text = os.fspath(source)
    path = Path(text)
    if path.is_dir() or any(ch in text for ch in "*?["):
        return ImageFolder(text)
    if not path.exists():
        raise FrameFileError(f"{text}: no such file or folder")
    suffix = path.suffix.lower()
    if suffix in _TIFF_SUFFIXES:
        return TiffStack(path)
    if suffix in IMAGE_SUFFIXES:
        return ImageFolder(path)
    return VideoFile(path)

"""A folder (or glob pattern, or list) of images, one frame each, in natural order (frame2 before frame10).

PNG, TIFF and BMP keep the camera's pixels; JPEG does not (``lossy``), and a folder mixing them is lossy if any is.
Images are read with OpenCV (8- or 16-bit, grey or colour); every image must have the size and type of the first.
Natural order is natsort's path sort. An image folder declares neither a frame rate nor a pixel size.
"""

from __future__ import annotations

import glob
import math
import os
from pathlib import Path
from typing import Any, Iterator, Sequence

import cv2
from natsort import natsorted, ns

from skinstretch.drivers.errors import FrameFileError
from skinstretch.drivers.frame_readers.base import FrameReader, SourceFrame, is_colour, to_grey

__all__ = ["IMAGE_SUFFIXES", "ImageFolder"]

#: File name endings read as frames of a folder.
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")
#: Of those, the endings of lossy images.
_LOSSY_SUFFIXES = (".jpg", ".jpeg")


class ImageFolder(FrameReader):
    """The images of a folder, of a glob pattern, or of an explicit list, as frames.

    Parameters
    ----------
    source : path-like, glob pattern, or sequence of paths
        A directory (its PNG, TIFF, BMP and JPEG files, in natural order), a pattern such as
        ``"run1/frame*.png"`` (natural order), or a list of image files (taken in the order given).
    """

    kind = "image folder"

    def __init__(self, source: str | os.PathLike | Sequence[str | os.PathLike]) -> None:
        if isinstance(source, (list, tuple)):
            paths = [Path(p) for p in source]
            where = Path(paths[0]).parent if paths else Path(".")
        else:
            text = os.fspath(source)
            where = Path(text)
            if where.is_dir():
                paths = [p for p in where.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
            elif any(ch in text for ch in "*?["):
                paths = [Path(p) for p in glob.glob(text) if Path(p).suffix.lower() in IMAGE_SUFFIXES]
                where = Path(text).parent
            elif where.is_file() and where.suffix.lower() in IMAGE_SUFFIXES:
                paths = [where]
                where = where.parent
            else:
                raise FrameFileError(f"{text}: no such folder or image file")
            paths = natsorted(paths, alg=ns.PATH)
        super().__init__(where)
        if not paths:
            raise FrameFileError(f"{where}: no images found ({', '.join(IMAGE_SUFFIXES)})")
        self.paths: list[Path] = paths
        suffixes = sorted({p.suffix.lower().lstrip(".") for p in paths})
        self.compression = "/".join(suffixes)
        self.lossy = any(p.suffix.lower() in _LOSSY_SUFFIXES for p in paths)
        self.n_frames = len(paths)
        first = self._image(0)
        self.shape = first.shape
        self.dtype = first.dtype

    @property
    def name(self) -> str:
        return f"{self.path}/ ({self.n_frames} images)"

    def _image(self, k: int):
        path = self.paths[k]
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise FrameFileError(f"{path}: cannot be read as an image (corrupt, or not an image OpenCV reads)")
        if k == 0:  # the file's first image says whether it is colour
            self.colour = is_colour(image)
        return to_grey(image, channel_order="bgr", where=str(path))

    def read(self, index: int) -> SourceFrame:
        if not 0 <= index < self.n_frames:
            raise IndexError(f"{self.name}: no frame {index} (the folder holds {self.n_frames})")
        image = self._image(index)
        if image.shape != self.shape or image.dtype != self.dtype:
            raise FrameFileError(
                f"{self.paths[index]}: {image.shape[1]}x{image.shape[0]} {image.dtype} differs from the first "
                f"image {self.paths[0].name} ({self.shape[1]}x{self.shape[0]} {self.dtype})"
            )
        return SourceFrame(index, image, math.nan)

    def frames(self) -> Iterator[SourceFrame]:
        for k in range(self.n_frames):
            yield self.read(k)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "first_file": self.paths[0].name, "last_file": self.paths[-1].name}

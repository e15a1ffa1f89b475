"""Multi-page TIFF stacks, OME-TIFF and ImageJ hyperstacks through tifffile, with the rate and pixel size they declare.

The first image series of the file is read one page (one frame) at a time. Its axes other than the image's own
(Y, X and colour samples S) must reduce to one frame axis: T, Z, I, Q... of any size, every other axis of size 1.
A series whose frames are not one page each (a contiguous ImageJ hyperstack over 4 GB) is memory-mapped.

Metadata read when present (nothing else is trusted: the baseline TIFF resolution tags default to 72 dpi in most
writers and say nothing about the sample):

* OME-TIFF: ``Pixels/@PhysicalSizeX`` with its unit (micrometres by default), ``Pixels/@TimeIncrement`` with its
  unit (seconds by default), and each plane's ``DeltaT`` as the frame's time;
* ImageJ: ``finterval`` (s) or ``fps``, and the X resolution tag in pixels per ImageJ ``unit``.

Damage: tifffile reads what it can of a truncated or damaged file and logs the rest as errors (a page or tag
offset past the end of the file) instead of raising; such a file is refused here, naming what tifffile found, so
that a cut-off stack is not taken for a shorter good one.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import threading
from typing import Any, Iterator

import numpy as np
import tifffile

from skinstretch.drivers.errors import FrameFileError
from skinstretch.drivers.frame_readers.base import FrameReader, SourceFrame, is_colour, positive_or_none, to_grey

__all__ = ["TiffStack"]

#: Length units of OME and ImageJ metadata, in millimetres.
_LENGTH_MM = {
    "nm": 1e-6, "nanometer": 1e-6, "nanometre": 1e-6,
    "um": 1e-3, "µm": 1e-3, "μm": 1e-3, "micron": 1e-3, "microns": 1e-3, "micrometer": 1e-3, "micrometre": 1e-3,
    "mm": 1.0, "millimeter": 1.0, "millimetre": 1.0,
    "cm": 10.0, "centimeter": 10.0, "centimetre": 10.0,
    "m": 1000.0, "meter": 1000.0, "metre": 1000.0,
}
#: Time units of OME metadata, in seconds.
_TIME_S = {"s": 1.0, "ms": 1e-3, "µs": 1e-6, "us": 1e-6, "μs": 1e-6, "ns": 1e-9, "min": 60.0, "h": 3600.0}
_IMAGE_AXES = set("YXS")
#: TIFF compressions that change the pixels, and those that keep them (the rest, such as WebP, JPEG 2000 or JPEG XL,
#: can be either: ``lossy`` None).
_LOSSY = {"JPEG", "OJPEG", "ALT_JPEG", "JPEG_99", "JPEG_LOSSY", "JPEG_2000_LOSSY"}
_LOSSLESS = {"NONE", "LZW", "ADOBE_DEFLATE", "DEFLATE", "PACKBITS", "ZSTD", "ZSTD_DEPRECATED", "LZMA", "PNG",
             "CCITTRLE", "CCITTFAX3", "CCITTFAX4"}


class _TifffileProblems(logging.Filter):
    """Collects the error records tifffile logs while this thread opens a file (dropped from the log: the reader
    turns them into one FrameFileError); records of other threads, or outside :meth:`collecting`, pass."""

    def __init__(self) -> None:
        super().__init__()
        self._local = threading.local()

    @contextlib.contextmanager
    def collecting(self) -> Iterator[list[str]]:
        found: list[str] = []
        self._local.found = found
        try:
            yield found
        finally:
            self._local.found = None

    def filter(self, record: logging.LogRecord) -> bool:
        found = getattr(self._local, "found", None)
        if found is None:
            return True
        if record.levelno >= logging.ERROR:
            found.append(record.getMessage())
        return False


_PROBLEMS = _TifffileProblems()
logging.getLogger("tifffile").addFilter(_PROBLEMS)


class TiffStack(FrameReader):
    """The frames of a (multi-page, OME or ImageJ) TIFF file."""

    kind = "TIFF stack"

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(path)
        if not self.path.is_file():
            raise FrameFileError(f"{self.path}: no such TIFF file")
        self._fh = open(self.path, "rb")  # ours to close: tifffile leaves its handle open when it refuses a file
        try:
            with _PROBLEMS.collecting() as problems:
                try:
                    self._tif = tifffile.TiffFile(self._fh, name=self.path.name)
                    series = self._tif.series[0]
                except (tifffile.TiffFileError, OSError, ValueError, IndexError, KeyError) as exc:
                    raise FrameFileError(f"{self.path}: not a TIFF file tifffile can read ({exc})") from None
                if problems:
                    raise self._damaged(problems[0])
                self._setup(series)
        except BaseException:
            if hasattr(self, "_tif"):
                self._tif.close()
            self._fh.close()
            raise

    def _damaged(self, detail: str) -> FrameFileError:
        return FrameFileError(f"{self.path}: truncated or damaged TIFF ({detail.lstrip('<').replace('> ', ': ', 1)})")

    def _setup(self, series) -> None:
        axes, shape = series.axes, tuple(series.shape)
        self.axes = axes
        stack = [(a, n) for a, n in zip(axes, shape) if a not in _IMAGE_AXES and n > 1]
        if len(stack) > 1:
            raise FrameFileError(
                f"{self.path}: series axes {axes} of shape {shape} hold more than one stack axis "
                f"({', '.join(a for a, _ in stack)}); save one channel and one position as a plain time series"
            )
        self.frame_axis = stack[0][0] if stack else "-"
        self.n_frames = stack[0][1] if stack else 1
        page_axes = series.keyframe.axes
        self._samples_first = page_axes.startswith("S")
        self._memmap = None
        if len(series.pages) != self.n_frames or set(page_axes) - _IMAGE_AXES:
            try:  # frames spread over pages differently (a contiguous hyperstack): map the data instead
                self._memmap = tifffile.memmap(self.path, series=0, mode="r").reshape(self.n_frames, -1)
            except (ValueError, OSError) as exc:
                if series.dataoffset is not None and series.dataoffset + series.nbytes > self.path.stat().st_size:
                    raise self._damaged(f"it declares {self.n_frames} frames of {series.shape[-1]}x"
                                        f"{series.shape[-2]} but ends before their data") from None
                raise FrameFileError(
                    f"{self.path}: its {self.n_frames} frames are not one page each and cannot be memory-mapped ({exc})"
                ) from None
            self._frame_shape = tuple(n for a, n in zip(axes, shape) if a in _IMAGE_AXES)
            self._samples_first = [a for a in axes if a in _IMAGE_AXES][0] == "S"
        self._series = series
        compression = series.keyframe.compression
        self.compression = getattr(compression, "name", str(compression))
        self.lossy = True if self.compression in _LOSSY else False if self.compression in _LOSSLESS else None
        self._read_metadata()
        first = self._image(0)
        self.shape = first.shape
        self.dtype = first.dtype

    def _read_metadata(self) -> None:
        self.metadata_source = "none"
        self._times: np.ndarray | None = None
        tif = self._tif
        if tif.is_ome and tif.ome_metadata:
            pixels = _ome_pixels(tif.ome_metadata)
            size = positive_or_none(pixels.get("PhysicalSizeX"))
            unit = _LENGTH_MM.get(str(pixels.get("PhysicalSizeXUnit", "µm")).strip().lower())
            if size and unit:
                self.px_per_mm = 1.0 / (size * unit)
            step = positive_or_none(pixels.get("TimeIncrement"))
            t_unit = _TIME_S.get(str(pixels.get("TimeIncrementUnit", "s")).strip())
            if step and t_unit:
                self.fps = 1.0 / (step * t_unit)
            self._times = _ome_plane_times(pixels, self.n_frames)
            self.metadata_source = "OME"
        elif tif.is_imagej and tif.imagej_metadata:
            meta = tif.imagej_metadata
            interval = positive_or_none(meta.get("finterval"))
            self.fps = 1.0 / interval if interval else positive_or_none(meta.get("fps"))
            unit = _LENGTH_MM.get(str(meta.get("unit", "")).strip().lower().replace("\\u00b5", "µ"))
            tag = tif.pages[0].tags.get("XResolution")
            if unit and tag is not None:
                num, den = tag.value
                per_unit = positive_or_none(num / den if den else 0)
                if per_unit:
                    self.px_per_mm = per_unit / unit
            self.metadata_source = "ImageJ"

    def _image(self, k: int) -> np.ndarray:
        where = f"{self.path} frame {k}"
        try:
            if self._memmap is not None:
                raw = np.asarray(self._memmap[k]).reshape(self._frame_shape)
            else:
                raw = self._series.asarray(key=k)
        except (tifffile.TiffFileError, OSError, ValueError, IndexError, KeyError) as exc:
            raise FrameFileError(f"{where}: cannot be read ({exc})") from None
        if self._samples_first and raw.ndim == 3:
            raw = np.moveaxis(raw, 0, -1)
        if k == 0:  # the file's first image says whether it is colour
            self.colour = is_colour(raw)
        return to_grey(raw, channel_order="rgb", where=where)

    def read(self, index: int) -> SourceFrame:
        if not 0 <= index < self.n_frames:
            raise IndexError(f"{self.name}: no frame {index} (the file holds {self.n_frames})")
        image = self._image(index)
        if image.shape != self.shape:
            raise FrameFileError(f"{self.path} frame {index}: {image.shape} differs from frame 0's {self.shape}")
        if self._times is not None:
            t = float(self._times[index])
        else:
            t = index / self.fps if self.fps else math.nan
        return SourceFrame(index, image, t)

    def frames(self) -> Iterator[SourceFrame]:
        for k in range(self.n_frames):
            yield self.read(k)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "axes": self.axes, "frame_axis": self.frame_axis,
                "metadata": self.metadata_source}

    def close(self) -> None:
        super().close()
        self._memmap = None
        self._tif.close()
        self._fh.close()


def _ome_pixels(xml: str) -> dict[str, Any]:
    try:
        ome = tifffile.xml2dict(xml)["OME"]
        image = ome["Image"]
        image = image[0] if isinstance(image, list) else image
        return dict(image["Pixels"])
    except (KeyError, TypeError, IndexError, ValueError):
        return {}


def _ome_plane_times(pixels: dict[str, Any], n_frames: int) -> np.ndarray | None:
    """Each frame's ``DeltaT`` relative to the first, when every plane of the first channel and slice has one."""
    planes = pixels.get("Plane")
    if not planes:
        return None
    planes = planes if isinstance(planes, list) else [planes]
    times = {}
    for p in planes:
        if int(p.get("TheC", 0)) == 0 and int(p.get("TheZ", 0)) == 0 and "DeltaT" in p:
            scale = _TIME_S.get(str(p.get("DeltaTUnit", "s")).strip())
            if scale is None:
                return None
            times[int(p.get("TheT", 0))] = float(p["DeltaT"]) * scale
    if len(times) != n_frames or set(times) != set(range(n_frames)):
        return None
    t = np.array([times[k] for k in range(n_frames)])
    return t - t[0] if np.all(np.isfinite(t)) else None

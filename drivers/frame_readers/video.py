"""Video files (AVI, MP4, MOV, MKV and every other container and codec FFmpeg reads) through PyAV.

PyAV rather than OpenCV's FFmpeg backend: it gives each frame's own presentation time (so a variable-rate or
dropped-frame video keeps its real timing), the frame count the container declares (OpenCV estimates it from the
duration), grey or 16-bit grey straight from FFmpeg's converter without a colour round trip, and FFmpeg's own
error for a damaged file. Its wheels bundle FFmpeg, so nothing is needed from the system.
"""

from __future__ import annotations

import math
import os
from typing import Any, Iterator

import av
import numpy as np

from skinstretch.drivers.errors import FrameFileError
from skinstretch.drivers.frame_readers.base import FrameReader, SourceFrame, positive_or_none

__all__ = ["VideoFile"]


class VideoFile(FrameReader):
    """The first video stream of a file, decoded one frame at a time.

    ``fps`` is the stream's average frame rate, ``n_frames`` the count its container declares (None when it
    declares none, as Matroska does); frame times come from each frame's presentation time stamp. A video of
    more than 8 bits per sample is read as uint16 grey, any other as uint8 (see the grey rule in
    :mod:`skinstretch.drivers.frame_readers.base`). A file that FFmpeg cannot open or decode, or that ends before
    the frame count its container declares, raises :class:`FrameFileError` naming it.
    """

    kind = "video"

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(path)
        if not self.path.is_file():
            raise FrameFileError(f"{self.path}: no such video file")
        with self._open() as container:
            stream = container.streams.video[0]
            self.codec = stream.codec_context.name
            self.compression, self.lossy = _compression(stream.codec_context)
            self.container_format = container.format.name
            fmt = stream.codec_context.format
            bits = max((c.bits for c in fmt.components), default=8) if fmt is not None else 8
            self._pixel_format = "gray16le" if bits > 8 else "gray"
            self.dtype = np.dtype(np.uint16 if bits > 8 else np.uint8)
            self.source_pixel_format = fmt.name if fmt is not None else "unknown"
            self.colour = fmt is not None and len(fmt.components) >= 3  # YUV or RGB; grey has one (two with alpha)
            self.fps = positive_or_none(stream.average_rate) or positive_or_none(stream.guessed_rate)
            self.n_frames = int(stream.frames) if stream.frames and stream.frames > 0 else None
        frames = self.frames()
        first = next(frames, None)
        frames.close()
        if first is None:
            raise FrameFileError(f"{self.path}: the video holds no frame that can be decoded")
        self.shape = first.image.shape

    def _open(self):
        try:
            container = av.open(str(self.path), mode="r")
        except (av.FFmpegError, OSError, UnicodeDecodeError) as exc:
            raise FrameFileError(f"{self.path}: not a video FFmpeg can read ({_reason(exc)})") from None
        if not container.streams.video:
            container.close()
            raise FrameFileError(f"{self.path}: the file holds no video stream")
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"  # FFmpeg decodes on its own threads; frames still come out in order
        return container

    def frames(self) -> Iterator[SourceFrame]:
        container = self._open()
        try:
            stream = container.streams.video[0]
            t0 = None
            k = 0
            decoded = container.decode(stream)
            while True:
                try:
                    frame = next(decoded)
                except StopIteration:
                    break
                except av.FFmpegError as exc:
                    raise FrameFileError(f"{self.path}: frame {k} cannot be decoded ({_reason(exc)})") from None
                t = frame.time
                if t is not None and t0 is None:
                    t0 = t
                time_s = float(t - t0) if t is not None and t0 is not None else math.nan
                yield SourceFrame(k, frame.to_ndarray(format=self._pixel_format), time_s)
                k += 1
            if self.n_frames is not None and k < self.n_frames:
                raise FrameFileError(
                    f"{self.path}: the video ends after {k} of the {self.n_frames} frames its container declares "
                    "(truncated or damaged)"
                )
        finally:
            container.close()

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "container": self.container_format, "codec": self.codec,
                "pixel_format": self.source_pixel_format}


#: The H.264 profile x264's lossless mode writes (its transform bypass exists only there): any other profile is lossy.
_H264_LOSSLESS_PROFILE = "High 4:4:4 Predictive"
#: Codecs with a lossless mode that FFmpeg's descriptor does not mark (libvpx-vp9 ``-lossless 1``).
_ALSO_LOSSLESS = {"vp9"}


def _compression(context) -> tuple[str, bool | None]:
    """(codec and profile by name, whether it is lossy) from FFmpeg's codec descriptor: a codec that is only lossless
    (FFV1, raw, HuffYUV...) or only lossy (MJPEG, MPEG-4 part 2, ProRes...) says so; one with both modes (H.264,
    HEVC, AV1, VP9) is lossy unless the stream can be in its lossless mode, which only H.264's profile reveals."""
    profile = context.profile or ""
    name = f"{context.name} ({profile})" if profile else context.name
    codec = context.codec
    if codec.lossless and not codec.lossy:
        return name, False
    if codec.lossy and not codec.lossless and context.name not in _ALSO_LOSSLESS:
        return name, True
    if context.name == "h264" and profile and profile != _H264_LOSSLESS_PROFILE:
        return name, True
    return name, None


def _reason(exc: BaseException) -> str:
    text = getattr(exc, "strerror", None) or str(exc)
    return " ".join(str(text).split())

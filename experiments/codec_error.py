"""A lossy video's displacement error, measured on the clip's own frame: the codec term of the predicted errors.

A codec's error follows the motion from frame to frame, so a registration's residual shows little of it, and how
large it is depends on the codec, its quality setting, the pixel scale and the ridge contrast. It is measured here
rather than assumed: one decoded frame of the file is moved by known sub-pixel steps (not half or quarter pixels,
which a codec's motion compensation reproduces exactly), encoded again with the file's codec at the file's quality
(x264's or x265's ``crf`` or ``qp`` as their headers record them, else a quantiser matched on a key frame's size,
else the stream's bit rate), decoded, and registered pair by pair with the dense flow. The codec's error per axis
is what the encoding adds to the registration's error on the same frames uncompressed. A second generation of
compression errs about as much as the first or more (docs/tuning-log.md), so the term is seldom too small.
Hand-written: no library measures a codec's displacement error.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

__all__ = ["CodecError", "EncoderSettings", "measure_codec_error", "encoder_settings"]

log = logging.getLogger(__name__)

#: Sub-pixel steps per frame (px, x and y) of the two probe clips.
_STEPS = ((0.37, 0.23), (0.13, 0.29))
#: Frames per probe clip (the first is the codec's key frame).
_FRAMES = 12
#: Largest probe frame (px, rows and columns): the middle of a larger frame is used.
_MAX_SIDE = (480, 640)
#: Decoder name -> encoder for the codecs PyAV's FFmpeg can write again.
_ENCODERS = {"h264": "libx264", "hevc": "libx265", "mpeg4": "mpeg4", "vp9": "libvpx-vp9", "mjpeg": "mjpeg",
             "mpeg2video": "mpeg2video", "av1": "libsvtav1"}
#: Codecs with one quantiser scale (lowest, highest + 1) whose quality a key frame's size gives away.
_QUANTISER_SCALE = {"mpeg4": (1, 32), "mpeg2video": (1, 32), "mpeg1video": (1, 32), "msmpeg4": (1, 32),
                    "mjpeg": (1, 32), "h263": (1, 32)}
#: Packets searched for a second key frame.
_KEY_FRAME_SEARCH = 600
#: The options header x264 and x265 write into the stream (its rate control and quality).
_HEADERS = {"libx264": rb"x264 - core \d+.*?options: ([^\x00]*)",
            "libx265": rb"x265 \(build[^\x00]*?options: ([^\x00]*)"}
#: Bytes of the file searched for x264's or x265's header (it sits in the first frame).
_HEADER_BYTES = 1 << 20


@dataclass(frozen=True)
class CodecError:
    """The codec's displacement error per axis ``sigma_px`` (px), the part of it that points a registration window
    apart do not share (``independent_px``: what strain sees; the rest moves neighbours alike and cancels), how it
    was measured (``how``: encoder and setting) and on how many registered points (``n_points``)."""

    sigma_px: float
    independent_px: float
    how: str
    n_points: int

    def to_dict(self) -> dict:
        return {"sigma_px": self.sigma_px, "independent_px": self.independent_px, "how": self.how,
                "n_points": self.n_points}

    @property
    def shared_px(self) -> float:
        """The part neighbouring points share (px per axis)."""
        return math.sqrt(max(self.sigma_px**2 - self.independent_px**2, 0.0))


@dataclass(frozen=True)
class EncoderSettings:
    """How to encode again like a video file did: ``encoder``, its ``options`` (x264's or x265's ``crf`` or ``qp``),
    else a fixed ``quantizer`` (codecs with one quantiser scale, matched on a key frame of the file), else the
    stream's ``bit_rate`` (bit/s); ``pix_fmt`` the file's."""

    encoder: str
    options: dict[str, str]
    quantizer: int | None
    bit_rate: int | None
    pix_fmt: str

    def describe(self) -> str:
        if self.options:
            return ", ".join(f"{k} {v}" for k, v in self.options.items())
        if self.quantizer is not None:
            return f"quantiser {self.quantizer} (from a key frame's size)"
        return f"{self.bit_rate / 1e6:.2f} Mbit/s" if self.bit_rate else "its defaults"


def encoder_settings(path: str | Path) -> EncoderSettings:
    """The settings that re-encode like the video file ``path`` did; LookupError when no encoder of its codec is
    available here."""
    import av  # noqa: PLC0415

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        name, pix_fmt = stream.codec_context.name, stream.codec_context.pix_fmt or "yuv420p"
        bit_rate = stream.bit_rate or container.bit_rate or None
    encoder = _ENCODERS.get(name, name)
    try:
        av.codec.Codec(encoder, "w")
    except (av.FFmpegError, ValueError) as exc:
        raise LookupError(f"no encoder for {name} here ({exc})") from None
    options: dict[str, str] = {}
    if encoder in _HEADERS:
        with open(path, "rb") as f:
            header = re.search(_HEADERS[encoder], f.read(_HEADER_BYTES), re.S)
        if header:
            found = dict(re.findall(r"(?:^| )([\w-]+)=(\S+)", header.group(1).decode("ascii", "replace")))
            if found.get("rc") == "crf" and "crf" in found:
                options = {"crf": found["crf"]}
            elif found.get("rc") == "cqp" and "qp" in found:
                options = {"qp": found["qp"]}
    quantizer = _key_frame_quantizer(path, encoder, pix_fmt) if encoder in _QUANTISER_SCALE else None
    return EncoderSettings(encoder, options, quantizer, None if options or quantizer else bit_rate, pix_fmt)


def _key_frame_quantizer(path: str | Path, encoder: str, pix_fmt: str) -> int | None:
    """The quantiser scale at which a key frame of the file, encoded again on its own, takes as many bytes as in the
    file: the second key frame where there is one (a rate control starts coarse on the first), else the first."""
    import av  # noqa: PLC0415

    image, size = None, 0
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        for k, packet in enumerate(container.demux(stream)):
            if packet.size and packet.is_keyframe:
                frames = packet.decode()
                if frames:
                    image, size = frames[0].to_ndarray(format="gray"), packet.size
                if image is not None and k > 0:
                    break
            if k >= _KEY_FRAME_SEARCH:
                break
    if image is None:
        return None
    image = image[: image.shape[0] // 2 * 2, : image.shape[1] // 2 * 2]
    best, best_gap = None, math.inf
    for q in range(*_QUANTISER_SCALE[encoder]):
        context = av.CodecContext.create(encoder, "w")
        context.width, context.height, context.pix_fmt = image.shape[1], image.shape[0], pix_fmt
        context.time_base = Fraction(1, 60)
        context.qmin = context.qmax = q
        packets = context.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="gray"))
        packets += context.encode(None)
        gap = abs(math.log(max(sum(p.size for p in packets), 1) / size))
        if gap < best_gap:
            best, best_gap = q, gap
    return best


def _encode_decode(frames: np.ndarray, settings: EncoderSettings, path: Path) -> np.ndarray:
    import av  # noqa: PLC0415

    with av.open(str(path), "w") as container:
        stream = container.add_stream(settings.encoder, rate=60)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = settings.pix_fmt
        stream.options = {**settings.options, **({"x265-params": "log-level=error"} if settings.encoder == "libx265"
                                                 else {})}
        if settings.quantizer is not None:
            stream.codec_context.qmin = stream.codec_context.qmax = settings.quantizer
        elif settings.bit_rate:
            stream.bit_rate = int(settings.bit_rate)
        for f in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="gray")))
        container.mux(stream.encode())
    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="gray") for f in container.decode(video=0)])


def _pair_errors(frames: np.ndarray, step: np.ndarray, flow) -> tuple[np.ndarray, np.ndarray]:
    """Every valid node's displacement error (n, 2) px over the clip's consecutive pairs, and the differences (m, 2)
    of the errors of valid nodes a window apart (no shared pixels), along rows and columns."""
    points, differences = [], []
    apart = max(1, math.ceil(flow.window_px / flow.grid_step_px))
    for k in range(len(frames) - 1):
        field = flow.compute(frames[k], frames[k + 1], frame_a=k, frame_b=k + 1)
        error = np.where(field.valid[..., None], field.displacement - step, np.nan)
        points.append(error[field.valid])
        for d in (error[:, apart:] - error[:, :-apart], error[apart:] - error[:-apart]):
            differences.append(d[np.isfinite(d).all(axis=-1)])
    return np.concatenate(points), np.concatenate(differences)


def measure_codec_error(path: str | Path, frame: np.ndarray, *, px_per_mm: float, workdir: str | Path
                        ) -> CodecError | None:
    """The codec error of the video file ``path`` measured on ``frame`` (one of its decoded frames, 8-bit grey, at
    ``px_per_mm``), with scratch files in ``workdir``; None (with a log line) when it cannot be measured: no
    encoder for the codec, or no fingerprint texture the flow registers in the frame."""
    from scipy.ndimage import shift  # noqa: PLC0415

    from skinstretch.processing.flow import DenseFlow  # noqa: PLC0415
    from skinstretch.processing.pixel_scale import Calibration  # noqa: PLC0415

    try:
        settings = encoder_settings(path)
    except LookupError as exc:
        log.info("%s: the codec's error is not measured: %s", Path(path).name, exc)
        return None
    image = np.asarray(frame)
    if image.dtype != np.uint8 or image.ndim != 2:
        log.info("%s: the codec's error is not measured on %s frames", Path(path).name, image.dtype)
        return None
    h, w = (min(s, m) // 2 * 2 for s, m in zip(image.shape, _MAX_SIDE))  # even sides: chroma subsampling
    y0, x0 = (image.shape[0] - h) // 2, (image.shape[1] - w) // 2
    still = image[y0:y0 + h, x0:x0 + w].astype(np.float32)
    flow = DenseFlow(calibration=Calibration(px_per_mm=px_per_mm))
    workdir = Path(workdir)
    lossless, lossy = [], []
    try:
        for i, step in enumerate(np.asarray(_STEPS)):
            clip = np.stack([np.clip(np.rint(shift(still, (k * step[1], k * step[0]), order=3, mode="reflect")),
                                     0, 255).astype(np.uint8) for k in range(_FRAMES)])
            lossless.append(_pair_errors(clip, step, flow))
            decoded = _encode_decode(clip, settings, workdir / f"codec-probe-{i}.mkv")
            lossy.append(_pair_errors(decoded, step, flow))
    except Exception as exc:  # noqa: BLE001 - an encoder's or the registration's failure leaves the fixed term
        log.info("%s: the codec's error is not measured: %s: %s", Path(path).name, type(exc).__name__, exc)
        return None
    finally:
        for f in workdir.glob("codec-probe-*.mkv"):
            f.unlink(missing_ok=True)
    (a, da), (b, db) = ((np.concatenate([x[0] for x in r]), np.concatenate([x[1] for x in r]))
                        for r in (lossless, lossy))
    if min(len(a), len(b), len(da), len(db)) < 10:
        log.info("%s: the codec's error is not measured: too little texture in the middle frame", Path(path).name)
        return None
    sigma = math.sqrt(max(float(np.mean(b**2) - np.mean(a**2)), 0.0))  # per axis, the encoding's share
    # a difference of two independent errors has twice their variance; what the points share cancels in it
    independent = min(sigma, math.sqrt(max(float(np.mean(db**2) - np.mean(da**2)) / 2.0, 0.0)))
    return CodecError(sigma_px=sigma, independent_px=independent,
                      how=f"{settings.encoder} at {settings.describe()} on the middle frame moved by known sub-pixel "
                          f"steps ({len(b)} points)", n_points=int(len(b)))

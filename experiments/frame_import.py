"""A video, TIFF stack or folder of images made into a normal session file (``skinstretch import``).

The frames are read one at a time by the readers the replay camera uses (:mod:`skinstretch.drivers.frame_readers`)
and written as they come, so a file of any length imports in constant memory. The session is written under a
temporary name beside the output and renamed only once complete: a failure (a damaged frame, a full disk,
Ctrl-C) leaves no file at the output name. The result is an ordinary session (status complete) that ``analyze``,
``report`` and ``view`` read like a recorded one; its metadata ``source`` says where it came from and how it was
converted (docs/import-and-replay.md).

Rules
-----
* **Grey**: colour becomes BT.601 luma (:mod:`skinstretch.drivers.frame_readers.base`).
* **Bit depth**: 8-bit frames are stored unchanged. Deeper ones (16-bit, 32-bit, float) are mapped by one linear
  map for the whole file, from the smallest to the largest value of any (cropped) frame onto 0..255, rounded to
  the nearest level: all 256 levels are used and brightness changes between frames survive (a per-frame
  stretch would fake them). Finding the range takes a first pass over the file.
* **Time**: ``fps`` given: frame k is at k / fps. Otherwise each frame's own time in the file (a video's
  presentation time stamps, OME plane times), else k over the rate the file declares; a file that declares no
  rate (an image folder) needs ``fps``. Times are seconds after the first frame.
* **Pixel scale**: ``px_per_mm`` given, else ``calibration`` (a fitted mapping, cut to the crop), else the pixel
  size the file declares (OME, ImageJ); a file that declares none needs one of the two.
* **Surface**: ``surface`` given, else read from the frames as they are written
  (:mod:`skinstretch.processing.surface_detection`: flat, ridge or valley), recorded with how it was decided.
* **Lossy video**: the codec's displacement error is measured on the clip's middle frame
  (:mod:`skinstretch.experiments.codec_error`) and recorded as ``source.codec_error``; the analysis' predicted
  errors include it.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from skinstretch import __version__
from skinstretch.drivers.camera_modes import CameraMode
from skinstretch.drivers.frame_readers import FrameReader, SourceFrame, open_frame_reader
from skinstretch.drivers.frame_readers.video import VideoFile
from skinstretch.drivers.session_file import SessionWriter, replacing_file, write_metadata
from skinstretch.experiments.codec_error import measure_codec_error
from skinstretch.experiments.output_paths import REPLACE_IT, check_output_file
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError, Remedy
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.surface_detection import ContrastAccumulator, SurfaceEvidence
from skinstretch.processing.texture_gate import PLAUSIBLE_RIDGE_PERIOD_MM, ridge_period_mm
from skinstretch.progress import progress_bar

if TYPE_CHECKING:
    from skinstretch.processing.geometric_calibration import GridMapping

__all__ = ["Crop", "ImportResult", "import_frames", "IMPORTED_MODE_NAME"]

log = logging.getLogger(__name__)

#: Camera-mode name of an imported session (its size and rate are the file's).
IMPORTED_MODE_NAME = "imported"
_BATCH = 16  # frames per write at most: one resize of each dataset per batch
_BATCH_BYTES = 24 << 20  # and at most this much (large frames: 4000x3000 ones go two by two)
_PERIOD_WINDOW = 1024  # px: the part of the middle frame whose ridge period is checked (8 mm at 128 px/mm)
_SURFACE_FRAMES = 240  # frames of a long file the surface detection averages (evenly spread)


@dataclass(frozen=True)
class Crop:
    """A window of the source frames in pixels: left column ``x``, top row ``y``, ``width`` and ``height``."""

    x: int
    y: int
    width: int
    height: int

    @classmethod
    def parse(cls, text: str) -> "Crop":
        """``"X,Y,W,H"`` (integers)."""
        try:
            x, y, w, h = (int(v) for v in text.split(","))
        except ValueError:
            raise InvalidInputError(f"crop must be X,Y,W,H in whole pixels, got {text!r}") from None
        return cls(x, y, w, h)

    def check(self, shape: tuple[int, int], where: str) -> None:
        h, w = shape
        if self.width < 1 or self.height < 1 or self.x < 0 or self.y < 0 or self.x + self.width > w or \
                self.y + self.height > h:
            raise InvalidInputError(
                f"crop must lie inside the {w}x{h} frames of {where}, got {self.x},{self.y},{self.width},{self.height}"
            )

    def apply(self, image: np.ndarray) -> np.ndarray:
        return image[self.y : self.y + self.height, self.x : self.x + self.width]


@dataclass(frozen=True)
class ImportResult:
    """What an import wrote.

    Attributes
    ----------
    path : Path
        The session file.
    n_frames, width, height : int
        Frames written and their size.
    fps : float
        The session's nominal frame rate (Hz); ``fps_source`` says where it came from.
    px_per_mm : float
        Pixel scale; ``px_per_mm_source`` says where it came from.
    conversion : str
        How the pixels became 8-bit grey.
    surface : str or None
        The session's surface (None: not given and not readable from the frames); ``surface_source`` says how it
        was decided.
    seconds : float
        Wall time of the import.
    """

    path: Path
    n_frames: int
    width: int
    height: int
    fps: float
    fps_source: str
    px_per_mm: float
    px_per_mm_source: str
    conversion: str
    surface: str | None
    surface_source: str
    seconds: float


@dataclass(frozen=True)
class _DepthMap:
    """The linear map of deep pixels onto 0..255 (identity for 8-bit input)."""

    lo: float
    hi: float
    identity: bool

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if self.identity:
            return np.ascontiguousarray(image)
        scale = 255.0 / (self.hi - self.lo) if self.hi > self.lo else 0.0
        out = (image.astype(np.float32) - np.float32(self.lo)) * np.float32(scale)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)

    def describe(self, dtype: np.dtype, *, colour: bool) -> str:
        grey = "colour to grey by the luma rule (BT.601), " if colour else ""
        if self.identity:
            return f"{grey}8-bit, unchanged" if colour else "8-bit grey, unchanged"
        return f"{grey}{dtype} mapped linearly from [{self.lo:g}, {self.hi:g}] (the whole file's range) to [0, 255]"


def _depth_map(reader: FrameReader, crop: Crop | None, progress: bool) -> _DepthMap:
    if reader.dtype == np.uint8:
        return _DepthMap(0.0, 255.0, True)
    lo, hi = math.inf, -math.inf
    with progress_bar(reader.n_frames, enabled=progress, desc="range of values") as bar:
        for frame in reader.frames():
            image = crop.apply(frame.image) if crop else frame.image
            finite = image[np.isfinite(image)] if image.dtype.kind == "f" else image
            if finite.size:
                lo, hi = min(lo, float(finite.min())), max(hi, float(finite.max()))
            bar.update(1)
    if not math.isfinite(lo):
        raise InvalidInputError(f"{reader.name}: no finite pixel value in any frame")
    return _DepthMap(lo, hi, False)


def _scale(reader: FrameReader, *, px_per_mm: float | None, calibration: GridMapping | None,
           crop: Crop | None) -> tuple[Calibration, str]:
    if px_per_mm is not None and calibration is not None:
        raise InvalidInputError("give a pixel scale or a calibration, not both")
    if px_per_mm is not None:
        if not (math.isfinite(px_per_mm) and px_per_mm > 0):
            raise InvalidInputError(f"px_per_mm must be a positive number, got {px_per_mm!r}")
        return Calibration(px_per_mm=float(px_per_mm)), "given"
    if calibration is not None:
        from skinstretch.experiments.skin_mapping_step import mapping_for_frames  # noqa: PLC0415

        h, w = reader.shape
        if crop is not None:
            if (calibration.width, calibration.height) != (w, h):
                raise InvalidInputError(
                    f"the calibration was fitted on {calibration.width}x{calibration.height} images and {reader.name} "
                    f"is {w}x{h}: a crop needs a calibration of the uncropped frames"
                )
            mapping = calibration.for_window(x0=crop.x, y0=crop.y, width=crop.width, height=crop.height)
        else:
            mapping = mapping_for_frames(calibration, w, h)
        return Calibration(px_per_mm=mapping.px_per_mm, mapping=mapping), "calibration"
    if reader.px_per_mm is not None:
        return Calibration(px_per_mm=reader.px_per_mm), f"{reader.kind} metadata"
    raise InvalidInputError(
        f"{reader.name} declares no pixel size",
        remedy=Remedy(("px_per_mm", "calibration"), "to give the pixel scale"),
    )


def _timed(reader: FrameReader, fps: float | None) -> tuple[Iterator[tuple[SourceFrame, float]], float | None, str]:
    """Each frame with its time (s), the nominal rate when known before reading, and where times come from."""
    if fps is not None:
        if not (math.isfinite(fps) and fps > 0):
            raise InvalidInputError(f"fps must be a positive number, got {fps!r}")
        return ((f, f.index / fps) for f in reader.frames()), float(fps), "given"
    if reader.fps is None and not math.isfinite(reader.read(0).time_s):
        raise InvalidInputError(f"{reader.name} declares no frame rate", remedy=Remedy(("fps",), "to give it"))

    def file_times() -> Iterator[tuple[SourceFrame, float]]:
        for f in reader.frames():
            if math.isfinite(f.time_s):
                yield f, f.time_s
            elif reader.fps is not None:
                yield f, f.index / reader.fps
            else:
                raise InvalidInputError(f"{reader.name} gives frame {f.index} no time and declares no frame rate",
                                        remedy=Remedy(("fps",), "to give it"))

    return file_times(), reader.fps, f"{reader.kind} time stamps"


def import_frames(
    source: str | os.PathLike | Sequence[str | os.PathLike],
    output: str | os.PathLike,
    *,
    px_per_mm: float | None = None,
    calibration: GridMapping | None = None,
    fps: float | None = None,
    crop: Crop | None = None,
    surface: str | None = None,
    overwrite: bool = False,
    progress: bool = False,
) -> ImportResult:
    """Import a video, TIFF stack or image folder into the session file ``output`` (see the module's rules).

    Parameters
    ----------
    source : path-like, glob pattern or list of paths
        A video file, a TIFF file, a folder or pattern of PNG/TIFF/BMP/JPEG images, or a list of images.
    output : path-like
        Session file to write; an existing one is replaced only with ``overwrite``.
    px_per_mm, calibration : optional
        Pixel scale, or a fitted calibration mapping (:class:`GridMapping` of ``skinstretch calibrate``).
    fps : float, optional
        Frame rate in Hz; replaces the file's own times.
    crop : Crop, optional
        Window of the frames to keep.
    surface : str, optional
        What the finger slid on ("flat", "ridge", "valley"...): recorded as the session's ``surface`` (the
        analysis removes the glass shading of non-flat surfaces). None: read from the frames
        (:func:`~skinstretch.processing.surface_detection.detect_surface`), recorded with the evidence.

    Raises
    ------
    FrameFileError
        The source is missing, corrupt, truncated or of a kind no reader reads (nothing is left at ``output``).
    InvalidInputError
        A bad option, or a rate or pixel scale the file does not declare and the caller did not give.
    """
    t_start = time.perf_counter()
    # before the source is read: an output that cannot be written is named (not the hidden file written first)
    output = check_output_file(output, overwrite=overwrite, remedy=REPLACE_IT)
    with open_frame_reader(source) as reader:
        if crop is not None:
            crop.check(reader.shape, reader.name)
        height, width = (crop.height, crop.width) if crop is not None else reader.shape
        cal, scale_source = _scale(reader, px_per_mm=px_per_mm, calibration=calibration, crop=crop)
        frames, nominal_fps, time_source = _timed(reader, fps)
        if nominal_fps is None:  # times from the file and no declared rate: derived once they are known
            nominal_fps = 1.0
        depth = _depth_map(reader, crop, progress)
        conversion = depth.describe(reader.dtype, colour=reader.colour)
        source_record: dict[str, Any] = {
            **reader.describe(),
            "times": time_source,
            "px_per_mm": scale_source,
            "conversion": conversion,
            "crop": [crop.x, crop.y, crop.width, crop.height] if crop is not None else None,
        }
        _say_if_lossy(reader)
        metadata: dict[str, Any] = {"source": source_record, "imported_by": f"skinstretch {__version__}",
                                    "imported_unix": time.time()}
        if surface:
            metadata["surface"] = {"kind": surface, "decided_by": "given"}
        contrast = None if surface else ContrastAccumulator(px_per_mm=cal.px_per_mm)
        mode = CameraMode(IMPORTED_MODE_NAME, width, height, nominal_fps)
        with replacing_file(output, overwrite=overwrite) as tmp:
            writer = SessionWriter(tmp, camera_mode=mode, calibration=cal, metadata=metadata, flush_interval_s=1.0)
            try:
                n, times, sample = _write_frames(writer, frames, crop=crop, depth=depth, total=reader.n_frames,
                                                 progress=progress, where=reader.name, contrast=contrast)
                writer.close()
            except BaseException as exc:
                writer.fail(f"import stopped: {type(exc).__name__}: {exc}")
                raise
            fps_out, fps_source = _nominal_rate(fps, reader.fps, times, time_source)
            if fps_out != nominal_fps:
                _set_rate(tmp, fps_out)
            source_record["ridge_period_mm"] = _checked_ridge_period(sample, cal.px_per_mm, reader.name,
                                                                     scale_source)
            if reader.lossy and isinstance(reader, VideoFile) and sample is not None:
                source_record["codec_error"] = _codec_error(reader, sample, cal.px_per_mm)
            if contrast is not None:
                metadata["surface"] = _detected_surface(contrast, reader.name)
            else:
                log.info("surface %s (given by --surface)", surface)
            write_metadata(tmp, metadata)
    seconds = time.perf_counter() - t_start
    log.debug("imported %d frames of %s into %s in %.1f s (%s)", n, reader.name, output, seconds, conversion)
    return ImportResult(path=output, n_frames=n, width=width, height=height, fps=fps_out, fps_source=fps_source,
                        px_per_mm=cal.px_per_mm, px_per_mm_source=scale_source, conversion=conversion,
                        surface=metadata["surface"]["kind"], surface_source=metadata["surface"]["decided_by"],
                        seconds=seconds)


def _codec_error(reader: VideoFile, sample: np.ndarray, px_per_mm: float) -> dict | None:
    """The lossy codec's displacement error measured on the clip's middle frame (:mod:`..codec_error`), logged; the
    analysis includes it in its predicted errors. None when it cannot be measured."""
    with tempfile.TemporaryDirectory(prefix="skinstretch-codec-") as scratch:
        found = measure_codec_error(reader.path, sample, px_per_mm=px_per_mm, workdir=scratch)
    if found is None:
        return None
    log.info("%s: the codec's displacement error is %.3f px per axis (%s); the analysis' predicted errors include "
             "it", reader.name, found.sigma_px, found.how)
    return found.to_dict()


def _say_if_lossy(reader: FrameReader) -> None:
    """One line, before anything is written, when the file's compression changed (or may have changed) the pixels:
    what is measured from such frames departs from what the camera's own frames give (the `import` bench)."""
    if reader.lossy:
        log.warning("%s: %s is lossy compression: the frames are not the camera's, and motion measured from them "
                    "departs from a lossless recording's (docs/import-and-replay.md, Accuracy); keep lossless video "
                    "(FFV1) or TIFF for measurement", reader.name, reader.compression)
    elif reader.lossy is None:
        log.info("%s: %s can be lossy or lossless and the file does not say which; if lossy, motion measured from "
                 "the frames departs from a lossless recording's (docs/import-and-replay.md, Accuracy)",
                 reader.name, reader.compression)


def _checked_ridge_period(sample: np.ndarray | None, px_per_mm: float, where: str, scale_source: str) -> float | None:
    """The ridge period of the clip's middle frame at the session's scale (mm; None when not measurable), with a
    warning when no fingertip has it: a wrong pixel scale (a guessed ``--px-per-mm``) would otherwise surface only
    as frames the analysis refuses as out of focus or without texture."""
    if sample is None or min(sample.shape) < 32:
        return None
    # the middle of a large frame tells as well: a whole 4000x3000 one took 0.7 GB, the import's peak memory
    h, w = sample.shape
    cut = sample[max(0, h // 2 - _PERIOD_WINDOW // 2):][:_PERIOD_WINDOW, max(0, w // 2 - _PERIOD_WINDOW // 2):]
    period = ridge_period_mm(cut[:, :_PERIOD_WINDOW], px_per_mm=px_per_mm)
    if not np.isfinite(period):
        return None
    lo, hi = PLAUSIBLE_RIDGE_PERIOD_MM
    if not lo <= period <= hi:
        log.warning("%s: the ridges repeat every %.2f mm at %.4g px/mm (%s), a fingertip's every 0.39-0.46 mm: is "
                    "the pixel scale right (--px-per-mm, --calibration)? Or is there no fingerprint in the frames?",
                    where, period, px_per_mm, scale_source)
    return round(period, 4)


def _detected_surface(contrast: ContrastAccumulator, where: str) -> dict[str, Any]:
    """The session's ``surface`` record read from the frames, logged in one line."""
    try:
        evidence: SurfaceEvidence = contrast.result()
    except InsufficientDataError as exc:
        log.info("surface not detected in %s (%s); analysed as flat unless --surface gives it", where, exc)
        return {"kind": None, "decided_by": f"not detected: {exc}"}
    log.info("surface detected in %s: %s (--surface overrides)", where, evidence.describe())
    return {"kind": evidence.kind, "decided_by": "detected from the frames",
            "detection": {"rule": "skinstretch.processing.surface_detection", **evidence.to_dict()}}


def _write_frames(writer: SessionWriter, frames, *, crop: Crop | None, depth: _DepthMap, total: int | None,
                  progress: bool, where: str, contrast: ContrastAccumulator | None = None,
                  ) -> tuple[int, np.ndarray, np.ndarray | None]:
    """Write every frame in batches, adding every ``stride``-th to ``contrast`` (the surface detection: at most
    ~:data:`_SURFACE_FRAMES` frames of a long file); returns the count, every frame's time and the middle frame
    (the first when the count is not declared)."""
    stride = max(1, (total or 0) // _SURFACE_FRAMES)
    middle = (total or 0) // 2
    sample = None
    times: list[float] = []
    batch: list[np.ndarray] = []
    batch_t: list[float] = []

    def flush() -> None:
        if batch:
            k = len(times) - len(batch)
            ts = np.asarray(batch_t)
            writer.append_frames(np.stack(batch), timestamps=ts, device_timestamps=ts,
                                 frame_ids=np.arange(k, k + len(batch)))
            batch.clear()
            batch_t.clear()

    with progress_bar(total, enabled=progress, desc="importing") as bar:
        for frame, t in frames:
            image = depth(crop.apply(frame.image) if crop is not None else frame.image)
            if len(times) == middle:
                sample = image
            if contrast is not None and len(times) % stride == 0:
                contrast.add(image)
            batch.append(image)
            batch_t.append(t)
            times.append(t)
            if len(batch) >= min(_BATCH, max(1, _BATCH_BYTES // image.nbytes)):
                flush()
            bar.update(1)
        flush()
    if not times:
        raise InvalidInputError(f"{where} holds no frame")
    return len(times), np.asarray(times), sample


def _nominal_rate(given: float | None, declared: float | None, times: np.ndarray, source: str) -> tuple[float, str]:
    if given is not None:
        return float(given), "given"
    if declared is not None:
        return float(declared), source.replace("time stamps", "metadata")
    span = float(times[-1] - times[0]) if times.size > 1 else 0.0
    if span > 0:
        return (times.size - 1) / span, source
    raise InvalidInputError("the file's frame times do not advance", remedy=Remedy(("fps",), "to give the rate"))


def _set_rate(path: Path, fps: float) -> None:
    import h5py  # noqa: PLC0415

    with h5py.File(path, "r+") as f:
        f["camera"].attrs["fps"] = fps

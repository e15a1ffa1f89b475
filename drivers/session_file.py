"""The session file: one HDF5 file per recorded or simulated trial (format documented in docs/session-format.md).

Everything in skinstretch reads and writes sessions through this module: the scene simulator, the recorder, the
replay camera and the analysis. Datasets are created up front (resizable along time) so that a recorder can
write in HDF5 SWMR mode, which survives a SIGKILL with nothing lost (see shared FACTS: recording crash test).

Writing
-------
* :class:`SessionWriter` streams frames (and optional sample streams such as force or display feedback) into a
  file in SWMR mode, flushing at least every ``flush_interval_s``.
* :func:`write_session` writes a whole in-memory session at once (the scene simulator uses it).

A full disk (:mod:`skinstretch.drivers.disk_space`): :func:`expected_session_bytes` says what a recording needs
before it starts; a :class:`SessionWriter` keeps a few MB in reserve and checks the free space before every
write, stops with :class:`~skinstretch.drivers.errors.DiskFullError` before HDF5 could meet ENOSPC (which it does
not survive), and then closes the file marked failed, every frame written so far readable.

Reading
-------
:func:`open_session` returns a :class:`Session`; anything that is not a readable skinstretch session raises
:class:`skinstretch.drivers.errors.SessionFileError` with a message naming the file and what is wrong.

Files that explain themselves
-----------------------------
Every dataset is written with ``units``, a ``description``, named axes (HDF5 dimension labels), ``columns`` for
a set of columns and ``enum_values`` / ``enum_names`` for codes, in the words of
:mod:`skinstretch.drivers.file_vocabulary` (shared with the results files), from :data:`SESSION_DATASETS` and the
:class:`StreamSpec` of each stream (:data:`KNOWN_STREAMS`); :meth:`Session.dataset_info` reads them back, and
describes a file written before they existed from the same tables.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import h5py
import numpy as np

from skinstretch.drivers.camera_modes import CameraMode
from skinstretch.drivers.disk_space import (DEFAULT_RESERVE_BYTES, SpaceReserve, check_fits, close_on_a_full_disk,
                                            free_bytes, is_disk_full, megabytes, unclosed_files)
from skinstretch.processing.feature_table import KIND_NAMES
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.drivers.errors import DiskFullError, SessionFileError
from skinstretch.drivers.file_vocabulary import (DEG, GREY_LEVEL, N, N_M, ONE, PX, S, TEXT, UM, UNSPECIFIED,
                                                  CONVENTIONS, DatasetInfo, describe_dataset,
                                                  read_dataset_info)
from skinstretch.processing.errors import InvalidInputError, Remedy

FORMAT_NAME = "skinstretch-session"
FORMAT_VERSION = 1

STATUS_RECORDING = 0
STATUS_COMPLETE = 1
STATUS_FAILED = 2
STATUS_NAMES = {STATUS_RECORDING: "recording", STATUS_COMPLETE: "complete", STATUS_FAILED: "failed"}
_REASON_LEN = 512

@dataclass(frozen=True)
class StreamSpec:
    """A time-stamped sample stream of a session (force, display positions...): the shape and type of one sample,
    and how it explains itself in the file (``units``, ``axes`` of one sample, ``columns`` of a 1-D sample)."""

    shape: tuple[int, ...]
    dtype: Any
    units: str
    axes: tuple[str, ...] = ()
    columns: tuple[str, ...] = ()
    description: str = ""

    def info(self) -> DatasetInfo:
        axes = self.axes or tuple(f"dim{k}" for k in range(1, len(self.shape) + 1))
        return DatasetInfo(self.units, ("sample", *axes), self.description, self.columns)


_CONTACTOR_AXES = ("contactor_row", "contactor_column")

#: How the streams skinstretch records explain themselves (a declaration by name and shape picks these up).
KNOWN_STREAMS: dict[str, StreamSpec] = {
    "force": StreamSpec((6,), "f8", ", ".join([N, N, N, N_M, N_M, N_M]), ("component",),
                        ("fx", "fy", "fz", "tx", "ty", "tz"), "force (N) and torque (N m) in the sensor frame"),
    "display_state": StreamSpec((10, 10), "f4", UM, _CONTACTOR_AXES, (),
                                "measured lateral position of every contactor of the display"),
    "display_target": StreamSpec((10, 10), "f4", UM, _CONTACTOR_AXES, (), "target position of every contactor"),
    "display_command": StreamSpec((10, 10), "f4", UM, _CONTACTOR_AXES, (),
                                  "position sent to every contactor (after the driver's limits)"),
    "display_measured": StreamSpec((10, 10), "f4", UM, _CONTACTOR_AXES, (),
                                   "measured position of every contactor, aligned to the target it answers"),
}

#: Every dataset of a session (``streams/<name>/data`` come from their :class:`StreamSpec`). Files written before
#: these attributes existed are read with these same descriptions (:meth:`Session.dataset_info`).
SESSION_DATASETS: dict[str, DatasetInfo] = {
    "frames": DatasetInfo(GREY_LEVEL, ("frame", "y", "x"), "8-bit grey images (0 black, 255 white)"),
    "timestamps": DatasetInfo(S, ("frame",), "host time of each frame (Unix epoch; imported sessions: from the "
                                             "first frame)"),
    "device_timestamps": DatasetInfo(S, ("frame",), "camera (or file) time of each frame; NaN where none"),
    "frame_ids": DatasetInfo(ONE, ("frame",), "camera frame counter (a gap is a dropped frame)"),
    "status": DatasetInfo(ONE, (), "state of the session", enum=STATUS_NAMES),
    "status_reason": DatasetInfo(TEXT, (), "why the session failed (empty otherwise)"),
    "truth/feature_id": DatasetInfo(ONE, ("feature",), "stable id of every true minutia and pore"),
    "truth/feature_kind": DatasetInfo(ONE, ("feature",), "kind of every true feature", enum=KIND_NAMES),
    "truth/feature_x": DatasetInfo(PX, ("frame", "feature"), "true x (column) of every feature in every frame"),
    "truth/feature_y": DatasetInfo(PX, ("frame", "feature"), "true y (row) of every feature in every frame"),
    "truth/feature_visible": DatasetInfo(ONE, ("frame", "feature"), "feature in view and in contact (bool)"),
    "truth/grid_x": DatasetInfo(PX, ("grid_x",), "frame-0 x of the displacement grid"),
    "truth/grid_y": DatasetInfo(PX, ("grid_y",), "frame-0 y of the displacement grid"),
    "truth/displacement": DatasetInfo(PX, ("frame", "grid_y", "grid_x", "component"),
                                      "Lagrangian displacement of the skin point at the grid point in frame 0",
                                      ("dx", "dy")),
    "truth/displacement_valid": DatasetInfo(ONE, ("frame", "grid_y", "grid_x"),
                                            "that skin point is in view and in contact (bool)"),
    "truth/rigid": DatasetInfo(", ".join([PX, PX, DEG]), ("frame", "component"),
                               "fingertip rigid motion relative to frame 0 (theta counter-clockwise on the image)",
                               ("tx", "ty", "theta")),
    "truth/rigid_center": DatasetInfo(PX, ("component",), "centre of that rotation in frame 0", ("x", "y")),
    "truth/strain": DatasetInfo(ONE, ("frame", "grid_y", "grid_x", "component"),
                                "Green-Lagrange strain of frame k relative to frame 0, image axes (a fraction)",
                                ("exx", "eyy", "exy")),
}
_STREAM_TIME = DatasetInfo(S, ("sample",), "host time of each sample")


def stream_spec(name: str, declared: StreamSpec | tuple) -> StreamSpec:
    """The :class:`StreamSpec` of a declared stream: as given, the known one of that name and shape, or one whose
    units say ``unspecified``."""
    if isinstance(declared, StreamSpec):
        return declared
    shape, dtype = declared
    shape = tuple(int(t) for t in shape)
    known = KNOWN_STREAMS.get(name)
    if known is not None and known.shape == shape:
        return StreamSpec(shape, dtype, known.units, known.axes, known.columns, known.description)
    return StreamSpec(shape, dtype, UNSPECIFIED)


@contextmanager
def replacing_file(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Write a file under a temporary name beside ``path`` and move it onto ``path`` only when the block succeeds.

    Yields the temporary path (not yet created). If the block raises, the temporary file is removed and ``path``
    is untouched, so a half-written file never stands at ``path`` as if it were good. ``path`` existing is an
    error unless ``overwrite``.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise InvalidInputError(f"{path} exists", remedy=Remedy(("overwrite",), "to replace it", True))
    if path.is_dir():
        raise InvalidInputError(f"{path} is a directory, not a file name")
    if not path.parent.is_dir():
        raise InvalidInputError(f"{path.parent} is not an existing directory")
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    tmp.unlink()  # writers create it themselves (and refuse to overwrite)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@dataclass
class SessionTruth:
    """Ground truth of a simulated session (all positions in image pixels, x = column, y = row).

    Attributes
    ----------
    feature_id : (F,) int64
        Stable id of every true feature (minutia or pore).
    feature_kind : (F,) int8
        :class:`skinstretch.processing.feature_table.FeatureKind` value of each feature.
    feature_x, feature_y : (N, F) float64
        Sub-pixel position of every feature in every frame.
    feature_visible : (N, F) bool
        False when the feature is out of view or out of contact in that frame (its position is still the
        true skin position, projected).
    grid_x : (GX,) float64, grid_y : (GY,) float64
        Grid of frame-0 image positions (px, spacing <= 8 px) at which the displacement field is given.
    displacement : (N, GY, GX, 2) float32
        Lagrangian displacement (dx, dy) in px of the skin point that is at (grid_x, grid_y) in frame 0:
        its position in frame k is (grid_x + dx, grid_y + dy).
    displacement_valid : (N, GY, GX) bool
        Whether that skin point is in view and in contact in frame k.
    rigid : (N, 3) float64
        Fingertip rigid motion relative to frame 0: tx, ty in px and rotation theta in degrees
        (counter-clockwise on the image, about ``rigid_center``).
    rigid_center : (2,) float64
        Centre (x, y) of the rotation in frame-0 pixels.
    strain : (N, GY, GX, 3) float32
        Green-Lagrange strain (Exx, Eyy, Exy) of frame k relative to frame 0 at the grid points, in image axes.
    attrs : dict
        Free scalar/string attributes (scene name, scene YAML, seed, noise...).
    """

    feature_id: np.ndarray
    feature_kind: np.ndarray
    feature_x: np.ndarray
    feature_y: np.ndarray
    feature_visible: np.ndarray
    grid_x: np.ndarray
    grid_y: np.ndarray
    displacement: np.ndarray
    displacement_valid: np.ndarray
    rigid: np.ndarray
    rigid_center: np.ndarray
    strain: np.ndarray
    attrs: dict[str, Any] = field(default_factory=dict)

    _ARRAYS = (
        "feature_id",
        "feature_kind",
        "feature_x",
        "feature_y",
        "feature_visible",
        "grid_x",
        "grid_y",
        "displacement",
        "displacement_valid",
        "rigid",
        "rigid_center",
        "strain",
    )

    def validate(self, n_frames: int) -> None:
        f = np.asarray(self.feature_id).shape[0]
        gy, gx = np.asarray(self.grid_y).size, np.asarray(self.grid_x).size
        expected = {
            "feature_kind": (f,),
            "feature_x": (n_frames, f),
            "feature_y": (n_frames, f),
            "feature_visible": (n_frames, f),
            "displacement": (n_frames, gy, gx, 2),
            "displacement_valid": (n_frames, gy, gx),
            "rigid": (n_frames, 3),
            "rigid_center": (2,),
            "strain": (n_frames, gy, gx, 3),
        }
        for name, shape in expected.items():
            got = np.asarray(getattr(self, name)).shape
            if got != shape:
                raise InvalidInputError(f"truth.{name} has shape {got}, expected {shape}")
        if len(self.grid_x) > 1 and np.max(np.diff(self.grid_x)) > 8 + 1e-9:
            raise InvalidInputError("truth.grid_x spacing must be at most 8 px")
        if len(self.grid_y) > 1 and np.max(np.diff(self.grid_y)) > 8 + 1e-9:
            raise InvalidInputError("truth.grid_y spacing must be at most 8 px")


# --------------------------------------------------------------------------------------------------- writing


def _json_attr(value: Mapping[str, Any] | None) -> str:
    return json.dumps(dict(value or {}), sort_keys=True, default=str)


def _create_layout(
    f: h5py.File,
    *,
    height: int,
    width: int,
    camera_mode: CameraMode,
    calibration: Calibration,
    metadata: Mapping[str, Any] | None,
    streams: Mapping[str, StreamSpec | tuple[tuple[int, ...], Any]] | None,
    n_frames: int,
    compression: str | None,
) -> None:
    """Create every group, attribute and dataset of a session up front (SWMR forbids creating them later)."""
    f.attrs["format"] = FORMAT_NAME
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["conventions"] = CONVENTIONS
    f.attrs["created_unix"] = time.time()
    f.attrs["metadata_json"] = _json_attr(metadata)
    cam = f.create_group("camera")
    cam.attrs["mode"] = camera_mode.name
    cam.attrs["width"] = camera_mode.width
    cam.attrs["height"] = camera_mode.height
    cam.attrs["fps"] = camera_mode.fps
    cal = f.create_group("calibration")
    cal.attrs["px_per_mm"] = calibration.px_per_mm
    mapping = getattr(calibration, "mapping", None)
    cal.attrs["mapping_json"] = json.dumps(mapping.to_dict()) if mapping is not None else ""
    f.create_dataset(
        "frames",
        shape=(n_frames, height, width),
        maxshape=(None, height, width),
        dtype=np.uint8,
        chunks=(1, height, width),
        compression=compression,
    )
    for name, dtype in (("timestamps", np.float64), ("device_timestamps", np.float64), ("frame_ids", np.int64)):
        f.create_dataset(name, shape=(n_frames,), maxshape=(None,), dtype=dtype, chunks=(4096,))
    f.create_dataset("status", data=np.int8(STATUS_RECORDING))
    f.create_dataset("status_reason", data=np.bytes_(b"".ljust(_REASON_LEN)), dtype=f"S{_REASON_LEN}")
    for name in ("frames", "timestamps", "device_timestamps", "frame_ids", "status", "status_reason"):
        describe_dataset(f[name], SESSION_DATASETS[name])
    sg = f.create_group("streams")
    for name, declared in (streams or {}).items():
        spec = stream_spec(name, declared)
        g = sg.create_group(name)
        tail, dtype = spec.shape, spec.dtype
        describe_dataset(g.create_dataset("t", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(4096,)),
                         _STREAM_TIME)
        chunk_rows = max(1, min(4096, (1 << 20) // max(1, int(np.prod(tail or (1,))) * np.dtype(dtype).itemsize)))
        data = g.create_dataset("data", shape=(0, *tail), maxshape=(None, *tail), dtype=dtype, chunks=(chunk_rows, *tail))
        describe_dataset(data, spec.info())


#: HDF5 metadata of a session (groups, attributes, dataset headers, chunk indices) stays below this.
_LAYOUT_BYTES = 256 << 10


def expected_session_bytes(
    camera_mode: CameraMode,
    n_frames: int,
    *,
    streams: Mapping[str, tuple[tuple[int, ...], Any]] | None = None,
    samples: Mapping[str, int] | None = None,
    reserve_bytes: int = DEFAULT_RESERVE_BYTES,
) -> int:
    """Bytes a recording of ``n_frames`` frames (and ``samples[name]`` rows of each stream) takes on disk, with
    its layout and the reserve a :class:`SessionWriter` holds while writing; frames are stored uncompressed."""
    per_frame = camera_mode.width * camera_mode.height + 3 * 8  # image, two time stamps, frame id
    total = int(n_frames) * per_frame + _LAYOUT_BYTES + int(reserve_bytes)
    for name, (tail, dtype) in (streams or {}).items():
        row = int(np.prod(tuple(int(t) for t in tail) or (1,))) * np.dtype(dtype).itemsize + 8  # sample + time
        total += int((samples or {}).get(name, 0)) * row
    return total


class SessionWriter:
    """Stream frames and samples into a new session file in HDF5 SWMR mode.

    The file is flushed at least every ``flush_interval_s`` seconds of wall time, so a process killed at any
    moment loses at most that much data and leaves a file that opens (its status then reads "recording",
    which :class:`Session` reports as incomplete).

    Parameters
    ----------
    path : path-like
        File to create; an existing file is an error (recordings are never overwritten).
    camera_mode : CameraMode
        Size and rate of the frames.
    calibration : Calibration
        Pixel scale (and mapping, if fitted) of the frames.
    metadata : mapping, optional
        Free JSON-serialisable metadata (subject, surface, protocol, trial...).
    streams : mapping name -> StreamSpec or (sample shape, dtype), optional
        Extra time-stamped sample streams, e.g. ``{"force": ((6,), "f8")}``; a stream of :data:`KNOWN_STREAMS`
        declared by name and shape gets its units and column names, any other should be a :class:`StreamSpec`.
    reserve_bytes : int, optional
        Disk space held next to the file (``.NAME.reserve``) until it is closed, so it can always be closed.
    min_free_bytes : int, optional
        A write that would leave less free space than this is refused with DiskFullError (nothing written).
    free_bytes : callable, optional
        ``free_bytes(directory) -> int``; tests inject a disk that fills up.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        camera_mode: CameraMode,
        calibration: Calibration,
        metadata: Mapping[str, Any] | None = None,
        streams: Mapping[str, StreamSpec | tuple[tuple[int, ...], Any]] | None = None,
        flush_interval_s: float = 0.05,
        compression: str | None = None,
        reserve_bytes: int = DEFAULT_RESERVE_BYTES,
        min_free_bytes: int = 1 << 20,
        free_bytes: Callable[[Path], int] = free_bytes,
    ) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise InvalidInputError(f"session file {self.path} already exists; recordings are never overwritten")
        self._height, self._width = camera_mode.height, camera_mode.width
        self._flush_interval = float(flush_interval_s)
        self._free_bytes = free_bytes
        self._min_free = int(min_free_bytes)
        self._unflushed = 0  # bytes appended since the last flush (HDF5 keeps them in memory until then)
        self._closed = True  # until the file exists
        self._check_room(_LAYOUT_BYTES)
        self._reserve = SpaceReserve(self.path, reserve_bytes)  # DiskFullError before the file is created
        try:
            self._file = h5py.File(self.path, "w", libver="latest")
        except BaseException:
            self._reserve.release()
            raise
        try:
            _create_layout(
                self._file,
                height=self._height,
                width=self._width,
                camera_mode=camera_mode,
                calibration=calibration,
                metadata=metadata,
                streams=streams,
                n_frames=0,
                compression=compression,
            )
            self._file.swmr_mode = True
        except BaseException:
            self._file.close()
            self._reserve.release()
            raise
        self._frames = self._file["frames"]
        self._ts = self._file["timestamps"]
        self._dts = self._file["device_timestamps"]
        self._ids = self._file["frame_ids"]
        self._n = 0
        self._stream_n: dict[str, int] = {name: 0 for name in (streams or {})}
        self._last_flush = time.monotonic()
        self._closed = False

    def _check_room(self, nbytes: int) -> None:
        """DiskFullError, before anything is written, when ``nbytes`` (plus what HDF5 still holds in memory: it
        writes raw data at flushes) would leave less than the minimum free."""
        free = self._free_bytes(self.path.parent)
        if free < nbytes + self._unflushed + self._min_free:
            raise DiskFullError(f"{self.path}: disk full: {megabytes(free)} free for {megabytes(nbytes + self._unflushed)}"
                                f" to write and {megabytes(self._min_free)} to keep free; recording stopped, "
                                "everything written before is kept")

    @contextmanager
    def _writing(self, nbytes: int | None):
        """Around every write of ``nbytes`` (None: a flush): refuse it when the disk has no room for it and for what
        is not flushed yet, and turn an ENOSPC that HDF5 meets
        anyway (another process filled the disk since the check) into DiskFullError, after releasing the reserve
        and flushing again so that the file can still be closed (see :mod:`skinstretch.drivers.disk_space`)."""
        if self._closed:
            raise SessionFileError(f"{self.path}: the session writer is closed")
        if nbytes is not None:  # a flush (None) is never refused: the appends before it kept the room for it
            self._check_room(nbytes)
            self._unflushed += nbytes
        try:
            yield
        except (OSError, RuntimeError) as exc:
            if not is_disk_full(exc):
                raise
            self._reserve.release()
            try:
                self._file.flush()
            except (OSError, RuntimeError):
                pass  # close() tries again
            raise DiskFullError(f"{self.path}: disk full while writing (ENOSPC); recording stopped, everything "
                                "flushed before is kept") from None

    @property
    def n_frames(self) -> int:
        return self._n

    def append_frame(
        self, frame: np.ndarray, *, timestamp: float, frame_id: int, device_timestamp: float = math.nan
    ) -> None:
        """Append one uint8 frame of the mode's size with its host timestamp (s) and camera frame id."""
        if frame.dtype != np.uint8 or frame.shape != (self._height, self._width):
            raise InvalidInputError(
                f"frame must be uint8 of shape {(self._height, self._width)}, got {frame.dtype} {frame.shape}"
            )
        n = self._n
        with self._writing(frame.nbytes + 24):
            # Time stamps first, frame last: a reader trusts only rows present in all three (see n_frames).
            for ds, value in ((self._ts, timestamp), (self._dts, device_timestamp), (self._ids, frame_id)):
                ds.resize((n + 1,))
                ds[n] = value
            self._frames.resize((n + 1, self._height, self._width))
            self._frames[n] = frame
            self._n = n + 1
            self._maybe_flush()

    def append_frames(
        self, frames: np.ndarray, *, timestamps: np.ndarray, frame_ids: np.ndarray, device_timestamps: np.ndarray
    ) -> None:
        """Append k frames at once (k, H, W) uint8: one resize per dataset instead of one per frame."""
        frames = np.asarray(frames)
        k = frames.shape[0] if frames.ndim == 3 else -1
        if frames.dtype != np.uint8 or frames.shape[1:] != (self._height, self._width):
            raise InvalidInputError(
                f"frames must be uint8 of shape (k, {self._height}, {self._width}), got {frames.dtype} {frames.shape}"
            )
        cols = [np.asarray(v).reshape(-1) for v in (timestamps, device_timestamps, frame_ids)]
        if any(c.shape[0] != k for c in cols):
            raise InvalidInputError(f"timestamps, device_timestamps and frame_ids must each hold {k} values")
        n = self._n
        with self._writing(frames.nbytes + 24 * k):
            # Time stamps first, frames last, as in append_frame.
            for ds, values in zip((self._ts, self._dts, self._ids), cols):
                ds.resize((n + k,))
                ds[n : n + k] = values
            self._frames.resize((n + k, self._height, self._width))
            self._frames[n : n + k] = frames
            self._n = n + k
            self._maybe_flush()

    def append_samples(self, stream: str, t: np.ndarray | float, data: np.ndarray) -> None:
        """Append samples (``t`` of shape (k,), ``data`` of shape (k, *sample_shape)) to a declared stream."""
        if stream not in self._stream_n:
            raise InvalidInputError(f"stream {stream!r} was not declared when the session was created")
        g = self._file["streams"][stream]
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        data = np.asarray(data)
        if data.shape[1:] != g["data"].shape[1:] and data.shape == g["data"].shape[1:]:
            data = data[None]
        if data.shape[0] != t.shape[0] or data.shape[1:] != g["data"].shape[1:]:
            raise InvalidInputError(
                f"stream {stream!r}: got t {t.shape} and data {data.shape}, expected (k,) and (k, *{g['data'].shape[1:]})"
            )
        n, k = self._stream_n[stream], t.shape[0]
        with self._writing(data.nbytes + t.nbytes):
            g["data"].resize((n + k, *g["data"].shape[1:]))
            g["data"][n : n + k] = data
            g["t"].resize((n + k,))
            g["t"][n : n + k] = t
            self._stream_n[stream] = n + k
            self._maybe_flush()

    def _maybe_flush(self) -> None:
        now = time.monotonic()
        if now - self._last_flush >= self._flush_interval:
            self.flush()
            self._last_flush = now

    def flush(self) -> None:
        """Write everything buffered to the file (readers in SWMR mode then see it)."""
        with self._writing(None):
            self._file.flush()
            self._unflushed = 0

    def close(self, *, status: int = STATUS_COMPLETE, reason: str = "") -> None:
        """Mark the session complete (or failed, with a reason) and close the file. Idempotent.

        The disk reserve is released first, so the last writes have room even on a full disk. If HDF5 still
        cannot write (another process took that room too) the flush is retried while space may come back (see
        :func:`~skinstretch.drivers.disk_space.close_on_a_full_disk`); after that the file stays open in HDF5 and
        DiskFullError says so (:func:`unclosed_sessions`).
        """
        if self._closed:
            return
        self._closed = True
        self._reserve.release()

        def mark() -> None:
            self._file["status_reason"][()] = np.bytes_(reason.encode("utf-8")[:_REASON_LEN].ljust(_REASON_LEN))
            self._file["status"][()] = np.int8(status)

        close_on_a_full_disk(self._file, self.path, last_writes=mark, keep=self,
                             lost="writes since its last flush are lost, frames flushed before are kept")

    def fail(self, reason: str) -> None:
        """Close the session marked failed with ``reason``; the data written so far is kept."""
        self.close(status=STATUS_FAILED, reason=reason)

    def __enter__(self) -> "SessionWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close()
        else:
            self.fail(f"{exc_type.__name__}: {exc}")


def unclosed_sessions() -> list[Path]:
    """Session files this process could not close because the disk stayed full (normally none); see
    :func:`skinstretch.drivers.disk_space.unclosed_files`, which also lists other HDF5 files left so."""
    return unclosed_files()


def write_session(
    path: str | os.PathLike,
    frames: np.ndarray,
    *,
    timestamps: np.ndarray,
    camera_mode: CameraMode,
    calibration: Calibration,
    frame_ids: np.ndarray | None = None,
    metadata: Mapping[str, Any] | None = None,
    truth: SessionTruth | None = None,
    overwrite: bool = False,
    compression: str | None = None,
) -> Path:
    """Write a complete in-memory session (e.g. a simulated one) to ``path`` and return the path.

    Frames are stored uncompressed by default: camera noise leaves lzf nothing to gain (54 vs 55 MB for a
    180-frame 640x484 scene) at 10x the write time. ``compression`` ("lzf", "gzip") is there for noise-free data.
    """
    path = Path(path)
    frames = np.asarray(frames)
    if frames.dtype != np.uint8 or frames.ndim != 3:
        raise InvalidInputError(f"frames must be uint8 of shape (N, H, W), got {frames.dtype} {frames.shape}")
    n, h, w = frames.shape
    timestamps = np.asarray(timestamps, dtype=np.float64)
    if timestamps.shape != (n,):
        raise InvalidInputError(f"timestamps must have shape ({n},), got {timestamps.shape}")
    frame_ids = np.arange(n, dtype=np.int64) if frame_ids is None else np.asarray(frame_ids, dtype=np.int64)
    if frame_ids.shape != (n,):
        raise InvalidInputError(f"frame_ids must have shape ({n},), got {frame_ids.shape}")
    if truth is not None:
        truth.validate(n)
    # HDF5 does not survive a full disk (see disk_space): refuse what cannot fit before writing a byte
    truth_bytes = _truth_bytes(truth) if truth is not None else 0
    check_fits(path.parent, frames.nbytes + 24 * n + truth_bytes + _LAYOUT_BYTES, what=f"session {path.name}")
    with replacing_file(path, overwrite=overwrite) as tmp:
        with h5py.File(tmp, "w", libver="latest") as f:
            _create_layout(
                f,
                height=h,
                width=w,
                camera_mode=camera_mode,
                calibration=calibration,
                metadata=metadata,
                streams=None,
                n_frames=n,
                compression=compression,
            )
            f["frames"][...] = frames
            f["timestamps"][...] = timestamps
            f["device_timestamps"][...] = timestamps
            f["frame_ids"][...] = frame_ids
            if truth is not None:
                _write_truth(f, truth)
            f["status"][()] = np.int8(STATUS_COMPLETE)
    return path


def _write_truth(f: h5py.File, truth: SessionTruth, room: Callable[[int], Any] = lambda nbytes: None) -> None:
    """The truth group; ``room(nbytes)`` is asked before each array is written (it raises when there is none).

    Each array is flushed before the next is created: a compressed dataset writes its cached chunks when its handle
    is dropped, where an ENOSPC can only be printed ("Exception ignored"), not raised to the caller."""
    g = f.create_group("truth")
    for key, value in truth.attrs.items():
        g.attrs[key] = value if isinstance(value, (str, int, float, bool, np.number)) else json.dumps(value)
    for name in SessionTruth._ARRAYS:
        arr = np.asarray(getattr(truth, name))
        room(arr.nbytes)
        big = arr.ndim >= 3  # the per-frame fields: lzf keeps ~10 % off at half gzip's time (noisy floats)
        ds = g.create_dataset(name, data=arr, compression="lzf" if big else None)
        describe_dataset(ds, SESSION_DATASETS[f"truth/{name}"])
        f.flush()


def _truth_bytes(truth: SessionTruth) -> int:
    return sum(np.asarray(getattr(truth, a)).nbytes for a in SessionTruth._ARRAYS)


def attach_truth(path: str | os.PathLike, truth: SessionTruth) -> Path:
    """Add the ground truth of a simulated *recorded* session to its closed file (the truth of frame k of the
    file must be row k of ``truth``). A file that already has a truth is an error.

    The disk is handled as a recording's is (:mod:`skinstretch.drivers.disk_space`): a truth that does not fit is
    refused (DiskFullError) before the file is opened, and if another process fills the disk while it is written,
    the part written is removed with the room of a reserve and the file closed as it was, its recording intact.
    """
    path = Path(path)
    check_fits(path.parent, _truth_bytes(truth) + DEFAULT_RESERVE_BYTES + _LAYOUT_BYTES,
               what=f"the ground truth of {path.name}")
    with SpaceReserve(path) as reserve:
        f = h5py.File(path, "r+", libver="latest")
        try:
            if "truth" in f:
                raise InvalidInputError(f"{path} already has a ground truth")
            n = int(min(f["frames"].shape[0], f["timestamps"].shape[0], f["frame_ids"].shape[0]))
            truth.validate(n)
            _write_truth(f, truth, room=lambda nbytes: check_fits(path.parent, nbytes + (1 << 20),
                                                                  what=f"the ground truth of {path.name}"))
        except (OSError, RuntimeError, DiskFullError) as exc:
            if not is_disk_full(exc):
                raise
            reserve.release()

            def without_truth() -> None:
                if "truth" in f:
                    del f["truth"]

            close_on_a_full_disk(f, path, last_writes=without_truth, lost="its recording is kept")
            raise DiskFullError(f"{path}: disk full while adding the ground truth; the recording is kept without "
                                "it") from None
        finally:
            if f.id.valid and path not in unclosed_files():
                close_on_a_full_disk(f, path, reserve=reserve, lost="its recording is kept")
    return path


def write_calibration(path: str | os.PathLike, calibration: Calibration) -> Path:
    """Store a calibration (pixel scale and fitted mapping, seed 3.4) into an existing, closed session file.

    The file is opened read-write (not SWMR): a recorder must have closed it. Returns the path.
    """
    path = Path(path)
    if not isinstance(calibration, Calibration):
        raise InvalidInputError(f"calibration must be a Calibration, got {type(calibration).__name__}")
    open_session(path).close()  # refuse anything that is not a readable session, saying why
    mapping = calibration.mapping
    mapping_json = json.dumps(mapping.to_dict()) if mapping is not None else ""
    try:
        with h5py.File(path, "r+", libver="latest") as f:
            f["calibration"].attrs["px_per_mm"] = calibration.px_per_mm
            f["calibration"].attrs["mapping_json"] = mapping_json
    except OSError as exc:
        raise SessionFileError(f"{path}: cannot open the session to write its calibration ({exc})") from None
    return path


def write_metadata(path: str | os.PathLike, metadata: Mapping[str, Any]) -> Path:
    """Replace the metadata of an existing, closed session file (e.g. what an import learned from all its frames).

    The file is opened read-write (not SWMR): a recorder must have closed it. Returns the path.
    """
    path = Path(path)
    try:
        with h5py.File(path, "r+", libver="latest") as f:
            f.attrs["metadata_json"] = _json_attr(metadata)
    except OSError as exc:
        raise SessionFileError(f"{path}: cannot open the session to write its metadata ({exc})") from None
    return path


def _calibration_from_attrs(path: Path, px_per_mm: float, mapping_json: str) -> Calibration:
    """The session's Calibration, with its fitted pixel-to-skin mapping rebuilt when one is stored."""
    if not mapping_json:
        return Calibration(px_per_mm=px_per_mm)
    # Imported here: only sessions that carry a mapping need the calibration module (scipy, OpenCV).
    from skinstretch.processing.errors import CalibrationError
    from skinstretch.processing.geometric_calibration import mapping_from_dict

    try:
        mapping = mapping_from_dict(json.loads(mapping_json))
    except (json.JSONDecodeError, CalibrationError, InvalidInputError) as exc:
        raise SessionFileError(f"{path}: /calibration mapping_json is not a valid mapping ({exc})") from None
    return Calibration(px_per_mm=px_per_mm, mapping=mapping)


# --------------------------------------------------------------------------------------------------- reading


class _SharedHandle:
    """The one HDF5 handle of a session file in this process, and the one handle of each of its frame datasets,
    shared by every :class:`Session` of that file (:func:`open_session`) and closed with the last of them.

    Why one: as soon as a dataset opened more than once in a process is refreshed (``H5Drefresh``, which a reader
    of a growing file must call), every handle of it reads the fill value, zeros, in place of the frames (measured
    with HDF5 2.0.0, h5py 3.16, SWMR or not: a second ``open_session`` of a file silently read black frames through
    both); and HDF5 refuses to open a file SWMR and non-SWMR at the same time.
    """

    def __init__(self, key: tuple[int, int], f: h5py.File) -> None:
        self.key, self.file, self.users = key, f, 0
        self.frames = f["frames"]
        self.timestamps = f["timestamps"]
        self.device_timestamps = f["device_timestamps"]
        self.frame_ids = f["frame_ids"]
        self.status = f["status"]


_SHARED: dict[tuple[int, int], _SharedHandle] = {}  # by (device, inode): one handle whatever path names the file
_SHARED_LOCK = threading.Lock()


def _release(shared: _SharedHandle) -> None:
    with _SHARED_LOCK:
        shared.users -= 1
        if shared.users <= 0:
            _SHARED.pop(shared.key, None)
            shared.file.close()


class Session:
    """A session file opened for reading (use :func:`open_session`). Closes on ``close()`` or ``with``.

    Every Session of one file in a process reads through one shared HDF5 handle (:class:`_SharedHandle`); the file
    is read again from the disk only once all of them are closed.
    """

    def __init__(self, path: Path, shared: _SharedHandle) -> None:
        self.path = path
        self._shared: _SharedHandle | None = shared
        f = self._f = shared.file
        self._frames, self._ts = shared.frames, shared.timestamps
        self._dts, self._ids = shared.device_timestamps, shared.frame_ids
        self._n_finished: int | None = None  # n_frames of a file that says it is finished
        try:
            cam = f["camera"].attrs
            self.camera_mode = CameraMode(
                str(cam["mode"]), int(cam["width"]), int(cam["height"]), float(cam["fps"])
            )
            cal = f["calibration"].attrs
            self.mapping_json: str = str(cal.get("mapping_json", ""))
            self.calibration = _calibration_from_attrs(path, float(cal["px_per_mm"]), self.mapping_json)
            self.metadata: dict[str, Any] = json.loads(str(f.attrs.get("metadata_json", "{}")))
            self._status = int(shared.status[()])
            raw_reason = f["status_reason"][()]
            self.status_reason = bytes(raw_reason).rstrip(b" \x00").decode("utf-8", "replace")
        except (KeyError, ValueError, TypeError, OSError) as exc:
            raise SessionFileError(f"{path}: session file is missing or has a damaged part ({exc})") from None

    # -- summary
    @property
    def n_frames(self) -> int:
        """Frames with all of image, timestamp and id written (a killed recording may leave ragged ends). Read
        again on every call while the file says it is being recorded; fixed once it says it is finished."""
        if self._status != STATUS_RECORDING and self._n_finished is not None:
            return self._n_finished
        try:
            self._frames.refresh()
            self._ts.refresh()
            self._ids.refresh()
        except (AttributeError, RuntimeError, OSError, ValueError):
            pass
        n = int(min(self._frames.shape[0], self._ts.shape[0], self._ids.shape[0]))
        if self._status != STATUS_RECORDING:
            self._n_finished = n
        return n

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.n_frames, int(self._frames.shape[1]), int(self._frames.shape[2]))

    @property
    def status(self) -> str:
        """'complete', 'failed' or 'recording' (a file still 'recording' when not open elsewhere is incomplete)."""
        return STATUS_NAMES.get(self._status, f"unknown({self._status})")

    @property
    def complete(self) -> bool:
        return self._status == STATUS_COMPLETE

    def refresh_status(self) -> str:
        """:attr:`status` read again from the file (a recorder sets it when it closes the file) and returned."""
        try:
            self._shared_handle().status.refresh()
        except (AttributeError, RuntimeError, OSError, ValueError):
            pass
        self._status = int(self._read(lambda: self._shared_handle().status[()]))
        return self.status

    def _shared_handle(self) -> _SharedHandle:
        if self._shared is None:
            raise SessionFileError(f"{self.path}: session is closed")
        return self._shared

    # -- data
    def frame(self, index: int) -> np.ndarray:
        n = self.n_frames
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {n} frames in {self.path}")
        return self._read(lambda: self._frames[index % n])

    def read_frames(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        n = self.n_frames
        stop = n if stop is None else min(stop, n)
        return self._read(lambda: self._frames[start:stop])

    def iter_frames(self, batch: int = 32) -> Iterator[np.ndarray]:
        n = self.n_frames
        for start in range(0, n, batch):
            yield from self.read_frames(start, min(start + batch, n))

    @property
    def timestamps(self) -> np.ndarray:
        return self._read(lambda: self._ts[: self.n_frames])

    def timestamp_faults(self) -> list[str]:
        """What is wrong with the frames' host time stamps, one sentence each (none for a sound file): values
        that are not finite, and steps back in time. The analysis works in frames, but rates, durations and the
        alignment with force and display streams are read from these times, so a reader is told."""
        ts = self.timestamps
        out = []
        bad = ~np.isfinite(ts)
        if bad.any():
            first = int(np.argmax(bad))
            out.append(f"{int(bad.sum())} of the {ts.size} frame time stamps are not finite (the first: frame "
                       f"{first}, {ts[first]}): rates and durations from them are meaningless")
        good = np.flatnonzero(~bad)
        back = np.flatnonzero(np.diff(ts[good]) < 0)
        if back.size:
            k = int(good[back[0] + 1])
            out.append(f"the frame time stamps go back in time {back.size} time(s) (the first: frame {k}, "
                       f"{ts[k]:.6f} s after {ts[int(good[back[0]])]:.6f} s): rates and durations from them are "
                       "meaningless")
        return out

    def timestamp(self, index: int) -> float:
        """The host time stamp of frame ``index`` (s), without reading the others."""
        return float(self._read(lambda: self._ts[index]))

    @property
    def device_timestamps(self) -> np.ndarray:
        return self._read(lambda: self._dts[: self.n_frames])

    @property
    def frame_ids(self) -> np.ndarray:
        return self._read(lambda: self._ids[: self.n_frames])

    def stream_names(self) -> list[str]:
        return sorted(self._f["streams"].keys()) if "streams" in self._f else []

    def read_stream(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(t, data) of a sample stream, trimmed to the rows written in both."""
        if name not in self.stream_names():
            raise SessionFileError(f"{self.path}: no stream {name!r} (has {self.stream_names()})")
        g = self._f["streams"][name]

        def read():
            k = min(g["t"].shape[0], g["data"].shape[0])
            return g["t"][:k], g["data"][:k]

        return self._read(read)

    def stream_info(self, name: str) -> DatasetInfo:
        """Units, axis names and column names of a stream's samples (``fx, fy, fz, tx, ty, tz`` for ``force``)."""
        if name not in self.stream_names():
            raise SessionFileError(f"{self.path}: no stream {name!r} (has {self.stream_names()})")
        return self.dataset_info(f"streams/{name}/data")

    def dataset_info(self, name: str) -> DatasetInfo:
        """What dataset ``name`` holds ("frames", "truth/strain", "streams/force/data"...): its units, axis names,
        columns and code names, from its attributes; a file written before they existed is described by
        :data:`SESSION_DATASETS` and :data:`KNOWN_STREAMS`, which is what its writer meant."""
        try:
            ds = self._f[name]
        except KeyError:
            raise SessionFileError(f"{self.path}: no dataset {name!r}") from None
        if not isinstance(ds, h5py.Dataset):
            raise SessionFileError(f"{self.path}: {name!r} is a group, not a dataset")
        info = read_dataset_info(ds)
        if info is not None:
            return info
        parts = name.strip("/").split("/")
        if len(parts) == 3 and parts[0] == "streams":
            if parts[2] == "t":
                return _STREAM_TIME
            return stream_spec(parts[1], (ds.shape[1:], ds.dtype)).info()
        info = SESSION_DATASETS.get(name.strip("/"))
        if info is None:
            raise SessionFileError(f"{self.path}: dataset {name!r} carries no units and is not a session dataset")
        return info

    @property
    def has_truth(self) -> bool:
        return "truth" in self._f

    @property
    def truth(self) -> SessionTruth:
        """Ground truth of a simulated session; SessionFileError when the session has none."""
        if not self.has_truth:
            raise SessionFileError(f"{self.path}: session has no ground truth (it was not simulated)")
        g = self._f["truth"]

        def read():
            arrays = {name: g[name][()] for name in SessionTruth._ARRAYS}
            attrs = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in g.attrs.items()}
            return SessionTruth(**arrays, attrs=attrs)

        try:
            return self._read(read)
        except KeyError as exc:
            raise SessionFileError(f"{self.path}: truth part is incomplete ({exc})") from None

    @property
    def h5(self) -> h5py.File:
        """The underlying h5py file, for extensions that store their own groups."""
        return self._f

    def _read(self, fn):
        try:
            return fn()
        except (OSError, RuntimeError) as exc:
            raise SessionFileError(f"{self.path}: cannot read data, file truncated or corrupt ({exc})") from None

    def close(self) -> None:
        shared, self._shared = self._shared, None
        if shared is not None:
            _release(shared)

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Session({str(self.path)!r}, frames={self.n_frames}, mode={self.camera_mode.name}, {self.status})"


def open_session(path: str | os.PathLike, *, swmr: bool = False) -> Session:
    """Open a session file for reading, or raise SessionFileError saying why it cannot be read.

    ``swmr=True`` reads a file a recorder is still writing. A file already open in this process (by any path) is
    served from the same HDF5 handle (see :class:`Session`), whatever ``swmr`` says. The file is read without
    HDF5's file lock (:func:`open_hdf5_for_reading`): while a Session is open, open the same file with h5py in this
    process with ``locking=False`` too (HDF5 refuses one file opened with two locking flags in one process).
    """
    path = Path(path)
    if not path.exists():
        raise SessionFileError(f"{path}: no such session file")
    if path.is_dir():
        raise SessionFileError(f"{path}: is a directory, not a session file")
    with open(path, "rb") as fh:
        head = fh.read(8)
        st = os.fstat(fh.fileno())
    if head != b"\x89HDF\r\n\x1a\n":
        raise SessionFileError(f"{path}: not an HDF5 file, so not a skinstretch session")
    key = (st.st_dev, st.st_ino)
    with _SHARED_LOCK:
        shared = _SHARED.get(key)
        if shared is None:
            shared = _SHARED[key] = _open_shared(path, key, swmr=swmr)
        shared.users += 1
    try:
        return Session(path, shared)
    except BaseException:
        _release(shared)
        raise


#: Superblock versions 2 and 3 (``libver="latest"``, every session and results file): where the file consistency
#: flags and the end-of-file address are (HDF5 file format specification, "Version 2 Superblock").
_SUPERBLOCK_FLAGS_AT = 11
_FLAG_OPEN_FOR_WRITE, _FLAG_OPEN_FOR_SWMR_WRITE = 0x1, 0x4


def _superblock(path: Path) -> tuple[int, int] | None:
    """(file consistency flags, end-of-file address) of a version 2 or 3 superblock at the start of ``path``;
    None for another version or a file too short to hold one."""
    with open(path, "rb") as fh:
        head = fh.read(48)
    if len(head) < 12 or head[:8] != b"\x89HDF\r\n\x1a\n" or head[8] not in (2, 3):
        return None
    offsets = head[9]
    at = 12 + 2 * offsets  # signature, version, sizes, flags, base address, superblock extension address
    if offsets not in (2, 4, 8) or len(head) < at + offsets:
        return None
    return head[_SUPERBLOCK_FLAGS_AT], int.from_bytes(head[at:at + offsets], "little")


def held_for_writing(path: str | os.PathLike) -> bool:
    """Whether a program has ``path`` open for writing now (or was killed while it had): the flag HDF5 sets in
    the superblock while a writer holds the file. False for a file without such a superblock."""
    sb = _superblock(Path(path))
    return sb is not None and bool(sb[0] & (_FLAG_OPEN_FOR_WRITE | _FLAG_OPEN_FOR_SWMR_WRITE))


def open_hdf5_for_reading(path: str | os.PathLike, *, swmr: bool = False) -> h5py.File:
    """``path`` opened read-only by a reader that can never make a writer fail; SessionFileError saying why not.

    * No file lock: HDF5 takes a shared lock by default, and a writer opening the file meanwhile then fails with
      errno 11 (the ground truth attached after a recording was lost so while the live viewer had it open).
    * A closed file is opened whole (HDF5 then refuses a truncated or corrupt one at once); a file a writer holds
      (or a killed one left so) is opened in SWMR mode, as is any with ``swmr=True``, after checking it is not
      shorter than its superblock says: an SWMR reader does not check, and retries its reads past the end for
      minutes (``view`` on a truncated copy hung so).
    """
    path = Path(path)

    def refused(exc: BaseException) -> SessionFileError:
        return SessionFileError(f"{path}: HDF5 file cannot be opened, truncated or corrupt ({exc})")

    def unlocked(**kwargs) -> h5py.File:
        try:
            return h5py.File(path, "r", locking=False, **kwargs)
        except (OSError, RuntimeError) as exc:
            if "locking flag values don't match" not in str(exc):
                raise
            # this process writes the file itself (with HDF5's lock): its own reader shares that handle
            return h5py.File(path, "r", **kwargs)

    if not swmr:
        try:
            return unlocked()
        except (OSError, RuntimeError) as exc:
            if "already open for write" not in str(exc):
                raise refused(exc) from None
        # A SWMR writer that is still running, or was killed, leaves the file marked open for writing; an SWMR
        # reader opens it all the same and sees everything flushed (the session then reads as incomplete).
    sb = _superblock(path)
    size = path.stat().st_size
    if sb is not None and size < sb[1]:
        raise SessionFileError(f"{path}: HDF5 file cannot be opened, truncated or corrupt (it ends at byte {size} "
                               f"of the {sb[1]} its superblock declares)")
    try:
        return unlocked(swmr=True, libver="latest")
    except (OSError, RuntimeError) as exc:
        raise refused(exc) from None


def _open_shared(path: Path, key: tuple[int, int], *, swmr: bool) -> _SharedHandle:
    f = open_hdf5_for_reading(path, swmr=swmr)
    try:
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode()
        if fmt != FORMAT_NAME:
            raise SessionFileError(f"{path}: HDF5 file is not a skinstretch session (format attribute {fmt!r})")
        version = int(f.attrs.get("format_version", -1))
        if version != FORMAT_VERSION:
            raise SessionFileError(
                f"{path}: session format version {version} is not supported (this skinstretch reads {FORMAT_VERSION})"
            )
        try:
            return _SharedHandle(key, f)
        except (KeyError, ValueError, TypeError, OSError) as exc:
            raise SessionFileError(f"{path}: session file is missing or has a damaged part ({exc})") from None
    except BaseException:
        f.close()
        raise

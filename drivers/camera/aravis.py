"""GigE Vision / USB3 Vision cameras through Aravis 0.8 (GObject introspection, ``gi.repository.Aravis``).

The acquisition thread pops filled buffers from the Aravis stream, copies the pixels out and pushes every buffer
straight back (a buffer kept by Python is a buffer the camera cannot fill: an underrun). Aravis counts completed,
failed and underrun buffers itself (:meth:`Aravis.Stream.get_statistics`); frame-id gaps count the rest.

The stream socket buffer is set FIXED at 4 MiB: with the kernel default a non-root GigE Vision stream falls to a
few frames per second (shared FACTS, "Camera: Aravis").

``AravisCamera.fake()`` opens Aravis's in-process fake camera ("Fake_1"), which runs the same code path at exact
frame rates without a network; ``AravisCamera("127.0.0.1")`` opens ``arv-fake-gv-camera-0.8 -i 127.0.0.1``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from skinstretch.drivers.camera.base import Camera, Frame, FrameIdUnwrapper
from skinstretch.drivers.camera_modes import CameraMode
from skinstretch.drivers.errors import DeviceError
from skinstretch.processing.errors import InvalidInputError

__all__ = ["AravisCamera", "aravis_available", "load_aravis"]

SOCKET_BUFFER_BYTES = 4 * 1024 * 1024
_PIXEL_FORMATS = {"Mono8": np.uint8, "Mono16": np.uint16}
_POP_TIMEOUT_US = 50_000  # how long the acquisition thread waits per pop before checking for stop()

_aravis_module = None


def load_aravis():
    """Import and return ``gi.repository.Aravis`` (0.8); DeviceError naming what is missing otherwise."""
    global _aravis_module
    if _aravis_module is None:
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis
        except (ImportError, ValueError) as exc:
            raise DeviceError(
                "Aravis is not available: install the system package gir1.2-aravis-0.8 and PyGObject<3.51 "
                f"(the 'camera' extra) ({type(exc).__name__}: {exc})"
            ) from None
        _aravis_module = Aravis
    return _aravis_module


def aravis_available() -> bool:
    """Whether the Aravis bindings can be imported here."""
    try:
        load_aravis()
    except DeviceError:
        return False
    return True


class AravisCamera(Camera):
    """A camera driven by Aravis.

    Parameters
    ----------
    device : str
        Aravis device id ("Fake_1", "Vendor-Model-Serial") or the camera's IP address.
    pixel_format : {"Mono8", "Mono16"}
        8-bit (uint8 frames) or 16-bit (uint16 frames) monochrome.
    exposure_s : float, optional
        Exposure time in seconds; by default 80 % of the frame period of each mode, so the rate is reachable.
    gain : float, optional
        Analog gain in the camera's units (dB on most GigE cameras); left as is when None.
    roi_offset_px : (int, int)
        Column and row of the region's top-left corner on the sensor.
    n_buffers : int
        Aravis buffers in the pool (default 32).
    queue_size : int
        Frames held between the acquisition thread and :meth:`read`.
    """

    def __init__(
        self,
        device: str,
        *,
        pixel_format: str = "Mono8",
        exposure_s: float | None = None,
        gain: float | None = None,
        roi_offset_px: tuple[int, int] = (0, 0),
        n_buffers: int = 32,
        queue_size: int = 256,
    ) -> None:
        super().__init__(queue_size=queue_size)
        if not isinstance(device, str) or not device:
            raise InvalidInputError(f"device must be a non-empty device id or IP address, got {device!r}")
        if pixel_format not in _PIXEL_FORMATS:
            raise InvalidInputError(f"pixel_format must be one of {sorted(_PIXEL_FORMATS)}, got {pixel_format!r}")
        if exposure_s is not None and not (exposure_s > 0 and math.isfinite(exposure_s)):
            raise InvalidInputError(f"exposure_s must be a positive number of seconds, got {exposure_s!r}")
        if gain is not None and not math.isfinite(gain):
            raise InvalidInputError(f"gain must be finite, got {gain!r}")
        if len(roi_offset_px) != 2 or min(roi_offset_px) < 0:
            raise InvalidInputError(f"roi_offset_px must be two non-negative ints, got {roi_offset_px!r}")
        if not isinstance(n_buffers, int) or n_buffers < 2:
            raise InvalidInputError(f"n_buffers must be an int >= 2, got {n_buffers!r}")
        self._device_name = device
        self._pixel_format = pixel_format
        self._exposure_s = exposure_s
        self._gain = gain
        self._roi_offset = (int(roi_offset_px[0]), int(roi_offset_px[1]))
        self._n_buffers = n_buffers
        self._enable_fake = False
        self._arv = None
        self._cam = None
        self._stream = None
        self._shape = (0, 0)
        self._final_statistics = {"completed": 0, "failures": 0, "underruns": 0}

    @classmethod
    def fake(cls, **kwargs) -> "AravisCamera":
        """Aravis's in-process fake camera ("Fake_1"): the real Aravis code path, no network, exact rates."""
        cam = cls("Fake_1", **kwargs)
        cam._enable_fake = True
        return cam

    # -- Camera
    def _do_open(self) -> None:
        arv = load_aravis()
        if self._enable_fake:
            arv.enable_interface("Fake")
        try:
            self._cam = arv.Camera.new(self._device_name)
        except Exception as exc:  # GLib.GError: not found, no answer, access denied
            raise DeviceError(f"Aravis camera {self._device_name!r} cannot be opened: {exc}") from None
        self._arv = arv

    def _do_close(self) -> None:
        self._stream = None
        self._cam = None  # Aravis releases the device when the last reference goes

    def _do_set_mode(self, mode: CameraMode) -> None:
        arv, cam = self._arv, self._cam
        sensor = cam.get_sensor_size()
        x0, y0 = self._roi_offset
        if x0 + mode.width > sensor.width or y0 + mode.height > sensor.height:
            raise InvalidInputError(
                f"mode {mode.name} ({mode.width}x{mode.height} at offset {x0},{y0}) does not fit the "
                f"{sensor.width}x{sensor.height} sensor of {self._device_name!r}"
            )
        bounds = cam.get_frame_rate_bounds()
        if not bounds.min <= mode.fps <= bounds.max:
            raise InvalidInputError(
                f"mode {mode.name}: fps {mode.fps} outside the camera's range [{bounds.min}, {bounds.max}]"
            )
        try:
            cam.set_acquisition_mode(arv.AcquisitionMode.CONTINUOUS)
            cam.set_region(x0, y0, mode.width, mode.height)
            cam.set_pixel_format_from_string(self._pixel_format)
            exposure_us = (self._exposure_s if self._exposure_s is not None else 0.8 / mode.fps) * 1e6
            if cam.is_exposure_time_available():
                lo, hi = cam.get_exposure_time_bounds()
                cam.set_exposure_time(min(max(exposure_us, lo), hi))
            if self._gain is not None:
                if not cam.is_gain_available():
                    raise InvalidInputError(f"gain was given but {self._device_name!r} has no gain control")
                cam.set_gain(self._gain)
            cam.set_frame_rate(mode.fps)
            got_fps = cam.get_frame_rate()
            region = cam.get_region()
        except InvalidInputError:
            raise
        except Exception as exc:
            raise DeviceError(f"{self._device_name!r}: setting mode {mode.name} failed: {exc}") from None
        if (region.width, region.height) != (mode.width, mode.height):
            raise DeviceError(
                f"{self._device_name!r}: asked for {mode.width}x{mode.height}, camera set {region.width}x{region.height}"
            )
        if abs(got_fps - mode.fps) > 0.01 * mode.fps:
            raise DeviceError(f"{self._device_name!r}: asked for {mode.fps} fps, camera set {got_fps} fps")
        self._shape = (mode.height, mode.width)

    def _do_start(self) -> None:
        arv, cam = self._arv, self._cam
        self._stream = None
        try:
            stream = cam.create_stream(None, None)
            if isinstance(stream, arv.GvStream):
                stream.set_property("socket-buffer", arv.GvStreamSocketBuffer.FIXED)
                stream.set_property("socket-buffer-size", SOCKET_BUFFER_BYTES)
            payload = cam.get_payload()
            for _ in range(self._n_buffers):
                stream.push_buffer(arv.Buffer.new_allocate(payload))
            self._stream = stream
            cam.start_acquisition()
        except Exception as exc:
            self._stream = None
            raise DeviceError(f"{self._device_name!r}: starting acquisition failed: {exc}") from None

    def _do_stop(self) -> None:
        try:
            self._cam.stop_acquisition()
        except Exception as exc:
            raise DeviceError(f"{self._device_name!r}: stopping acquisition failed: {exc}") from None
        finally:
            # Keep the final counters, then release the stream (its socket and thread): a GigE camera streams
            # to one receiver, so a stream left alive would steal the frames of the next start.
            self._final_statistics = self._read_statistics()
            self._stream = None

    def _do_grab(self) -> Frame | None:
        arv, stream = self._arv, self._stream
        buf = stream.timeout_pop_buffer(_POP_TIMEOUT_US)
        if buf is None:
            return None
        try:
            status = buf.get_status()
            if status != arv.BufferStatus.SUCCESS:
                self._count_failed()
                return None
            data = buf.get_data()  # a copy (bytes): the buffer can go straight back
            frame_id = buf.get_frame_id()
            device_t = buf.get_timestamp() * 1e-9
            host_t = buf.get_system_timestamp() * 1e-9
        finally:
            stream.push_buffer(buf)
        dtype = _PIXEL_FORMATS[self._pixel_format]
        h, w = self._shape
        image = np.frombuffer(data, dtype=np.dtype(dtype).newbyteorder("<"))
        if image.size != h * w:
            self._count_failed()
            return None
        image = image.reshape(h, w)
        if image.dtype.byteorder not in ("=", "|"):
            image = image.astype(dtype)
        return Frame(image, int(frame_id), device_t, host_t if host_t > 0 else time.time())

    def _read_statistics(self) -> dict[str, int]:
        stream = self._stream
        if stream is None:
            return dict(self._final_statistics)
        # The base-class statistics (completed, failures, underruns); GvStream overrides get_statistics.
        completed, failures, underruns = self._arv.Stream.get_statistics(stream)
        return {"completed": int(completed), "failures": int(failures), "underruns": int(underruns)}

    def _device_drops(self) -> int:
        return self._read_statistics()["underruns"]

    def _frame_id_unwrapper(self) -> FrameIdUnwrapper:
        return FrameIdUnwrapper(modulus=65536, skip_zero=True)

    # -- extras
    @property
    def pixel_format(self) -> str:
        return self._pixel_format

    @property
    def device_statistics(self) -> dict[str, int]:
        """Aravis's own stream counters (completed, failures, underruns) since the last start."""
        return self._read_statistics()

    def __repr__(self) -> str:
        return f"AravisCamera({self._device_name!r})"

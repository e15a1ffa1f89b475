"""Byte transports a display owns (never inherits): a serial port (pyserial URL) or a USB bulk pair (pyusb).

A transport moves bytes and nothing else. Link failures become :class:`skinstretch.drivers.errors.DeviceError`; a read
that times out returns ``b""`` (the protocol layer decides what a missing reply means).
"""

from __future__ import annotations

import abc
import errno
import math
import os
import select
import threading
import time

from skinstretch.drivers.errors import DeviceError

#: pid.codes test VID/PID: the STReSS prototype has no USB identity of its own; a real build would get one.

from skinstretch.processing.errors import InvalidInputError
STRESS_USB_VENDOR_ID = 0x1209
STRESS_USB_PRODUCT_ID = 0x0001
STRESS_USB_EP_OUT = 0x01
STRESS_USB_EP_IN = 0x81


class Transport(abc.ABC):
    """A full-duplex byte pipe."""

    @abc.abstractmethod
    def write(self, data: bytes) -> None:
        """Send every byte of ``data`` or raise DeviceError."""

    @abc.abstractmethod
    def read(self, max_bytes: int, *, timeout_s: float) -> bytes:
        """Return 1..max_bytes bytes as soon as some arrive, or ``b""`` after ``timeout_s``."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the link (idempotent)."""

    @property
    @abc.abstractmethod
    def description(self) -> str: ...


def _check_timeout(timeout_s: float) -> float:
    if not (isinstance(timeout_s, (int, float)) and math.isfinite(timeout_s) and timeout_s >= 0):
        raise InvalidInputError(f"timeout_s must be a finite number >= 0, got {timeout_s!r}")
    return float(timeout_s)


class SerialTransport(Transport):
    """A serial port opened with :func:`serial.serial_for_url` (device path, ``loop://``, ``stresssim://``...).

    Parameters
    ----------
    url : str
        Anything pyserial accepts. Custom schemes must be registered by the caller (experiments/simulators).
    baudrate : int, keyword-only
        Line rate in bit/s; the protocol needs >= 749 kbaud at 700 Hz (``docs/protocols/stress.md``).
    """

    WRITE_TIMEOUT_S = 1.0  # a port that takes no byte for this long is dead

    def __init__(self, url: str, *, baudrate: int = 2_000_000) -> None:
        import serial  # the dependency is only needed when a serial link is used

        if not isinstance(url, str) or not url:
            raise InvalidInputError(f"url must be a non-empty string, got {url!r}")
        if not (isinstance(baudrate, int) and baudrate > 0):
            raise InvalidInputError(f"baudrate must be a positive int, got {baudrate!r}")
        self._serial_module = serial
        self._url = url
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=self.WRITE_TIMEOUT_S)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open serial link {url!r}: {exc}") from exc
        self.baudrate = baudrate
        try:
            self._fd = self._port.fileno()
        except (AttributeError, OSError, self._serial_module.SerialException):
            self._fd = None  # URL handlers (loop://, stresssim://) have no file descriptor

    @property
    def description(self) -> str:
        return f"serial {self._url} @ {self.baudrate} baud"

    def write(self, data: bytes) -> None:
        if self._fd is not None:
            self._write_fd(data)
            return
        try:
            written = self._port.write(data)
            if written is not None and written != len(data):
                raise DeviceError(f"serial link {self._url!r} wrote {written} of {len(data)} bytes")
        except (self._serial_module.SerialException, OSError) as exc:
            raise DeviceError(f"serial link {self._url!r} lost while writing: {exc}") from exc

    def _write_fd(self, data: bytes) -> None:
        """Write to the port's (non-blocking) descriptor; wait for room only when the driver's buffer is full.

        pyserial's own write selects for writability after *every* write when a write timeout is set: on a pty
        that wait follows the kernel's buffer-flush worker (an ordinary thread) and took 0.5 ms at p99 and up to
        5 ms on a loaded machine, on the deadline path of every frame.
        """
        view = memoryview(data)
        deadline = None
        try:
            while view:
                try:
                    n = os.write(self._fd, view)
                except BlockingIOError:
                    n = 0
                view = view[n:]
                if view:
                    now = time.monotonic()
                    deadline = now + self.WRITE_TIMEOUT_S if deadline is None else deadline
                    if now >= deadline:
                        raise DeviceError(f"serial link {self._url!r} took {len(data) - len(view)} of {len(data)} "
                                          f"bytes within {self.WRITE_TIMEOUT_S} s")
                    select.select([], [self._fd], [], deadline - now)
        except OSError as exc:
            raise DeviceError(f"serial link {self._url!r} lost while writing: {exc}") from exc

    def read(self, max_bytes: int, *, timeout_s: float) -> bytes:
        timeout_s = _check_timeout(timeout_s)
        try:
            if self._fd is not None:
                # a real port: wait with select; changing pyserial's timeout would re-run tcsetattr every call
                ready, _, _ = select.select([self._fd], [], [], timeout_s)
                if not ready:
                    return b""
                try:
                    data = os.read(self._fd, max(1, max_bytes))  # the descriptor is non-blocking (pyserial)
                except BlockingIOError:
                    return b""
                if not data:
                    raise DeviceError(f"serial link {self._url!r} lost: readable but no data (device gone)")
                return data
            if self._port.timeout != timeout_s:
                self._port.timeout = timeout_s
            first = self._port.read(1)
            if not first:
                return b""
            waiting = self._port.in_waiting
            if waiting and max_bytes > 1:
                return first + self._port.read(min(waiting, max_bytes - 1))
            return first
        except (self._serial_module.SerialException, OSError, TypeError, ValueError) as exc:
            # pyserial reports an unplugged adapter / closed pty as SerialException ("returned no data")
            raise DeviceError(f"serial link {self._url!r} lost while reading: {exc}") from exc

    def close(self) -> None:
        self._fd = None  # the number may be reused by the next open file: never write to it again
        try:
            self._port.close()
        except (self._serial_module.SerialException, OSError):
            pass  # closing a vanished port: nothing left to release


class UsbTransport(Transport):
    """A pair of USB bulk endpoints, found with :func:`usb.core.find` (``backend`` pluggable, e.g. a simulator).

    pyusb waits in whole milliseconds, too coarse for a 1.43 ms frame period, so a reader thread keeps one bulk
    IN read pending (as libusb's asynchronous transfers would) and :meth:`read` waits on its buffer with any
    timeout.

    Parameters
    ----------
    vendor_id, product_id : int, keyword-only
        USB identity to look for.
    backend : usb.backend.IBackend or None, keyword-only
        None lets pyusb pick libusb; a simulator passes its own backend object.
    """

    def __init__(self, *, vendor_id: int = STRESS_USB_VENDOR_ID, product_id: int = STRESS_USB_PRODUCT_ID,
                 backend=None, ep_out: int = STRESS_USB_EP_OUT, ep_in: int = STRESS_USB_EP_IN,
                 read_size: int = 512) -> None:
        import usb.core
        import usb.util

        self._usb = usb
        try:
            device = usb.core.find(idVendor=vendor_id, idProduct=product_id, backend=backend)
        except (usb.core.NoBackendError, usb.core.USBError) as exc:
            raise DeviceError(f"cannot search USB for {vendor_id:04x}:{product_id:04x}: {exc}") from exc
        if device is None:
            raise DeviceError(f"no USB device {vendor_id:04x}:{product_id:04x} found")
        try:
            device.set_configuration()
        except usb.core.USBError as exc:
            raise DeviceError(f"cannot configure USB device {vendor_id:04x}:{product_id:04x}: {exc}") from exc
        self._device = device
        self._ep_out, self._ep_in = ep_out, ep_in
        self._read_size = read_size
        self._name = f"usb {vendor_id:04x}:{product_id:04x}"
        self._closed = False
        self._buffer = bytearray()
        self._error: Exception | None = None
        self._ready = threading.Condition()
        self._reader = threading.Thread(target=self._read_loop, name="usb-bulk-in", daemon=True)
        self._reader.start()

    @property
    def description(self) -> str:
        return self._name

    def _lost(self, exc: Exception, doing: str) -> DeviceError:
        return DeviceError(f"{self._name} lost while {doing}: {exc}")

    def _read_loop(self) -> None:
        timeout = self._usb.core.USBTimeoutError
        while not self._closed:
            try:
                data = self._device.read(self._ep_in, self._read_size, timeout=20)
            except timeout:
                continue
            except (self._usb.core.USBError, OSError) as exc:
                if getattr(exc, "errno", None) == errno.ETIMEDOUT:
                    continue
                with self._ready:
                    self._error = exc
                    self._ready.notify_all()
                return
            if data:
                with self._ready:
                    self._buffer += bytes(data)
                    self._ready.notify_all()

    def write(self, data: bytes) -> None:
        if self._closed:
            raise DeviceError(f"{self._name} is closed")
        try:
            written = self._device.write(self._ep_out, data, timeout=1000)
        except self._usb.core.USBTimeoutError as exc:
            raise DeviceError(f"{self._name} did not accept a bulk write within 1 s") from exc
        except (self._usb.core.USBError, OSError) as exc:
            raise self._lost(exc, "writing") from exc
        if written != len(data):
            raise DeviceError(f"{self._name} took {written} of {len(data)} bytes")

    def read(self, max_bytes: int, *, timeout_s: float) -> bytes:
        timeout_s = _check_timeout(timeout_s)
        with self._ready:
            if not self._buffer and self._error is None and not self._closed and timeout_s > 0:
                self._ready.wait_for(lambda: self._buffer or self._error is not None or self._closed, timeout_s)
            if self._buffer:
                out = bytes(self._buffer[:max_bytes])
                del self._buffer[:max_bytes]
                return out
            if self._error is not None:
                raise self._lost(self._error, "reading")
            if self._closed:
                raise DeviceError(f"{self._name} is closed")
            return b""

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self._ready:
            self._ready.notify_all()
        self._reader.join(1.0)
        try:
            self._usb.util.dispose_resources(self._device)
        except (self._usb.core.USBError, OSError):
            pass  # the device is gone already

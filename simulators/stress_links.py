"""Reach the STReSS firmware simulator through the same doors as the hardware.

- a pyserial URL ``stresssim://NAME?baud=2000000&faults=drop:0.001&seed=0&load=0.15`` (call :func:`register_url_handler`
  once; driver code then uses :func:`serial.serial_for_url` unchanged). ``NAME`` selects a link attached with
  :func:`attach` (tests attach one with a manual clock); an unknown name creates a real-time link from the query.
- a real pty pair served by a thread (:func:`start_pty_firmware`) or by a separate process
  (:class:`FirmwareProcess`: the firmware's receive clock is then free of the host's GIL).
- a pyusb backend (:class:`StressUsbBackend`) simulating the device's bulk endpoints:
  ``usb.core.find(idVendor=..., backend=StressUsbBackend(link))``.
"""

from __future__ import annotations

import array
import errno
import os
import select
import subprocess
import sys
import threading
import tty
from pathlib import Path
from types import SimpleNamespace
from urllib.parse import parse_qs, urlparse

import numpy as np
import serial
import usb.backend
import usb.core
from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.drivers.display.transports import (STRESS_USB_EP_IN, STRESS_USB_EP_OUT, STRESS_USB_PRODUCT_ID,
                                        STRESS_USB_VENDOR_ID)
from skinstretch.child_process import stop_child_process
from skinstretch.drivers.errors import DeviceError
from skinstretch.processing.errors import InvalidInputError

from .stress_firmware import StressFirmware
from .stress_pty import PtyFirmwareServer
from .stress_wire import Clock, LinkFaults, LinkVanished, PacedLink, RealClock

URL_HANDLER_PACKAGE = "skinstretch.simulators.stress_urlhandler"
_links: dict[str, PacedLink] = {}
_links_lock = threading.Lock()


def register_url_handler() -> None:
    """Make ``serial.serial_for_url("stresssim://...")`` work (idempotent). Simulator/experiment code calls it."""
    if URL_HANDLER_PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(URL_HANDLER_PACKAGE)


def attach(name: str, link: PacedLink) -> str:
    """Serve ``link`` at ``stresssim://NAME``; returns the URL."""
    if not name or not name.isidentifier():
        raise InvalidInputError(f"name must be an identifier, got {name!r}")
    with _links_lock:
        _links[name] = link
    return f"stresssim://{name}"


def detach(name: str) -> None:
    with _links_lock:
        _links.pop(name, None)


def link_for(name: str) -> PacedLink:
    with _links_lock:
        try:
            return _links[name]
        except KeyError:
            raise InvalidInputError(f"no stresssim link named {name!r}") from None


def make_link(*, baud: int = sp.DEFAULT_BAUD, seed: int = 0, faults: LinkFaults | str = LinkFaults(),
              clock: Clock | None = None) -> PacedLink:
    """A firmware behind a UART-paced link."""
    clock = clock or RealClock()
    if isinstance(faults, str):
        faults = LinkFaults.parse(faults)
    firmware = StressFirmware(seed=seed, t0=clock.now())
    return PacedLink.uart(firmware, clock=clock, baud=baud, faults=faults, seed=seed)


def _link_from_url(url: str) -> PacedLink:
    parts = urlparse(url)
    if parts.scheme != "stresssim":
        raise SerialException(f"expected a stresssim:// URL, got {url!r}")
    query = {k: v[-1] for k, v in parse_qs(parts.query).items()}
    unknown = set(query) - {"baud", "faults", "seed", "load"}
    if unknown:
        raise SerialException(f"unknown stresssim URL options {sorted(unknown)} in {url!r} "
                              "(known: baud, faults, seed, load)")
    name = parts.netloc or parts.path.strip("/")
    with _links_lock:
        if name and name in _links:
            return _links[name]
    try:
        link = make_link(baud=int(query.get("baud", sp.DEFAULT_BAUD)), seed=int(query.get("seed", 0)),
                         faults=query.get("faults", ""))
        link.firmware.benders.set_load(float(query.get("load", 0.0)))
    except (ValueError, InvalidInputError) as exc:
        raise SerialException(f"bad stresssim URL {url!r}: {exc}") from exc
    if name:
        with _links_lock:
            _links[name] = link
    return link


class StressSimSerial(SerialBase):
    """pyserial port class for ``stresssim://`` (used through :func:`serial.serial_for_url`)."""

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        self._link = _link_from_url(self._port)
        self._buffer = bytearray()
        self.is_open = True

    def _reconfigure_port(self) -> None:
        """Nothing to configure: the link's pacing was fixed when it was made."""

    def close(self) -> None:
        self.is_open = False
        super().close()

    def _pull(self) -> None:
        try:
            self._buffer += self._link.host_read(65536)
        except LinkVanished as exc:
            raise SerialException("device reports readiness to read but returned no data "
                                  f"(device disconnected or multiple access on port?): {exc}") from exc

    @property
    def in_waiting(self) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        self._pull()
        return len(self._buffer)

    def read(self, size: int = 1) -> bytes:
        if not self.is_open:
            raise PortNotOpenError()
        clock = self._link.clock
        deadline = None if self._timeout is None else clock.now() + self._timeout
        while True:
            self._pull()
            if len(self._buffer) >= size:
                break
            now = clock.now()
            if deadline is not None and now >= deadline:
                break
            nxt = self._link.next_event()
            target = deadline if nxt is None else (nxt if deadline is None else min(nxt, deadline))
            clock.sleep(0.001 if target is None else max(target - now, 1e-6))
        out = bytes(self._buffer[:size])
        del self._buffer[:size]
        return out

    def write(self, data) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        data = bytes(data)
        try:
            self._link.host_write(data)
        except LinkVanished as exc:
            raise SerialException(f"write failed: device disconnected: {exc}") from exc
        return len(data)

    def reset_input_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        self._buffer.clear()
        self._link.reset_host_input()

    def reset_output_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()

    def _update_break_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True


# ---- pty ---------------------------------------------------------------------------------------------------------

def start_pty_firmware(link: PacedLink) -> PtyFirmwareServer:
    """Serve ``link`` on a new pty pair from a thread; open ``server.port`` with pyserial. Stop with ``stop()``."""
    return PtyFirmwareServer(link).start()


class FirmwareProcess:
    """The firmware simulator in its own process on a pty; :attr:`port` is the device path to open.

    Use as a context manager. On exit (host side closed), the child saves its frame receive times to
    ``record_path`` (``.npz``), read back with :meth:`records`.
    """

    def __init__(self, *, record_path: Path, baud: int = sp.DEFAULT_BAUD, seed: int = 0, faults: str = "",
                 startup_timeout_s: float = 20.0) -> None:
        self.record_path = Path(record_path)
        master, slave = os.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        self._slave = slave
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "skinstretch.simulators.stress_pty", "--pty-fd", str(master), "--baud", str(baud),
                 "--seed", str(seed), "--faults", faults, "--record", str(self.record_path)],
                pass_fds=(master,), stdout=subprocess.PIPE, text=True)
        finally:
            os.close(master)
        ready, _, _ = select.select([self._process.stdout], [], [], startup_timeout_s)
        line = self._process.stdout.readline() if ready else ""
        if line.strip() != "ready":
            self.close(timeout_s=1.0)
            raise DeviceError(f"the firmware process did not start within {startup_timeout_s} s")

    def __enter__(self) -> "FirmwareProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self, timeout_s: float = 5.0) -> None:
        if self._slave is not None:
            os.close(self._slave)  # with the host's port closed too, the child's master read sees EIO
            self._slave = None
        # it exits by itself once its pty hangs up, saving its records; asked to stop only if it does not
        stop_child_process(self._process, grace_s=timeout_s, timeout_s=timeout_s)

    def records(self) -> dict[str, np.ndarray]:
        if not self.record_path.exists():
            raise DeviceError(f"the firmware process left no record at {self.record_path}")
        with np.load(self.record_path) as data:
            return {k: data[k] for k in data.files}


# ---- USB ---------------------------------------------------------------------------------------------------------

class StressUsbBackend(usb.backend.IBackend):
    """A pyusb backend whose only device is the firmware simulator on two bulk endpoints (no libusb)."""

    def __init__(self, link: PacedLink) -> None:
        super().__init__()
        self.link = link
        self._token = object()

    def enumerate_devices(self):
        if not self.link.vanished:
            yield self._token

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0xFF, bDeviceSubClass=0, bDeviceProtocol=0,
            bMaxPacketSize0=64, idVendor=STRESS_USB_VENDOR_ID, idProduct=STRESS_USB_PRODUCT_ID, bcdDevice=0x0100,
            iManufacturer=0, iProduct=0, iSerialNumber=0, bNumConfigurations=1, address=1, bus=1, port_number=1,
            port_numbers=(1,), speed=3)

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(config)
        return SimpleNamespace(bLength=9, bDescriptorType=2, wTotalLength=32, bNumInterfaces=1,
                               bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80, bMaxPower=50,
                               extra_descriptors=[])

    def get_interface_descriptor(self, dev, intf, alt, config):
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError((intf, alt, config))
        return SimpleNamespace(bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0,
                               bNumEndpoints=2, bInterfaceClass=0xFF, bInterfaceSubClass=0, bInterfaceProtocol=0,
                               iInterface=0, extra_descriptors=[])

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if (intf, alt, config) != (0, 0, 0) or ep not in (0, 1):
            raise IndexError((ep, intf, alt, config))
        address = STRESS_USB_EP_OUT if ep == 0 else STRESS_USB_EP_IN
        return SimpleNamespace(bLength=7, bDescriptorType=5, bEndpointAddress=address, bmAttributes=0x02,
                               wMaxPacketSize=512, bInterval=0, bRefresh=0, bSynchAddress=0, extra_descriptors=[])

    def _gone(self):
        return usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)

    def open_device(self, dev):
        if self.link.vanished:
            raise self._gone()
        return SimpleNamespace(dev=dev)

    def close_device(self, dev_handle):
        pass

    def set_configuration(self, dev_handle, config_value):
        if config_value not in (0, 1):
            raise usb.core.USBError("Invalid configuration", -2, errno.EINVAL)

    def get_configuration(self, dev_handle):
        return 1

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        pass

    def claim_interface(self, dev_handle, intf):
        pass

    def release_interface(self, dev_handle, intf):
        pass

    def clear_halt(self, dev_handle, ep):
        pass

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        if ep != STRESS_USB_EP_OUT:
            raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
        try:
            self.link.host_write(bytes(data))
        except LinkVanished:
            raise self._gone() from None
        return len(data)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        if ep != STRESS_USB_EP_IN:
            raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
        clock = self.link.clock
        deadline = clock.now() + timeout / 1000.0
        while True:
            try:
                data = self.link.host_read(len(buff))
            except LinkVanished:
                raise self._gone() from None
            if data:
                buff[:len(data)] = array.array("B", data)
                return len(data)
            now = clock.now()
            if now >= deadline:
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            nxt = self.link.next_event()
            clock.sleep(max(min(deadline, nxt if nxt is not None else deadline) - now, 1e-6))

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        raise usb.core.USBError("Pipe error (control requests are not used by this device)", -9, errno.EPIPE)

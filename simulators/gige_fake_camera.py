"""Aravis's ``arv-fake-gv-camera-0.8`` (Debian package aravis-tools) serving a GigE Vision camera on loopback.

The real :class:`skinstretch.drivers.camera.aravis.AravisCamera` then runs its whole network path (GVCP control, GVSP stream)
against it. Used by the camera conformance tests and the camera benchmark.

>>> # with FakeGigECamera() as address:
>>> #     with AravisCamera(address) as cam: ...
"""

from __future__ import annotations

import shutil
import subprocess
import time

from skinstretch.drivers.errors import DeviceError
from skinstretch.child_process import stop_child_process

__all__ = ["FakeGigECamera", "FAKE_GV_CAMERA"]

FAKE_GV_CAMERA = "arv-fake-gv-camera-0.8"


class FakeGigECamera:
    """Start the fake camera on ``address`` and wait (bounded) until Aravis can open it; stop it on exit.

    :meth:`start` raises :class:`DeviceError` naming what is missing (the binary, the bindings) or that the
    camera did not answer within ``timeout_s``.
    """

    def __init__(self, address: str = "127.0.0.1", *, timeout_s: float = 10.0) -> None:
        self.address = address
        self.timeout_s = float(timeout_s)
        self._proc: subprocess.Popen | None = None

    def start(self) -> str:
        binary = shutil.which(FAKE_GV_CAMERA)
        if binary is None:
            raise DeviceError(f"{FAKE_GV_CAMERA} not installed (Debian package aravis-tools)")
        from skinstretch.drivers.camera.aravis import load_aravis  # noqa: PLC0415  (GObject bindings, optional)

        arv = load_aravis()
        self._proc = subprocess.Popen([binary, "-i", self.address], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + self.timeout_s
        while True:  # bounded wait for the fake camera to answer
            try:
                arv.Camera.new(self.address)
                return self.address
            except Exception:  # noqa: BLE001  (Aravis raises GLib errors until the camera is up)
                if time.monotonic() > deadline or self._proc.poll() is not None:
                    self.stop()
                    raise DeviceError(f"{FAKE_GV_CAMERA} did not answer on {self.address} within "
                                      f"{self.timeout_s:g} s") from None
                time.sleep(0.1)

    def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        stop_child_process(proc)

    def __enter__(self) -> str:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

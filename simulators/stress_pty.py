"""Serve the STReSS firmware twin on a pty, from a thread or as a separate process.

``python -m skinstretch.simulators.stress_pty --pty-fd N`` serves it on an inherited pty master
(:class:`skinstretch.simulators.stress_links.FirmwareProcess` starts it so): the firmware's receive clock is then
free of the host's GIL, as the benchmark needs.
"""

from __future__ import annotations

import argparse
import errno
import os
import select
import sys
import threading
import tty

import numpy as np

from skinstretch.drivers.display import stress_protocol as sp

from .stress_firmware import StressFirmware
from .stress_wire import LinkFaults, LinkVanished, PacedLink, RealClock

__all__ = ["PtyFirmwareServer", "main"]


class PtyFirmwareServer:
    """Serve a :class:`PacedLink` on the master side of a pty; the driver opens :attr:`port` as a serial port.

    Either create the pty here (``PtyFirmwareServer(link)``, then :meth:`start` a thread) or hand over a master
    fd created by a parent process (``master_fd=``) and call :meth:`serve` in that process.
    """

    def __init__(self, link: PacedLink, *, master_fd: int | None = None) -> None:
        self.link = link
        self._slave_fd: int | None = None
        if master_fd is None:
            master_fd, slave_fd = os.openpty()
            tty.setraw(slave_fd)  # FACTS: raw mode on the slave, or the line discipline mangles bytes
            self._slave_fd = slave_fd
            self.port = os.ttyname(slave_fd)
        else:
            self.port = None
        self.master_fd = master_fd
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def start(self) -> "PtyFirmwareServer":
        self._thread = threading.Thread(target=self._run, name="stress-firmware-pty", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            self.serve()
        except BaseException as exc:  # noqa: BLE001 - kept for the owner to inspect
            self.error = exc

    def serve(self) -> None:
        """Run until :meth:`stop`, the host side closes (EIO), or the link vanishes."""
        fd = self.master_fd
        link = self.link
        clock = link.clock
        while not self._stop.is_set():
            now = clock.now()
            nxt = link.next_event()
            wait = 0.005 if nxt is None else min(max(nxt - now, 0.0), 0.005)
            readable, _, _ = select.select([fd], [], [], wait)
            if readable:
                try:
                    data = os.read(fd, 65536)
                except OSError as exc:
                    if exc.errno == errno.EIO:  # every slave fd closed: the host went away
                        return
                    raise
                if not data:
                    return
                try:
                    link.host_write(data)
                except LinkVanished:
                    break
            try:
                out = link.host_read(65536)
            except LinkVanished:
                break
            if out:
                try:
                    os.write(fd, out)
                except OSError as exc:
                    if exc.errno == errno.EIO:
                        return
                    raise
        if link.vanished:
            self._close_fds()  # an unplugged adapter: the host's port goes dead

    def _close_fds(self) -> None:
        for name in ("master_fd", "_slave_fd"):
            fd = getattr(self, name)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, name, None)

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        self._close_fds()


def main(argv: list[str] | None = None) -> int:
    """Serve the firmware on an inherited pty master fd; on exit save the frame receive times (``.npy``)."""
    parser = argparse.ArgumentParser(description="STReSS firmware simulator on a pty master fd")
    parser.add_argument("--pty-fd", type=int, required=True)
    parser.add_argument("--baud", type=int, default=sp.DEFAULT_BAUD)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--faults", default="")
    parser.add_argument("--record", default="", help="write frame receive times / seqs / targets here (.npz)")
    args = parser.parse_args(argv)
    clock = RealClock()
    firmware = StressFirmware(seed=args.seed, t0=clock.now())
    link = PacedLink.uart(firmware, clock=clock, baud=args.baud, faults=LinkFaults.parse(args.faults),
                          seed=args.seed)
    server = PtyFirmwareServer(link, master_fd=args.pty_fd)
    print("ready", flush=True)  # the parent waits for this before talking to the port
    try:
        server.serve()
    except KeyboardInterrupt:
        pass
    finally:
        if args.record:
            np.savez(args.record, frame_times=np.asarray(firmware.frame_times),
                     frame_seqs=np.asarray(firmware.frame_seqs, dtype=np.int16),
                     commands_um=np.asarray(firmware.commands_um).reshape(-1, sp.ROWS, sp.COLS),
                     watchdog_trips=firmware.watchdog_trips, crc_errors=firmware.crc_errors,
                     clamped_frames=firmware.clamped_frames, **firmware.timed.as_arrays(),
                     **{f"movie_{k}": v for k, v in firmware.movie_counters.items()})
        server._close_fds()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

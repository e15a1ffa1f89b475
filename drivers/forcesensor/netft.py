"""ATI Net F/T force/torque sensor over its RDT (raw data transfer) UDP protocol.

Protocol (shared FACTS "Force/torque: ATI Net F/T RDT over UDP"; several public implementations agree):

* requests to UDP port 49152, 8 bytes ``>HHI``: header 0x1234, command (0 stop, 2 real-time stream,
  3 buffered stream, 0x42 set software bias), sample count (0 = stream until stopped);
* responses, 36 bytes per record ``>III6i``: rdt_sequence (counts the UDP records sent since the stream
  started), ft_sequence (the box's internal sample counter), status (0 = healthy), then Fx Fy Fz Tx Ty Tz in
  counts. Buffered mode packs several records in one datagram. Counts divided by counts-per-force /
  counts-per-torque (the box's ``netftapi2.xml``: ``cfgcpf``, ``cfgcpt``) give N and N m.

The codec (:func:`encode_request`, :func:`decode_request`, :func:`encode_record`, :func:`decode_records`,
:class:`SequenceTracker`) is pure and tested on bytes; :class:`NetFTSensor` owns the UDP socket.
"""

from __future__ import annotations

import collections
import math
import socket
import struct
import time
import urllib.error
import urllib.request
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from enum import IntEnum
from typing import Sequence

import numpy as np

from skinstretch.drivers.forcesensor.base import ForceSample, ForceSensor
from skinstretch.drivers.errors import DeviceError, ProtocolError
from skinstretch.processing.errors import InvalidInputError

__all__ = [
    "RDT_HEADER",
    "RDT_PORT",
    "RECORD_SIZE",
    "REQUEST_SIZE",
    "NetFTSensor",
    "RdtCommand",
    "RdtRecord",
    "SequenceTracker",
    "counts_to_ft",
    "decode_record",
    "decode_records",
    "decode_request",
    "encode_record",
    "encode_request",
    "fetch_calibration",
    "ft_to_counts",
    "parse_calibration",
]

RDT_PORT = 49152
RDT_HEADER = 0x1234
_REQUEST = struct.Struct(">HHI")
_RECORD = struct.Struct(">III6i")
REQUEST_SIZE = _REQUEST.size  # 8
RECORD_SIZE = _RECORD.size  # 36
_U32 = 1 << 32
_I32_MIN, _I32_MAX = -(1 << 31), (1 << 31) - 1


class RdtCommand(IntEnum):
    """RDT request commands."""

    STOP = 0x0000
    START_REALTIME = 0x0002
    START_BUFFERED = 0x0003
    SET_SOFTWARE_BIAS = 0x0042


@dataclass(frozen=True)
class RdtRecord:
    """One decoded RDT record: sequence numbers, status word and the six raw counts."""

    rdt_sequence: int
    ft_sequence: int
    status: int
    counts: tuple[int, int, int, int, int, int]


# --------------------------------------------------------------------------------------------------- codec


def encode_request(command: RdtCommand | int, *, sample_count: int = 0) -> bytes:
    """The 8-byte request for ``command``; ``sample_count`` 0 streams until a STOP."""
    try:
        command = RdtCommand(command)
    except ValueError:
        raise InvalidInputError(f"command must be an RdtCommand, got {command!r}") from None
    if not isinstance(sample_count, int) or not 0 <= sample_count < _U32:
        raise InvalidInputError(f"sample_count must be an int in [0, 2**32), got {sample_count!r}")
    return _REQUEST.pack(RDT_HEADER, int(command), sample_count)


def decode_request(data: bytes) -> tuple[RdtCommand, int]:
    """(command, sample_count) of an 8-byte request; ProtocolError for anything else."""
    data = bytes(data)
    if len(data) != REQUEST_SIZE:
        raise ProtocolError(f"RDT request must be {REQUEST_SIZE} bytes, got {len(data)}")
    header, command, count = _REQUEST.unpack(data)
    if header != RDT_HEADER:
        raise ProtocolError(f"RDT request header must be 0x{RDT_HEADER:04x}, got 0x{header:04x}")
    try:
        return RdtCommand(command), count
    except ValueError:
        raise ProtocolError(f"unknown RDT command 0x{command:04x}") from None


def encode_record(record: RdtRecord) -> bytes:
    """The 36-byte wire form of a record."""
    if len(record.counts) != 6:
        raise InvalidInputError(f"record.counts must hold 6 values, got {len(record.counts)}")
    for name in ("rdt_sequence", "ft_sequence", "status"):
        v = getattr(record, name)
        if not 0 <= v < _U32:
            raise InvalidInputError(f"record.{name} must be in [0, 2**32), got {v!r}")
    if not all(_I32_MIN <= c <= _I32_MAX for c in record.counts):
        raise InvalidInputError(f"record.counts must be 32-bit signed ints, got {record.counts!r}")
    return _RECORD.pack(record.rdt_sequence, record.ft_sequence, record.status, *record.counts)


def decode_record(data: bytes) -> RdtRecord:
    """Decode exactly one 36-byte record; ProtocolError otherwise."""
    data = bytes(data)
    if len(data) != RECORD_SIZE:
        raise ProtocolError(f"RDT record must be {RECORD_SIZE} bytes, got {len(data)}")
    rdt, ft, status, *counts = _RECORD.unpack(data)
    return RdtRecord(rdt, ft, status, tuple(counts))


def decode_records(data: bytes) -> list[RdtRecord]:
    """Decode a datagram of one (real-time mode) or several (buffered mode) records; ProtocolError if the
    length is not a positive multiple of 36 bytes."""
    data = bytes(data)
    if not data or len(data) % RECORD_SIZE:
        raise ProtocolError(f"RDT datagram must be a positive multiple of {RECORD_SIZE} bytes, got {len(data)}")
    return [decode_record(data[i : i + RECORD_SIZE]) for i in range(0, len(data), RECORD_SIZE)]


def counts_to_ft(counts: Sequence[int], *, counts_per_force: float, counts_per_torque: float) -> np.ndarray:
    """Raw counts -> (Fx, Fy, Fz) N and (Tx, Ty, Tz) N m as one (6,) float64 array."""
    c = np.asarray(counts, dtype=np.float64)
    if c.shape != (6,):
        raise InvalidInputError(f"counts must hold 6 values, got shape {c.shape}")
    return np.concatenate([c[:3] / counts_per_force, c[3:] / counts_per_torque])


def ft_to_counts(ft: Sequence[float], *, counts_per_force: float, counts_per_torque: float) -> tuple[int, ...]:
    """N and N m -> the nearest raw counts, saturated to int32 as the box's ADC range would be."""
    f = np.asarray(ft, dtype=np.float64)
    if f.shape != (6,) or not np.all(np.isfinite(f)):
        raise InvalidInputError(f"ft must be 6 finite values, got {ft!r}")
    scaled = np.concatenate([f[:3] * counts_per_force, f[3:] * counts_per_torque])
    return tuple(int(v) for v in np.clip(np.rint(scaled), _I32_MIN, _I32_MAX))


def parse_calibration(xml_text: str | bytes) -> tuple[float, float]:
    """(counts per N, counts per N m) from the box's ``netftapi2.xml`` (elements ``cfgcpf`` and ``cfgcpt``).

    ProtocolError if the document is not XML or lacks a positive value for either.
    """
    try:
        root = ElementTree.fromstring(xml_text)
    except ElementTree.ParseError as exc:
        raise ProtocolError(f"netftapi2.xml is not well-formed XML ({exc})") from None
    values = []
    for tag in ("cfgcpf", "cfgcpt"):
        node = root if root.tag == tag else root.find(f".//{tag}")
        try:
            value = float(node.text) if node is not None and node.text else math.nan
        except ValueError:
            value = math.nan
        if not (value > 0 and math.isfinite(value)):
            raise ProtocolError(f"netftapi2.xml has no positive <{tag}> (got {None if node is None else node.text!r})")
        values.append(value)
    return values[0], values[1]


def fetch_calibration(host: str, *, http_port: int = 80, timeout_s: float = 2.0) -> tuple[float, float]:
    """Read (counts per N, counts per N m) from the box's web server (``http://host/netftapi2.xml``)."""
    if not (timeout_s > 0 and math.isfinite(timeout_s)):
        raise InvalidInputError(f"timeout_s must be a positive number of seconds, got {timeout_s!r}")
    url = f"http://{host}:{int(http_port)}/netftapi2.xml"
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as reply:
            text = reply.read()
    except (urllib.error.URLError, OSError) as exc:
        raise DeviceError(f"Net F/T calibration cannot be read from {url} ({exc})") from None
    return parse_calibration(text)


class SequenceTracker:
    """Follow a 32-bit wrapping sequence number: count gaps (lost), late arrivals (reordered) and duplicates.

    A sample counted lost that turns up later is taken back off ``lost`` and counted ``reordered``.

    Parameters
    ----------
    window : int
        How many recent missing sequence numbers are remembered to recognise late arrivals.
    """

    ACCEPT, LATE, DUPLICATE = "accept", "late", "duplicate"

    def __init__(self, *, window: int = 4096) -> None:
        self._window = int(window)
        self._last: int | None = None
        self._last_unwrapped = 0
        self._missing: collections.OrderedDict[int, int] = collections.OrderedDict()
        self.lost = 0
        self.reordered = 0
        self.duplicates = 0

    def feed(self, sequence: int) -> tuple[str, int]:
        """Classify ``sequence``; returns (verdict, unwrapped sequence). Duplicates should be discarded."""
        sequence = int(sequence) % _U32
        if self._last is None:
            self._last, self._last_unwrapped = sequence, sequence
            return self.ACCEPT, sequence
        step = (sequence - self._last) % _U32
        if step == 0:
            self.duplicates += 1
            return self.DUPLICATE, self._last_unwrapped
        if step < _U32 // 2:
            if step > 1:
                self.lost += step - 1
                for k in range(max(1, step - self._window), step):
                    self._missing[self._last_unwrapped + k] = 1
                while len(self._missing) > self._window:
                    self._missing.popitem(last=False)
            self._last = sequence
            self._last_unwrapped += step
            return self.ACCEPT, self._last_unwrapped
        unwrapped = self._last_unwrapped - ((self._last - sequence) % _U32)
        if unwrapped in self._missing:
            del self._missing[unwrapped]
            self.lost -= 1
            self.reordered += 1
            return self.LATE, unwrapped
        self.duplicates += 1
        return self.DUPLICATE, unwrapped


# --------------------------------------------------------------------------------------------------- driver


class NetFTSensor(ForceSensor):
    """An ATI Net F/T box streaming RDT over UDP.

    Parameters
    ----------
    host : str
        The box's IP address (or 127.0.0.1 for :class:`skinstretch.simulators.netft_box.NetFTSimulator`).
    port : int
        RDT port (49152 on the box).
    counts_per_force, counts_per_torque : float
        Scale factors from the box's calibration (``netftapi2.xml``: ``cfgcpf``, ``cfgcpt``), counts per N
        and counts per N m.
    socket_buffer_bytes : int
        Receive buffer asked of the kernel (bursts at 7 kHz must not overflow it).
    queue_size : int
        Samples held between the receive thread and :meth:`read`.
    silence_timeout_s : float
        A stream that brings no datagram for this long (from the start request on) fails with DeviceError (not
        the DeviceTimeoutError of a :meth:`read` that found nothing yet, which callers retry): a box that never
        answers (behind a firewall dropping its datagrams, at a wrong address that sends no ICMP refusal) is a
        fault, not a sensor reading nothing.

    Examples
    --------
    Against the simulated box (:mod:`skinstretch.simulators.netft_box`):

    >>> from skinstretch.simulators.netft_box import NetFTSimulator, normal_force_wrench
    >>> with NetFTSimulator(rate_hz=1000, wrench=normal_force_wrench(lambda t: 2.0)) as box:
    ...     host, port = box.address
    ...     with NetFTSensor(host, port=port) as sensor:
    ...         sensor.start()
    ...         sample = sensor.read(timeout_s=2.0)
    ...         sensor.stop()
    >>> round(float(sample.force_n[2]), 6)
    2.0
    """

    def __init__(
        self,
        host: str,
        *,
        port: int = RDT_PORT,
        counts_per_force: float = 1_000_000.0,
        counts_per_torque: float = 1_000_000.0,
        socket_buffer_bytes: int = 4 * 1024 * 1024,
        queue_size: int = 65536,
        silence_timeout_s: float = 1.0,
    ) -> None:
        super().__init__(queue_size=queue_size)
        if not (isinstance(silence_timeout_s, (int, float)) and 0 < silence_timeout_s < math.inf):
            raise InvalidInputError(f"silence_timeout_s must be a positive number of seconds, "
                                    f"got {silence_timeout_s!r}")
        self._silence_timeout = float(silence_timeout_s)
        self._last_heard = time.monotonic()
        if not isinstance(host, str) or not host:
            raise InvalidInputError(f"host must be an IP address or host name, got {host!r}")
        if not isinstance(port, int) or not 0 < port < 65536:
            raise InvalidInputError(f"port must be in 1..65535, got {port!r}")
        for name, value in (("counts_per_force", counts_per_force), ("counts_per_torque", counts_per_torque)):
            if not (isinstance(value, (int, float)) and value > 0 and math.isfinite(value)):
                raise InvalidInputError(f"{name} must be a positive number, got {value!r}")
        if not isinstance(socket_buffer_bytes, int) or socket_buffer_bytes < 4096:
            raise InvalidInputError(f"socket_buffer_bytes must be an int >= 4096, got {socket_buffer_bytes!r}")
        self._address = (host, port)
        self._cpf = float(counts_per_force)
        self._cpt = float(counts_per_torque)
        self._rcvbuf = socket_buffer_bytes
        self._scale = np.array([1 / self._cpf] * 3 + [1 / self._cpt] * 3)
        self._sock: socket.socket | None = None
        self._tracker = SequenceTracker()

    @classmethod
    def from_box(cls, host: str, *, http_port: int = 80, timeout_s: float = 2.0, **kwargs) -> "NetFTSensor":
        """A sensor scaled with the calibration the box itself reports (:func:`fetch_calibration`)."""
        cpf, cpt = fetch_calibration(host, http_port=http_port, timeout_s=timeout_s)
        return cls(host, counts_per_force=cpf, counts_per_torque=cpt, **kwargs)

    def _do_open(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self._rcvbuf)
            sock.settimeout(0.05)
            sock.connect(self._address)  # a connected UDP socket only accepts datagrams from the box
        except OSError as exc:
            sock.close()
            raise DeviceError(f"Net F/T at {self._address[0]}:{self._address[1]}: cannot set up UDP ({exc})") from None
        self._sock = sock

    def _do_close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _send(self, command: RdtCommand) -> None:
        try:
            self._sock.send(encode_request(command))
        except OSError as exc:
            raise DeviceError(f"{self!r}: sending {command.name} failed ({exc})") from None

    def _do_start(self) -> None:
        self._tracker = SequenceTracker()
        # Discard datagrams of an earlier stream still sitting in the socket buffer.
        self._sock.setblocking(False)
        try:
            while True:
                self._sock.recv(65536)
        except (BlockingIOError, OSError):
            pass
        finally:
            self._sock.settimeout(0.05)
        self._last_heard = time.monotonic()
        self._send(RdtCommand.START_REALTIME)

    def _do_stop(self) -> None:
        self._send(RdtCommand.STOP)

    def _do_bias(self) -> None:
        self._send(RdtCommand.SET_SOFTWARE_BIAS)

    def _do_receive(self) -> list[ForceSample]:
        try:
            data = self._sock.recv(65536)
        except socket.timeout:
            silent = time.monotonic() - self._last_heard
            if silent > self._silence_timeout:
                raise DeviceError(
                    f"{self!r}: no data for {silent:.1f} s ({self.stats.received} samples received since the start "
                    "request): the box does not answer (address, firewall, cable?)") from None
            return []
        except ConnectionRefusedError:
            raise DeviceError(f"{self!r}: nothing answers at {self._address[0]}:{self._address[1]} (ICMP refused)")
        self._last_heard = time.monotonic()
        host_t = time.time()
        try:
            records = decode_records(data)
        except ProtocolError:
            self._count("protocol_errors")
            return []
        samples = []
        tracker = self._tracker
        lost0, reordered0, duplicates0 = tracker.lost, tracker.reordered, tracker.duplicates
        status_errors = 0
        for rec in records:
            verdict, sequence = tracker.feed(rec.rdt_sequence)
            if verdict == SequenceTracker.DUPLICATE:
                continue
            if rec.status:
                status_errors += 1
            ft = np.array(rec.counts, dtype=np.float64) * self._scale
            samples.append(ForceSample(ft, sequence, rec.ft_sequence, rec.status, host_t))
        with self._lock:  # one update per datagram: this runs up to 7000 times a second
            c = self._counts
            c["lost"] += tracker.lost - lost0
            c["reordered"] += tracker.reordered - reordered0
            c["duplicates"] += tracker.duplicates - duplicates0
            c["status_errors"] += status_errors
            c["received"] += len(samples)
        return samples

    def __repr__(self) -> str:
        return f"NetFTSensor({self._address[0]}:{self._address[1]})"

"""A simulated ATI Net F/T box: the RDT protocol over real UDP on 127.0.0.1, up to 7 kHz.

It answers the same request bytes as the box (see :mod:`skinstretch.drivers.forcesensor.netft`) and streams 36-byte records
to whoever sent the start request, so :class:`skinstretch.drivers.forcesensor.netft.NetFTSensor` runs against it unchanged.
The load is any function of time (for instance the scene simulator's normal force, see
:func:`normal_force_wrench`); loss, reordering, duplication and garbled datagrams can be injected, seeded.

Time ``t`` given to the load function is seconds since the latest start request.
"""

from __future__ import annotations

import math
import select
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from pydantic import model_validator

from skinstretch.drivers.forcesensor.netft import RdtCommand, RdtRecord, decode_request, encode_record
from skinstretch.drivers.errors import DeviceError, ProtocolError
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import Probability, validated_dataclass
from skinstretch.child_process import stop_child_process

__all__ = ["NetFTBoxProcess", "NetFTFaults", "NetFTSimulator", "SimulatorStats", "normal_force_wrench"]

Wrench = Callable[[float], Sequence[float]]
INTERNAL_RATE_HZ = 7000.0  # the box samples at 7 kHz; ft_sequence counts those samples
_I32_MIN, _I32_MAX = -(1 << 31), (1 << 31) - 1


def normal_force_wrench(normal_force_n: Callable[[float], float]) -> Wrench:
    """A load with only a normal force (+Fz, N) following ``normal_force_n(t)``, e.g. ``SceneRenderer.force_at``."""
    if not callable(normal_force_n):
        raise InvalidInputError(f"normal_force_n must be callable (t -> N), got {normal_force_n!r}")

    def wrench(t: float) -> tuple[float, ...]:
        return (0.0, 0.0, float(normal_force_n(t)), 0.0, 0.0, 0.0)

    return wrench


@validated_dataclass
class NetFTFaults:
    """Faults injected per datagram, drawn from the simulator's seeded generator.

    Attributes
    ----------
    loss_probability : float
        A datagram is not sent (its rdt_sequence is used up: a gap).
    reorder_probability : float
        A datagram is held back and sent after the next one.
    duplicate_probability : float
        A datagram is sent twice.
    garble_probability : float
        A datagram is replaced by random bytes of a wrong length (its sequence number is used up).
    silent : bool
        The box reads every request and sends nothing back, as one behind a firewall that drops its datagrams
        (nothing refuses the requests either, so the driver hears nothing at all).
    """

    loss_probability: Probability = 0.0
    reorder_probability: Probability = 0.0
    duplicate_probability: Probability = 0.0
    garble_probability: Probability = 0.0
    silent: bool = False

    @model_validator(mode="after")
    def _one_fault_at_most(self) -> "NetFTFaults":
        total = self.loss_probability + self.reorder_probability + self.duplicate_probability + self.garble_probability
        if total >= 1:
            raise InvalidInputError(f"fault probabilities must add up to less than 1, got {total!r}")
        return self


@dataclass(frozen=True)
class SimulatorStats:
    """What the simulator did since it was started: datagrams sent and faults injected."""

    requests: int = 0
    bad_requests: int = 0
    sent: int = 0
    lost: int = 0
    reordered: int = 0
    duplicated: int = 0
    garbled: int = 0


class NetFTSimulator:
    """A Net F/T box on a local UDP port. Use as a context manager, or :meth:`start` / :meth:`close`.

    Parameters
    ----------
    rate_hz : float
        Records per second while streaming, up to 7000 (the box's maximum).
    wrench : callable t -> 6 values, optional
        Load (Fx, Fy, Fz N, Tx, Ty, Tz N m) at ``t`` s after the start request; zero by default.
    counts_per_force, counts_per_torque : float
        The box's calibration scale (counts per N, counts per N m).
    noise_n : float
        Standard deviation of Gaussian noise added to the forces, N (torques get ``noise_n`` * 0.01 N m).
    records_per_packet : int
        Records per datagram in buffered mode (command 3); real-time mode (command 2) always sends one.
    faults : NetFTFaults, optional
        Faults to inject.
    seed : int
        Seed of the noise and of the faults.
    host : str
        Address to bind (127.0.0.1).
    port : int
        Port to bind; 0 picks a free one (see :attr:`address`).
    """

    def __init__(
        self,
        *,
        rate_hz: float = 1000.0,
        wrench: Wrench | None = None,
        counts_per_force: float = 1_000_000.0,
        counts_per_torque: float = 1_000_000.0,
        noise_n: float = 0.0,
        records_per_packet: int = 1,
        faults: NetFTFaults | None = None,
        seed: int = 0,
        host: str = "127.0.0.1",
        port: int = 0,
    ) -> None:
        if not (isinstance(rate_hz, (int, float)) and 0 < rate_hz <= INTERNAL_RATE_HZ):
            raise InvalidInputError(f"rate_hz must be in (0, {INTERNAL_RATE_HZ:g}], got {rate_hz!r}")
        if wrench is not None and not callable(wrench):
            raise InvalidInputError(f"wrench must be callable (t -> 6 values), got {wrench!r}")
        for name, value in (("counts_per_force", counts_per_force), ("counts_per_torque", counts_per_torque)):
            if not (isinstance(value, (int, float)) and value > 0 and math.isfinite(value)):
                raise InvalidInputError(f"{name} must be a positive number, got {value!r}")
        if not (noise_n >= 0 and math.isfinite(noise_n)):
            raise InvalidInputError(f"noise_n must be >= 0, got {noise_n!r}")
        if not isinstance(records_per_packet, int) or not 1 <= records_per_packet <= 40:
            raise InvalidInputError(f"records_per_packet must be an int in 1..40, got {records_per_packet!r}")
        if faults is not None and not isinstance(faults, NetFTFaults):
            raise InvalidInputError(f"faults must be a NetFTFaults, got {faults!r}")
        self.rate_hz = float(rate_hz)
        self._wrench = wrench or (lambda t: (0.0,) * 6)
        self._cpf = float(counts_per_force)
        self._cpt = float(counts_per_torque)
        self._noise = float(noise_n)
        self._records_per_packet = records_per_packet
        self._faults = faults or NetFTFaults()
        self._rng = np.random.default_rng(seed)
        self._bind = (host, port)
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._stats = dict.fromkeys(SimulatorStats.__dataclass_fields__, 0)
        self._bias = [0] * 6
        self._boot = time.monotonic()
        self._error: BaseException | None = None
        # streaming state (simulator thread only)
        self._dest = None
        self._remaining = 0
        self._per_packet = 1
        self._t_start = 0.0
        self._n_due = 0
        self._rdt_sequence = 0
        self._held: bytes | None = None

    # -- life cycle
    def start(self) -> "NetFTSimulator":
        """Bind the socket and serve in a background thread. Returns self."""
        if self._thread is not None:
            return self
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(self._bind)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
        except OSError as exc:
            sock.close()
            raise DeviceError(f"Net F/T simulator cannot bind {self._bind[0]}:{self._bind[1]} ({exc})") from None
        sock.setblocking(False)
        self._sock = sock
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="NetFTSimulator", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving and release the port (idempotent)."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> "NetFTSimulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) the simulator listens on."""
        if self._sock is None:
            raise DeviceError("Net F/T simulator is not started")
        return self._sock.getsockname()

    @property
    def stats(self) -> SimulatorStats:
        with self._lock:
            return SimulatorStats(**self._stats)

    @property
    def streaming(self) -> bool:
        return self._dest is not None

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the serving thread, if any."""
        return self._error

    def inject(self, faults: NetFTFaults) -> None:
        """Replace the faults to inject."""
        if not isinstance(faults, NetFTFaults):
            raise InvalidInputError(f"faults must be a NetFTFaults, got {faults!r}")
        self._faults = faults

    def load_at(self, t: float) -> np.ndarray:
        """The noise-free load (6,) at ``t`` s after the start request, N and N m."""
        return np.asarray(self._wrench(t), dtype=np.float64).reshape(6)

    # -- serving thread
    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._stats[name] += n

    def _serve(self) -> None:
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if self._dest is not None:
                    next_due = self._t_start + self._n_due * self._per_packet / self.rate_hz
                    wait = max(0.0, next_due - now)
                else:
                    wait = 0.05
                readable, _, _ = select.select([self._sock], [], [], min(wait, 0.05))
                if readable:
                    self._handle_requests()
                if self._dest is not None:
                    self._send_due(time.monotonic())
        except BaseException as exc:  # noted for the owner; the socket then goes quiet like a dead box
            self._error = exc

    def _handle_requests(self) -> None:
        while True:
            try:
                data, addr = self._sock.recvfrom(2048)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:  # ICMP from a client that went away; irrelevant to UDP serving
                continue
            self._count("requests")
            try:
                command, count = decode_request(data)
            except ProtocolError:
                self._count("bad_requests")
                continue
            if command in (RdtCommand.START_REALTIME, RdtCommand.START_BUFFERED):
                self._dest = addr
                self._remaining = count  # 0: until stopped
                self._per_packet = self._records_per_packet if command == RdtCommand.START_BUFFERED else 1
                self._t_start = time.monotonic()
                self._n_due = 0
                self._rdt_sequence = 0
                self._held = None
            elif command == RdtCommand.STOP:
                self._dest = None
                self._held = None
            elif command == RdtCommand.SET_SOFTWARE_BIAS:
                t = time.monotonic() - self._t_start if self._dest is not None else 0.0
                self._bias = self._raw_counts(t)

    def _raw_counts(self, t: float) -> list[int]:
        # Plain Python floats: this runs up to 7000 times a second, where numpy's per-call overhead dominates.
        w = [float(v) for v in self._wrench(t)]
        if len(w) != 6 or not all(math.isfinite(v) for v in w):
            raise InvalidInputError(f"wrench({t:g}) must return 6 finite values, got {w!r}")
        if self._noise > 0:
            n = self._rng.normal(0.0, self._noise, 6)
            w = [w[i] + float(n[i]) * (1.0 if i < 3 else 0.01) for i in range(6)]
        cpf, cpt = self._cpf, self._cpt
        return [round(w[i] * (cpf if i < 3 else cpt)) for i in range(6)]

    def _record(self, t: float) -> bytes:
        self._rdt_sequence = (self._rdt_sequence + 1) % (1 << 32)
        raw = self._raw_counts(t)
        bias = self._bias
        counts = tuple(min(max(raw[i] - bias[i], _I32_MIN), _I32_MAX) for i in range(6))  # the ADC saturates
        ft_sequence = int((time.monotonic() - self._boot) * INTERNAL_RATE_HZ) % (1 << 32)
        return encode_record(RdtRecord(self._rdt_sequence, ft_sequence, 0, counts))

    def _send_due(self, now: float) -> None:
        # Catch up on every packet due, so a briefly starved simulator still keeps the sequence and the rate,
        # but in bursts of at most 64 so that a stop request is never kept waiting behind a long backlog.
        for _ in range(64):
            if self._dest is None:
                return
            t_due = self._n_due * self._per_packet / self.rate_hz
            if self._t_start + t_due > now:
                return
            packet = b"".join(
                self._record(t_due + i / self.rate_hz) for i in range(self._per_packet)
            )
            self._n_due += 1
            self._emit(packet)
            if self._remaining:
                self._remaining -= 1
                if self._remaining == 0:
                    self._dest = None

    def _emit(self, packet: bytes) -> None:
        f = self._faults
        if f.silent:
            self._count("lost")
            return
        r = self._rng.random() if (f.loss_probability or f.reorder_probability or f.duplicate_probability
                                   or f.garble_probability) else 1.0
        held, self._held = self._held, None
        if r < f.loss_probability:
            self._count("lost")
        elif r < f.loss_probability + f.garble_probability:
            size = int(self._rng.integers(1, 80))
            if size % 36 == 0:
                size += 1
            self._send(self._rng.bytes(size))
            self._count("garbled")
        elif r < f.loss_probability + f.garble_probability + f.reorder_probability and held is None:
            self._held = packet  # sent after the next one
            self._count("reordered")
        else:
            self._send(packet)
            if r < f.loss_probability + f.garble_probability + f.reorder_probability + f.duplicate_probability:
                self._send(packet)
                self._count("duplicated")
        if held is not None:
            self._send(held)

    def _send(self, data: bytes) -> None:
        try:
            self._sock.sendto(data, self._dest)
            self._count("sent")
        except BlockingIOError:
            # The kernel send buffer is full (receiver gone or far too slow): the datagram is lost, as on a wire.
            self._count("lost")
        except ConnectionRefusedError:
            pass  # the client's port is closed; UDP does not care


class NetFTBoxProcess:
    """The simulated box as a program of its own (``python -m skinstretch.simulators.netft_box``), as a real box is a
    separate machine: the driver's CPU use is then its own. A context manager giving the box's ``(host, port)``; on
    exit the program is stopped and :attr:`stats` holds what it did (sent, lost...).

    >>> # with NetFTBoxProcess(rate_hz=1000.0, force_n=2.5) as (host, port):
    >>> #     with NetFTSensor(host, port=port) as sensor: ...
    """

    def __init__(self, *, rate_hz: float, force_n: float = 0.0, loss_probability: float = 0.0, seed: int = 0) -> None:
        self.args = ["--port", "0", "--rate", str(float(rate_hz)), "--force", str(float(force_n)),
                     "--loss", str(float(loss_probability)), "--seed", str(int(seed))]
        self.stats: SimulatorStats | None = None
        self._proc: subprocess.Popen | None = None

    def __enter__(self) -> tuple[str, int]:
        self._proc = subprocess.Popen([sys.executable, "-m", __name__, *self.args], stdout=subprocess.PIPE, text=True)
        line = self._proc.stdout.readline()  # "host port" once bound
        try:
            host, port = line.split()
            return host, int(port)
        except ValueError:
            stop_child_process(self._proc)
            raise DeviceError(f"the Net F/T box program did not start (it said {line.strip()!r})") from None

    def __exit__(self, *exc) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        tail = stop_child_process(proc) or ""  # the program's last line: what it did, as key=value pairs
        counts = dict(kv.split("=", 1) for kv in tail.split() if "=" in kv)
        try:
            self.stats = SimulatorStats(**{k: int(v) for k, v in counts.items()})
        except (TypeError, ValueError):
            self.stats = None  # killed before it could say


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m skinstretch.simulators.netft_box``: serve a simulated Net F/T box until interrupted."""
    import argparse
    import signal

    p = argparse.ArgumentParser(prog="python -m skinstretch.simulators.netft_box", description=__doc__.splitlines()[0])
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=49152, help="UDP port (0: any free one, printed)")
    p.add_argument("--rate", type=float, default=1000.0, help="records per second (<= 7000)")
    p.add_argument("--force", type=float, default=0.0, help="constant normal force Fz, N")
    p.add_argument("--loss", type=float, default=0.0, help="datagram loss probability")
    p.add_argument("--silent", action="store_true", help="read requests, answer nothing (a firewalled box)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    sim = NetFTSimulator(
        rate_hz=args.rate,
        wrench=normal_force_wrench(lambda t: args.force),
        faults=NetFTFaults(loss_probability=args.loss, silent=args.silent),
        seed=args.seed,
        host=args.host,
        port=args.port,
    )
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    with sim:
        print(f"{sim.address[0]} {sim.address[1]}", flush=True)
        try:
            while not done.wait(0.5):
                if sim.error is not None:
                    raise sim.error
        except KeyboardInterrupt:
            pass
        stats = sim.stats
    print(" ".join(f"{k}={v}" for k, v in stats.__dict__.items()), flush=True)  # what the box did, for benches
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Build the devices of a rig: the ONLY place in skinstretch that chooses a real or a simulated device.

A :class:`skinstretch.experiments.protocol.Rig` names, for the camera, the force sensor and the display, either ``sim`` (the
default) or the real driver. :class:`RigDevices` turns it into objects the runner and playback use through small,
uniform adapters:

* ``camera_for(trial=, protocol=, n_frames=)`` -> a :class:`skinstretch.drivers.camera.base.Camera`-like object whose
  ``start()`` opens it in the protocol's mode and ``stop()`` releases it. A simulated camera renders the trial's
  surface (``Surface.scene_name``: ``flatL``, ``ridgeL``, ``valleyL``...) with the scene simulator.
* ``force`` -> a :class:`ForceSource` (``begin``/``end``/``read_block``/``latest``), or None.
* ``display`` -> a :class:`DisplayAdapter` (``rest``, ``measured_positions_um``) and ``display_device()`` the
  :class:`skinstretch.drivers.display.base.TactileDisplay` itself, for playback.

Device modules are imported when a device is built, so a rig that does not use Aravis never imports ``gi``.
"""

from __future__ import annotations

import itertools
import threading
from typing import Any

import numpy as np

from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.errors import DeviceError
from skinstretch.processing.errors import InvalidInputError
from skinstretch.experiments.protocol import Rig

__all__ = ["RigDevices", "ForceSource", "DisplayAdapter", "make_display", "is_sim_url", "sim_display_url",
           "subset_truth"]


def subset_truth(truth, rows: np.ndarray):
    """The truth of the recorded frames only: ``rows`` are source frame indices (from the frame ids)."""
    from skinstretch.drivers.session_file import SessionTruth  # noqa: PLC0415

    rows = np.asarray(rows, dtype=np.int64)
    per_frame = {"feature_x", "feature_y", "feature_visible", "displacement", "displacement_valid", "rigid", "strain"}
    arrays = {
        name: (np.asarray(getattr(truth, name))[rows] if name in per_frame else getattr(truth, name))
        for name in SessionTruth._ARRAYS
    }
    return SessionTruth(**arrays, attrs=dict(truth.attrs))

_sim_names = itertools.count()


# ----------------------------------------------------------------------------------------------- rendering


def render_scene(scene_yaml: str, seed: int):
    """Render every frame of a scene and its ground truth (runs in a worker process for a simulated camera)."""
    from skinstretch.simulators.scene import SceneRenderer, parse_scene  # noqa: PLC0415

    scene = parse_scene(scene_yaml, source="<trial scene>")
    renderer = SceneRenderer(scene, seed=seed)
    frames = np.stack([renderer.render_frame(k) for k in range(scene.n_frames)])
    truth = renderer.truth()
    truth.attrs.update({"scene": scene.name, "scene_yaml": scene_yaml, "seed": int(seed)})
    return frames, truth


# ------------------------------------------------------------------------------------------------------ force


class ForceSource:
    """Uniform view of a force sensor for the recorder (blocks of samples) and playback (latest sample).

    Wraps any object with ``start()``, ``stop()`` and ``read(timeout_s)`` returning a sample with ``t`` /
    ``timestamp_s`` and a 6-vector ``wrench`` / ``values`` (Fx Fy Fz N, Tx Ty Tz N m), or a ``read_block`` method.
    """

    def __init__(self, sensor: Any, *, description: str) -> None:
        self.sensor = sensor
        self.description = description
        self._latest: np.ndarray | None = None
        self._lock = threading.Lock()
        self._running = False
        self._bg: threading.Thread | None = None
        self._bg_stop = threading.Event()
        self._first = threading.Event()

    def begin(self) -> None:
        if not self._running:
            if not getattr(self.sensor, "is_open", True):
                self.sensor.open()
            self.sensor.start()
            self._running = True

    def end(self) -> None:
        if self._running:
            self._running = False
            self.sensor.stop()

    def read_block(self, *, timeout_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Samples that arrived (t (k,), wrench (k, 6)); may be empty after ``timeout_s``."""
        if hasattr(self.sensor, "drain"):
            t, data = _read_drain(self.sensor, timeout_s)
        else:
            t, data = _read_samples(self.sensor, timeout_s)
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        data = np.asarray(data, dtype=np.float64).reshape(-1, 6)
        if len(t):
            with self._lock:
                self._latest = data[-1].copy()
        return t, data

    def latest(self) -> np.ndarray | None:
        """The most recent wrench (6,), reading the sensor in the background while playback runs."""
        if self._bg is None:
            self.begin()
            self._bg_stop.clear()
            self._bg = threading.Thread(target=self._background, name="force-latest", daemon=True)
            self._bg.start()
            self._first.wait(0.5)
        with self._lock:
            return None if self._latest is None else self._latest.copy()

    def _background(self) -> None:
        while not self._bg_stop.is_set():
            try:
                t, _ = self.read_block(timeout_s=0.05)
            except (DeviceError, OSError):
                with self._lock:
                    self._latest = None
                return
            if len(t):
                self._first.set()

    def stop_background(self) -> None:
        if self._bg is not None:
            self._bg_stop.set()
            self._bg.join(1.0)
            self._bg = None

    def close(self) -> None:
        self.stop_background()
        try:
            self.end()
        finally:
            close = getattr(self.sensor, "close", None)
            if close is not None:
                close()


def _read_drain(sensor: Any, timeout_s: float) -> tuple[np.ndarray, np.ndarray]:
    """A :class:`skinstretch.drivers.forcesensor.base.ForceSensor`: wait for one sample, then take all that are queued."""
    from skinstretch.drivers.errors import DeviceTimeoutError  # noqa: PLC0415

    try:
        first = sensor.read(timeout_s=timeout_s)
    except DeviceTimeoutError:
        return np.zeros(0), np.zeros((0, 6))
    rest = sensor.drain()
    t = np.concatenate([[first.host_timestamp_s], rest["t"]])
    ft = np.concatenate([np.asarray(first.ft, float).reshape(1, 6), rest["ft"].reshape(-1, 6)])
    return t, ft


def _read_samples(sensor: Any, timeout_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Drain what a sample-at-a-time sensor has (first read waits up to ``timeout_s``)."""
    ts, rows = [], []
    wait = timeout_s
    for _ in range(256):
        try:
            s = sensor.read(timeout_s=wait)
        except TimeoutError:
            break
        if s is None:
            break
        ts.append(float(getattr(s, "host_timestamp_s", getattr(s, "timestamp_s", getattr(s, "t", np.nan)))))
        wrench = getattr(s, "wrench", None)
        if wrench is None:
            wrench = np.concatenate([np.asarray(getattr(s, "force_n")), np.asarray(getattr(s, "torque_nm"))])
        rows.append(np.asarray(wrench, float).reshape(6))
        wait = 0.0
    return np.array(ts), np.array(rows).reshape(-1, 6)


# ---------------------------------------------------------------------------------------------------- display


class DisplayAdapter:
    """What the recorder needs of the display: send it to rest, read where the contactors are."""

    def __init__(self, display: Any, *, description: str) -> None:
        self.device = display
        self.description = description

    def rest(self) -> None:
        self.device.rest()

    def measured_positions_um(self) -> np.ndarray:
        acks = getattr(self.device, "acks", None)
        if acks:
            return np.asarray(acks[-1].measured_um, dtype=np.float32)
        return np.zeros((10, 10), np.float32)

    def close(self) -> None:
        self.device.close()


def sim_display_url(*, seed: int = 0, load_n_per_mm: float = 0.15, faults: str = "", name: str | None = None) -> str:
    """Start a simulated STReSS (firmware twin behind a paced link) and return its ``stresssim://`` URL.

    ``load_n_per_mm`` is the finger's lateral stiffness on every contactor (the bender deflects less under it).
    """
    from skinstretch.simulators import stress_links  # noqa: PLC0415 - simulators are imported only for a sim rig

    if not (np.isfinite(load_n_per_mm) and load_n_per_mm >= 0):
        raise InvalidInputError(f"load_n_per_mm must be >= 0, got {load_n_per_mm!r}")
    stress_links.register_url_handler()
    link = stress_links.make_link(seed=seed, faults=faults)
    link.firmware.benders.set_load(load_n_per_mm)
    return stress_links.attach(name or f"rig{next(_sim_names)}", link)


def is_sim_url(url: str | None) -> bool:
    """Whether a display URL names the firmware twin (``stresssim://NAME?baud=...&faults=...&seed=...&load=...``)."""
    return bool(url) and url.startswith("stresssim://")


def make_display(url: str, **options: Any):
    """A :class:`skinstretch.drivers.display.stress.StressDisplay` on a serial port or pyserial URL."""
    from skinstretch.drivers.display.stress import StressDisplay  # noqa: PLC0415
    from skinstretch.drivers.display.transports import SerialTransport  # noqa: PLC0415

    baud = int(options.pop("baudrate", 2_000_000))
    return StressDisplay(SerialTransport(url, baudrate=baud), **options)


# ----------------------------------------------------------------------------------------------------- camera


class _TrialCamera:
    """Opens a camera in the protocol's mode on ``start`` and releases it on ``stop`` (one per trial)."""

    def __init__(self, camera: Any, mode, *, keep_open: bool = False) -> None:
        self.camera = camera
        self.mode = mode
        self.keep_open = keep_open
        self.truth = None  # SessionTruth of a simulated camera (row k = source frame k)

    def start(self) -> None:
        if not self.camera.is_open:
            self.camera.open()
        self.camera.set_mode(self.mode)
        self.camera.start()

    def read(self, timeout_s: float):
        return self.camera.read(timeout_s=timeout_s)

    def stop(self) -> None:
        try:
            if self.camera.is_streaming:
                self.camera.stop()
        finally:
            if not self.keep_open:
                self.camera.close()

    @property
    def stats(self):
        return self.camera.stats


# -------------------------------------------------------------------------------------------------------- rig


class RigDevices:
    """The devices of a rig, built on first use and closed by :meth:`close`."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self._force: ForceSource | None = None
        self._force_built = False
        self._display: DisplayAdapter | None = None
        self._display_built = False
        self._aravis = None
        self._sim_servers: list[Any] = []
        self._render_pool = None
        self._renders: dict[tuple[str, int], Any] = {}

    def describe(self) -> dict[str, str]:
        r = self.rig
        return {
            "camera": r.camera.kind + (f":{r.camera.device}" if r.camera.device else ""),
            "force": r.force.kind + (f":{r.force.address}" if r.force.address else ""),
            "display": r.display.kind + (f":{r.display.url}" if r.display.url else ""),
        }

    # -- camera
    def camera_for(self, *, trial, protocol, n_frames: int):
        spec = self.rig.camera
        mode = CAMERA_MODES[protocol.camera_mode]
        if spec.kind == "sim":
            return self._sim_camera(trial=trial, protocol=protocol, n_frames=n_frames, mode=mode)
        if spec.kind == "aravis":
            from skinstretch.drivers.camera.aravis import AravisCamera  # noqa: PLC0415

            if self._aravis is None:
                self._aravis = AravisCamera.fake(**spec.options) if spec.device == "Fake_1" else AravisCamera(
                    spec.device, **spec.options
                )
            return _TrialCamera(self._aravis, mode, keep_open=True)
        if spec.kind == "replay":
            from skinstretch.drivers.camera.replay import ReplayCamera  # noqa: PLC0415

            return _TrialCamera(ReplayCamera(spec.device, **spec.options), mode)
        if spec.kind == "v4l2":
            from skinstretch.drivers.camera.v4l2 import V4L2Camera  # noqa: PLC0415

            device: int | str = int(spec.device) if spec.device and spec.device.isdigit() else (spec.device or 0)
            return _TrialCamera(V4L2Camera(device, **spec.options), mode)
        raise DeviceError(f"camera kind {spec.kind!r} is not supported")

    def _sim_scene(self, *, trial, protocol, n_frames: int):
        """The simulator scene of a trial, adapted to it.

        The protocol's camera mode and field of view, the surface's shape, and the scene's bulk motion compressed
        (never stretched) into the trial's duration, so a short trial still crosses the whole ridge or valley
        (faster sliding, closer to the seed's 2.8-5.3 mm/s, seed 6.1).
        """
        try:
            from skinstretch.simulators.scene import load_scene  # noqa: PLC0415
        except ImportError as exc:
            raise DeviceError(f"the simulated camera is not available ({exc})") from None
        mode = CAMERA_MODES[protocol.camera_mode]
        surface = trial.surface
        scene = load_scene(surface.scene_name)
        scene_duration = scene.n_frames / CAMERA_MODES[scene.camera.mode].fps
        scale = min(1.0, (n_frames / mode.fps) / scene_duration)
        motion = scene.motion.model_copy(
            update={"keyframes": [(t * scale, u, s_, th) for t, u, s_, th in scene.motion.keyframes]}
        )
        update: dict[str, Any] = {
            "n_frames": int(n_frames),
            "camera": scene.camera.model_copy(update={"mode": mode.name, "field_of_view_mm": protocol.field_of_view_mm}),
            "motion": motion,
        }
        if surface.kind in ("flat", "ridge", "valley") and surface.scene is None:
            update["surface"] = scene.surface.model_copy(
                update={"kind": surface.kind, "width_mm": surface.width_mm, "height_mm": surface.height_mm}
            )
        return scene.model_copy(update=update)

    def prepare(self, *, protocol, trials) -> None:
        """Start rendering the simulated camera's frames of ``trials`` in worker processes (no-op for a real
        camera), so that rendering — slower than the camera rate — overlaps the recording of earlier trials."""
        if self.rig.camera.kind != "sim" or len(trials) < 2:
            return  # one trial: nothing to overlap, and starting worker processes costs seconds
        from skinstretch.experiments.process_lifetime import worker_pool  # noqa: PLC0415

        if self._render_pool is None:  # its workers die with this process, whatever kills it
            self._render_pool = worker_pool(min(2, len(trials)))
        mode = CAMERA_MODES[protocol.camera_mode]
        for trial in trials:
            n = max(1, int(round(trial.spec.duration_s * mode.fps)))
            scene = self._sim_scene(trial=trial, protocol=protocol, n_frames=n)
            seed = self.rig.camera.seed + trial.index
            self._renders[(trial.dirname, n)] = self._render_pool.submit(render_scene, scene.to_yaml(), seed)

    def _sim_camera(self, *, trial, protocol, n_frames: int, mode):
        """A simulated camera streaming the trial's surface at the camera's real rate, with the ground truth."""
        from skinstretch.simulators.simulated_camera import SimulatedCamera  # noqa: PLC0415

        spec = self.rig.camera
        future = self._renders.pop((trial.dirname, n_frames), None)
        rendered = None
        if future is not None:
            try:
                rendered = future.result()
            except Exception:  # a worker died (e.g. no __main__ guard in the caller): render here instead
                rendered = None
        if rendered is not None:
            frames, truth = rendered
        else:
            scene = self._sim_scene(trial=trial, protocol=protocol, n_frames=n_frames)
            frames, truth = render_scene(scene.to_yaml(), spec.seed + trial.index)
        options = dict(spec.options)
        if isinstance(options.get("faults"), dict):  # a fault drill from a rig file: {faults: {stall_at_frame: 20}}
            from skinstretch.simulators.simulated_camera import CameraFaults  # noqa: PLC0415

            options["faults"] = CameraFaults(**options["faults"])
        cam = SimulatedCamera(frames.__getitem__, mode, n_frames=n_frames, loop=False, seed=spec.seed + trial.index,
                              **options)
        trial_cam = _TrialCamera(cam, mode)
        trial_cam.truth = truth
        return trial_cam

    # -- force
    @property
    def force(self) -> ForceSource | None:
        if not self._force_built:
            self._force_built = True
            self._force = self._build_force()
        return self._force

    def _build_force(self) -> ForceSource | None:
        spec = self.rig.force
        if spec.kind == "none":
            return None
        from skinstretch.drivers.forcesensor.netft import NetFTSensor  # noqa: PLC0415

        if spec.kind == "sim":
            from skinstretch.simulators.netft_box import NetFTSimulator, normal_force_wrench  # noqa: PLC0415

            opts = dict(spec.options)
            force_n = float(opts.pop("normal_force_n", 1.5))  # a fingertip pressing lightly (seed 6.3.3)
            opts.setdefault("noise_n", 0.02)
            # 250 Hz is plenty for a force ceiling and keeps the in-process twin light (it shares the GIL with
            # the display stream).
            opts.setdefault("rate_hz", 250.0)
            server = NetFTSimulator(seed=spec.seed, wrench=normal_force_wrench(lambda t: force_n), **opts)
            server.start()
            self._sim_servers.append(server)
            host, port = server.address
            return ForceSource(NetFTSensor(host, port=port), description=f"sim Net F/T at {host}:{port}")
        return ForceSource(NetFTSensor(spec.address, **spec.options), description=f"Net F/T at {spec.address}")

    # -- display
    @property
    def display(self) -> DisplayAdapter | None:
        if not self._display_built:
            self._display_built = True
            spec = self.rig.display
            if spec.kind == "none":
                self._display = None
            else:
                if spec.kind == "sim":
                    opts = dict(spec.options)
                    url = sim_display_url(seed=spec.seed, load_n_per_mm=float(opts.pop("load_n_per_mm", 0.15)),
                                          faults=str(opts.pop("faults", "")))
                    # The twin shares this process (and a busy machine's cores): a 0.25 s watchdog instead of the
                    # hardware's 50 ms keeps a starved host from tripping it; a real display keeps its own value.
                    opts.setdefault("watchdog_s", 0.25)
                    device = make_display(url, **opts)
                    device.zero()  # the twin's sensors have offsets, removed by ZERO like the real display's
                elif is_sim_url(spec.url):
                    # the firmware twin named by a URL, with its fault switches (stresssim://NAME?faults=...)
                    from skinstretch.simulators import stress_links  # noqa: PLC0415

                    stress_links.register_url_handler()
                    url = spec.url
                    device = make_display(url, **{"watchdog_s": 0.25, **spec.options})
                    device.zero()
                else:
                    url = spec.url
                    device = make_display(url, **spec.options)
                self._display = DisplayAdapter(device, description=f"{spec.kind}:{url}")
        return self._display

    def display_device(self):
        """The TactileDisplay itself (for playback); DeviceError when the rig has none."""
        if self.display is None:
            raise DeviceError("the rig has no display (display.kind: none)")
        return self.display.device

    def close(self, *, now: bool = False) -> None:
        """Close every device; ``now``: a command asked to stop does not wait for the scene renders under way."""
        from skinstretch.experiments.process_lifetime import end_pool_now  # noqa: PLC0415

        pool = self._render_pool
        errors = []
        for closer in (
            (lambda: self._force.close()) if self._force is not None else None,
            (lambda: self._display.close()) if self._display is not None else None,
            (lambda: self._aravis.close()) if self._aravis is not None else None,
            ((lambda: end_pool_now(pool)) if now else (lambda: pool.shutdown(wait=True, cancel_futures=True)))
            if pool else None,
            *[(lambda s=s: s.close()) for s in self._sim_servers],
        ):
            if closer is None:
                continue
            try:
                closer()
            except Exception as exc:  # closing must go on for the other devices
                errors.append(f"{type(exc).__name__}: {exc}")
        self._force = self._display = self._aravis = self._render_pool = None
        self._sim_servers = []
        if errors:
            raise DeviceError("closing the rig: " + "; ".join(errors))

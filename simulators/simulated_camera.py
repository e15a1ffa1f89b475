"""A simulated camera: any frame source (e.g. the scene simulator) streamed in real time at a mode's rate.

:class:`SimulatedCamera` implements :class:`skinstretch.drivers.camera.base.Camera`, so everything that reads a camera reads
it unchanged. Frame ``k`` is due at ``k / fps`` seconds after :meth:`start` on a replaceable :class:`Clock`
(:class:`~skinstretch.drivers.camera.base.ManualClock` steps it by hand in tests). Faults can be injected
(:class:`CameraFaults`): dropped frames (gaps in the frame ids), a stall (no frames for a while, the frames due
meanwhile are lost, or the camera goes silent for good) and a device error at a given frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import field
from typing import Callable

import numpy as np
from pydantic import Field

from skinstretch.drivers.camera.base import Camera, Clock, EndOfStreamError, Frame, MonotonicClock
from skinstretch.drivers.camera_modes import CameraMode
from skinstretch.drivers.errors import DeviceError, DeviceTimeoutError
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import Float, NonNegativeInt, Probability, validated_dataclass

__all__ = ["CameraFaults", "SimulatedCamera"]

FrameSource = Callable[[int], np.ndarray]


@validated_dataclass
class CameraFaults:
    """Faults a :class:`SimulatedCamera` injects (all off by default).

    Attributes
    ----------
    drop_frames : frozenset of int
        Frame indices never delivered (their ids are skipped, as a lost GigE frame would be).
    drop_probability : float
        Probability in [0, 1) that any other frame is dropped (seeded by the camera's ``seed``).
    stall_at_frame : int or None
        Frame index at which the camera stops delivering for ``stall_s`` seconds.
    stall_s : float
        Stall duration in seconds; ``math.inf`` means the camera never delivers again.
    error_at_frame : int or None
        Frame index at which the device reports a timeout (a DeviceTimeoutError from :meth:`Camera.read`
        once the earlier frames have been read).
    """

    drop_frames: frozenset[int] = field(default_factory=frozenset)
    drop_probability: Probability = 0.0
    stall_at_frame: NonNegativeInt | None = None
    stall_s: Float = Field(default=math.inf, gt=0)  # math.inf: a dead camera
    error_at_frame: NonNegativeInt | None = None


class SimulatedCamera(Camera):
    """Stream ``frame_source(k)`` at ``mode.fps`` in real time (or on a manual clock).

    Parameters
    ----------
    frame_source : callable int -> (H, W) uint8 or uint16 array
        Renders frame ``k``. Must be thread-safe for sequential calls from the acquisition thread.
    mode : CameraMode
        Image size (must match the source's frames) and frame rate. ``set_mode`` may later change the rate.
    n_frames : int, optional
        Number of distinct frames of the source; frames are looped (``loop=True``) or the stream ends.
    loop : bool
        With ``n_frames``: loop forever (frame ``k`` shows source frame ``k % n_frames``) or end with
        :class:`~skinstretch.drivers.camera.base.EndOfStreamError` after the last frame.
    clock : Clock, optional
        Time source; real time (:class:`~skinstretch.drivers.camera.base.MonotonicClock`) by default.
    faults : CameraFaults, optional
        Faults to inject.
    seed : int
        Seed of the random drops.
    queue_size : int
        Frames held between the acquisition thread and :meth:`read`.

    Examples
    --------
    >>> import numpy as np
    >>> from skinstretch.drivers.camera import ManualClock
    >>> from skinstretch.drivers.camera_modes import CAMERA_MODES
    >>> clock = ManualClock()
    >>> source = lambda k: np.full((100, 640), k, np.uint8)
    >>> with SimulatedCamera(source, CAMERA_MODES["strip"], clock=clock) as cam:
    ...     cam.start()
    ...     clock.advance(2.5 / 220)  # frames 0, 1 and 2 fall due
    ...     [f.frame_id for f in cam.frames(3)]
    [0, 1, 2]
    """

    def __init__(
        self,
        frame_source: FrameSource,
        mode: CameraMode,
        *,
        n_frames: int | None = None,
        loop: bool = True,
        clock: Clock | None = None,
        faults: CameraFaults | None = None,
        seed: int = 0,
        queue_size: int = 256,
    ) -> None:
        super().__init__(queue_size=queue_size)
        if not callable(frame_source):
            raise InvalidInputError(f"frame_source must be callable (int -> image), got {frame_source!r}")
        if not isinstance(mode, CameraMode):
            raise InvalidInputError(f"mode must be a CameraMode, got {mode!r}")
        if n_frames is not None and (not isinstance(n_frames, int) or n_frames < 1):
            raise InvalidInputError(f"n_frames must be a positive int or None, got {n_frames!r}")
        if faults is not None and not isinstance(faults, CameraFaults):
            raise InvalidInputError(f"faults must be a CameraFaults, got {faults!r}")
        self._source = frame_source
        self._initial_mode = mode
        self._n_source = n_frames
        self._loop = loop
        self._clock = clock if clock is not None else MonotonicClock()
        self._faults = faults or CameraFaults()
        self._seed = seed
        self._frame_shape: tuple[int, int] | None = None
        self._next = 0
        self._lost = 0
        self._t0 = 0.0
        self._epoch_offset = 0.0
        self._rng = np.random.default_rng(seed)

    @classmethod
    def from_scene(
        cls,
        scene,
        *,
        seed: int = 0,
        prerender: bool | None = None,
        **kwargs,
    ) -> "SimulatedCamera":
        """A camera showing a scene of the scene simulator (``skinstretch.simulators.scene``), looped.

        Parameters
        ----------
        scene : str, scene object or SceneRenderer
            A scene name for ``skinstretch.simulators.scene.load_scene``, an already loaded scene, or a ready renderer
            (anything with ``render_frame``, ``camera_mode`` and ``n_frames``; its own seed then applies).
        seed : int
            Seed of the renderer (and of the random drops).
        prerender : bool, optional
            Render every frame up front. By default this is done when rendering one frame takes longer than
            half a frame period (e.g. strip mode at 220 Hz), so the stream keeps its rate.
        **kwargs
            Passed to the constructor (clock, faults, loop, queue_size).
        """
        if all(hasattr(scene, a) for a in ("render_frame", "camera_mode", "n_frames")):
            renderer = scene
        else:
            from skinstretch.simulators import scene as scene_module  # imported here: only this constructor needs it

            if isinstance(scene, str):
                scene = scene_module.load_scene(scene)
            renderer = scene_module.SceneRenderer(scene, seed=seed)
        mode = renderer.camera_mode
        n = int(renderer.n_frames)
        t = time.perf_counter()
        first = np.ascontiguousarray(renderer.render_frame(0))
        render_s = time.perf_counter() - t
        if prerender is None:
            prerender = render_s > 0.5 * mode.period_s
        if prerender:
            frames = np.empty((n, *first.shape), dtype=first.dtype)
            frames[0] = first
            for k in range(1, n):
                frames[k] = renderer.render_frame(k)
            source: FrameSource = frames.__getitem__
        else:
            cache = {0: first}

            def source(k: int) -> np.ndarray:
                if k not in cache:
                    cache[k] = np.ascontiguousarray(renderer.render_frame(k))
                return cache[k]

        return cls(source, mode, n_frames=n, seed=seed, **kwargs)

    @classmethod
    def from_frames(cls, frames: np.ndarray, fps: float, **kwargs) -> "SimulatedCamera":
        """A camera streaming an in-memory stack of frames (N, H, W) at ``fps`` Hz."""
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.shape[0] < 1 or frames.dtype not in (np.uint8, np.uint16):
            raise InvalidInputError(f"frames must be (N, H, W) uint8 or uint16, got {frames.dtype} {frames.shape}")
        mode = CameraMode("custom", frames.shape[2], frames.shape[1], float(fps))
        return cls(frames.__getitem__, mode, n_frames=frames.shape[0], **kwargs)

    @property
    def clock(self) -> Clock:
        return self._clock

    def inject(self, faults: CameraFaults) -> None:
        """Replace the faults to inject (takes effect from the next frame)."""
        if not isinstance(faults, CameraFaults):
            raise InvalidInputError(f"faults must be a CameraFaults, got {faults!r}")
        self._faults = faults

    # -- Camera
    def _do_open(self) -> None:
        frame = self._render(0)
        self._frame_shape = frame.shape
        self._do_set_mode(self._initial_mode)
        self._mode = self._initial_mode

    def _do_close(self) -> None:
        pass

    def _do_set_mode(self, mode: CameraMode) -> None:
        if self._frame_shape is not None and (mode.height, mode.width) != self._frame_shape:
            raise InvalidInputError(
                f"mode {mode.name} is {mode.width}x{mode.height} but the frame source renders "
                f"{self._frame_shape[1]}x{self._frame_shape[0]} frames"
            )

    def _do_start(self) -> None:
        self._next = 0
        self._lost = 0
        self._rng = np.random.default_rng(self._seed)
        self._t0 = self._clock.now()
        self._epoch_offset = time.time() - self._t0

    def _do_stop(self) -> None:
        pass

    def _device_drops(self) -> int:
        # The simulator knows what it dropped at once; frame-id gaps only show when a later frame arrives.
        return self._lost

    def _do_grab(self) -> Frame | None:
        k = self._next
        period = self._mode.period_s
        due = self._t0 + k * period
        faults = self._faults
        if not self._clock.wait_until(due, self._stop_event):
            return None
        if self._n_source is not None and not self._loop and k >= self._n_source:
            raise EndOfStreamError(f"{self!r}: all {self._n_source} frames delivered")
        if faults.error_at_frame is not None and k == faults.error_at_frame:
            raise DeviceTimeoutError(f"{self!r}: simulated device timeout at frame {k}")
        if faults.stall_at_frame is not None and k == faults.stall_at_frame:
            resume = due + faults.stall_s
            if math.isinf(resume):
                self._stop_event.wait()  # silent for good: read() times out, stop() ends the thread
                return None
            if not self._clock.wait_until(resume, self._stop_event):
                return None
            # Frame k and those that fell due during the stall are lost (their ids are skipped).
            self._next = k + max(1, math.ceil((resume - due) / period - 1e-9))
            self._lost += self._next - k
            return None
        self._next = k + 1
        if k in faults.drop_frames or (faults.drop_probability > 0 and self._rng.random() < faults.drop_probability):
            self._lost += 1
            return None
        image = self._render(k if self._n_source is None else k % self._n_source)
        device_t = k * period
        return Frame(image, k, device_t, self._epoch_offset + self._clock.now())

    def _render(self, index: int) -> np.ndarray:
        try:
            image = self._source(index)
        except Exception as exc:
            raise DeviceError(f"{self!r}: frame source failed at frame {index}: {type(exc).__name__}: {exc}") from exc
        image = np.asarray(image)
        if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
            raise DeviceError(
                f"{self!r}: frame source must return (H, W) uint8 or uint16, got {image.dtype} {image.shape}"
            )
        if self._frame_shape is not None and image.shape != self._frame_shape:
            raise DeviceError(f"{self!r}: frame {index} is {image.shape}, expected {self._frame_shape}")
        return image

    def __repr__(self) -> str:
        name = self._initial_mode.name
        return f"SimulatedCamera({name} {self._initial_mode.width}x{self._initial_mode.height})"

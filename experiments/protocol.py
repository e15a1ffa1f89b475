"""Protocol and rig files: what an experiment does, and with which devices (YAML, validated by pydantic).

A *protocol* describes one experiment session the way the seed ran them (seed 6.3): a subject slides a fingertip
over a flat surface, a ridge or a valley (3 mm wide, 0.5 mm high, seed 6.3.2) for a few seconds per trial, in one
camera mode (seed 3.3), and the sequence is analysed afterwards; optionally a tactile movie is played on the STReSS
display (seed 5.4, 6.4).

A *rig* says which device is real and which is simulated; everything is simulated unless the rig says otherwise.
:mod:`skinstretch.experiments.rig` is the only module that turns a rig into device objects.

Both files are loaded with their line numbers kept (``yaml.compose``), so every error names the file, the line and
the field, e.g. ``protocol.yaml:12: trials[1].duration_s: Input should be greater than 0``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.display.stress_protocol import MAX_RATE_MHZ, MIN_RATE_MHZ
from skinstretch.experiments.analysis.parameters import AnalysisParams
from skinstretch.config_file import parse_yaml_model, read_config_text
from skinstretch.processing.errors import ConfigError

__all__ = [
    "Subject",
    "Surface",
    "TrialSpec",
    "RecordSpec",
    "AnalysisSpec",
    "MovieSpec",
    "Protocol",
    "DeviceSpec",
    "Rig",
    "PlannedTrial",
    "load_protocol",
    "load_rig",
    "parse_protocol",
    "parse_rig",
]

_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"


class _Strict(BaseModel):
    # Unknown keys are errors: a misspelt option must not be silently ignored. NaN and infinities are refused as
    # such ("Input should be a finite number"), not by whichever bound they happen to fail.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Subject(_Strict):
    """Who is measured. ``id`` names the subject's directory in the data layout."""

    id: str = Field(pattern=_NAME_PATTERN)
    hand: Optional[Literal["left", "right"]] = None
    finger: Optional[str] = None
    notes: str = ""


class Surface(_Strict):
    """The contact surface on the prism (seed 6.3): flat, a Gaussian ridge or valley, or a custom scene file.

    ``width_mm`` and ``height_mm`` are the seed's shape (3 mm wide, 0.5 mm high). ``scene`` names a simulator
    scene (``ridgeL``) or a scene YAML file; it is only used by a simulated camera and, when absent, the
    simulator's scene is picked from ``kind`` and ``field`` (``ridge`` + ``L`` -> ``ridgeL``).
    """

    kind: Literal["flat", "ridge", "valley", "custom"] = "flat"
    width_mm: float = Field(default=3.0, gt=0, le=20)
    height_mm: float = Field(default=0.5, ge=0, le=5)
    field: Literal["L", "S"] = "L"
    scene: Optional[str] = None

    @model_validator(mode="after")
    def _custom_needs_scene(self) -> "Surface":
        if self.kind == "custom" and not self.scene:
            raise ValueError("a custom surface needs 'scene' (a scene name or scene YAML file)")
        return self

    @property
    def scene_name(self) -> str:
        """The simulator scene standing for this surface."""
        return self.scene or f"{self.kind}{self.field}"


class TrialSpec(_Strict):
    """One trial: what the subject is told, the sliding direction, how long, how many times."""

    name: str = Field(pattern=_NAME_PATTERN)
    instructions: str = ""
    direction: Literal["left", "right", "up", "down", "back-and-forth", "rotate", "press"] = "right"
    duration_s: float = Field(gt=0, le=3600)
    repetitions: int = Field(default=1, ge=1, le=1000)
    surface: Optional[Surface] = None


class RecordSpec(_Strict):
    """What is recorded in each trial's session file."""

    frames: bool = True
    force: bool = True
    display: bool = False
    force_rate_hz: float = Field(default=500.0, gt=0, le=7000)

    @model_validator(mode="after")
    def _something(self) -> "RecordSpec":
        if not self.frames:
            raise ValueError("frames: false is not supported: a session file always holds the camera frames")
        return self


class AnalysisSpec(_Strict):
    """What is analysed after each trial (seed chapter 5), in a separate process so acquisition never waits.

    ``options`` are the analysis' parameters by stage (:class:`skinstretch.experiments.analysis.AnalysisParams`,
    e.g. ``{strain: {spans: [1, 11]}, tracking: {min_length_frames: 20}, flow: {window_mm: 0.5}}``), checked when
    the protocol loads: a misspelt or out-of-range option stops it before anything is recorded.
    """

    enabled: bool = True
    when: Literal["after_trial", "later"] = "after_trial"
    method: Literal["features", "flow"] = "features"
    options: AnalysisParams = AnalysisParams()


#: The highest normal-force ceiling a movie may be given, N (a fingertip on the display presses 0.5-5 N).
MAX_FORCE_CEILING_N = 50.0


class MovieSpec(_Strict):
    """A tactile movie to play on the display at the end of the session (seed 5.4).

    ``source`` is a results directory, a ``.npy`` / ``.h5`` movie file, or ``last_trial`` for the movie computed
    from the last analysed trial. ``gain`` scales contactor positions (the seed's figures scale by 10).
    """

    source: str = "last_trial"
    closed_loop: bool = True
    rate_hz: Optional[float] = Field(default=None, ge=MIN_RATE_MHZ / 1000, le=MAX_RATE_MHZ / 1000)  # the display's
    gain: float = Field(default=1.0, gt=0, le=100)
    force_ceiling_n: float = Field(default=5.0, gt=0, le=MAX_FORCE_CEILING_N)


class CalibrationSpec(_Strict):
    """Geometric calibration of the session (seed 3.4), done once before the first trial and stored in every
    trial's session file so the analysis measures on the skin.

    ``source`` is a grid image, a session file of the (moving) grid, or a calibration JSON written by
    ``skinstretch calibrate``; a relative path is relative to the protocol file. The other fields are those of
    ``skinstretch calibrate``. A fit that cannot be trusted stops the session before any trial is recorded.
    """

    source: str = Field(min_length=1)
    surface: Literal["auto", "flat", "ridge", "valley"] = "auto"
    spacing_mm: float = Field(default=0.5, gt=0, le=10)
    dot_diameter_mm: float = Field(default=0.2, gt=0, le=5)
    max_frames: int = Field(default=10, ge=1, le=1000)
    max_rms_px: float = Field(default=0.5, gt=0)


class Protocol(_Strict):
    """A whole experiment session (see module docstring)."""

    name: str = Field(pattern=_NAME_PATTERN)
    session: Optional[str] = Field(default=None, pattern=_NAME_PATTERN)
    description: str = ""
    subject: Subject
    surface: Surface = Surface()
    camera_mode: str = "full"
    field_of_view_mm: float = Field(default=10.3, gt=0, le=100)
    trials: list[TrialSpec] = Field(min_length=1)
    record: RecordSpec = RecordSpec()
    analysis: AnalysisSpec = AnalysisSpec()
    movie: Optional[MovieSpec] = None
    calibration: Optional[CalibrationSpec] = None

    @field_validator("camera_mode")
    @classmethod
    def _known_mode(cls, value: str) -> str:
        if value not in CAMERA_MODES:
            raise ValueError(f"unknown camera mode {value!r}; known: {sorted(CAMERA_MODES)}")
        return value

    @field_validator("trials")
    @classmethod
    def _unique_trials(cls, value: list[TrialSpec]) -> list[TrialSpec]:
        names = [t.name for t in value]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"trial names must be unique, repeated: {dupes}")
        return value

    @property
    def session_name(self) -> str:
        """Directory of this session under the subject's directory (``session`` or the protocol name)."""
        return self.session or self.name

    def planned_trials(self) -> list["PlannedTrial"]:
        """Every trial repetition in order, each with its surface resolved and a stable directory name."""
        out: list[PlannedTrial] = []
        for spec in self.trials:
            for rep in range(spec.repetitions):
                index = len(out)
                out.append(
                    PlannedTrial(
                        index=index,
                        spec=spec,
                        repetition=rep,
                        surface=spec.surface or self.surface,
                        dirname=f"{index:03d}-{spec.name}-r{rep + 1}",
                    )
                )
        return out


class PlannedTrial(_Strict):
    """One repetition of one trial, as the runner executes it."""

    index: int
    spec: TrialSpec
    repetition: int
    surface: Surface
    dirname: str


# ------------------------------------------------------------------------------------------------------- rig


class DeviceSpec(_Strict):
    """One device of the rig: ``kind: sim`` (the default) or the real driver's kind, with its options.

    camera: ``sim`` | ``aravis`` (``device``: Aravis id or IP, e.g. ``Fake_1``) | ``v4l2`` (``device``: ``/dev/videoN``
    or its index, default 0) | ``replay`` (``device``: a session file, image directory/glob or video); force: ``sim`` | ``netft``
    (``address``); display: ``sim`` | ``stress`` (``url``: a serial port or pyserial URL).
    """

    kind: str = "sim"
    device: Optional[str] = None
    address: Optional[str] = None
    url: Optional[str] = None
    seed: int = 0
    options: dict[str, Any] = Field(default_factory=dict)


_KINDS = {
    "camera": {"sim", "aravis", "v4l2", "replay"},
    "force": {"sim", "netft", "none"},
    "display": {"sim", "stress", "none"},
}


class Rig(_Strict):
    """Which device is real and which simulated (everything ``sim`` by default)."""

    name: str = "simulated"
    camera: DeviceSpec = DeviceSpec()
    force: DeviceSpec = DeviceSpec()
    display: DeviceSpec = DeviceSpec()

    @model_validator(mode="after")
    def _known_kinds(self) -> "Rig":
        for role, allowed in _KINDS.items():
            kind = getattr(self, role).kind
            if kind not in allowed:
                raise ValueError(f"{role}.kind {kind!r} is not one of {sorted(allowed)}")
        if self.camera.kind == "aravis" and not self.camera.device:
            raise ValueError("camera.kind aravis needs camera.device (an Aravis id such as Fake_1, or an IP)")
        if self.force.kind == "netft" and not self.force.address:
            raise ValueError("force.kind netft needs force.address (the Net F/T box's IP)")
        if self.display.kind == "stress" and not self.display.url:
            raise ValueError("display.kind stress needs display.url (a serial port or pyserial URL)")
        return self

    @property
    def all_simulated(self) -> bool:
        return all(getattr(self, r).kind in ("sim", "none") for r in _KINDS)


def parse_protocol(text: str, *, source: str = "<protocol>") -> Protocol:
    """Validate protocol YAML text; ConfigError names ``source``, the line and the field of every problem."""
    return parse_yaml_model(Protocol, text, source=source)


def parse_rig(text: str, *, source: str = "<rig>") -> Rig:
    """Validate rig YAML text; ConfigError names ``source``, the line and the field of every problem."""
    return parse_yaml_model(Rig, text, source=source)


def load_protocol(path: str | os.PathLike) -> Protocol:
    """Load and validate a protocol YAML file (raises ConfigError with file:line: field: message)."""
    text, source = read_config_text(path, "protocol")
    protocol = parse_protocol(text, source=source)
    cal = protocol.calibration
    if cal is not None and not Path(cal.source).is_absolute():
        resolved = str((Path(path).parent / cal.source).resolve())
        protocol = protocol.model_copy(update={"calibration": cal.model_copy(update={"source": resolved})})
    return protocol


def load_rig(path: str | os.PathLike | None) -> Rig:
    """Load a rig YAML file; ``None`` gives the all-simulated rig."""
    if path is None:
        return Rig()
    text, source = read_config_text(path, "rig")
    return parse_rig(text, source=source)


def bundled_protocol(name: str) -> Path:
    """Path of a protocol shipped in :mod:`skinstretch.experiments.protocols` (e.g. ``demo``)."""
    p = Path(__file__).with_name("protocols") / f"{name}.yaml"
    if not p.exists():
        raise ConfigError(f"no bundled protocol {name!r} (looked for {p})")
    return p

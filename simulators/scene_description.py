"""What a simulated trial is: the pydantic scene description (camera, print, contact, surface, motion,
deformation) loaded from YAML, in physical units (mm, s, degrees, N; camera effects in pixels and grey levels).

:mod:`skinstretch.simulators.scene` renders a :class:`Scene`; the built-in scenes are ``simulators/scenes/*.yaml``.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from skinstretch.config_file import parse_yaml_model, validation_messages
from skinstretch.processing.errors import ConfigError, InvalidInputError

Pair = tuple[float, float]


def _times_increasing(keyframes: list) -> list:
    """Keyframes whose first entries (times) increase strictly; at least one."""
    if not keyframes:
        raise ValueError("needs at least one keyframe")
    times = [k[0] for k in keyframes]
    if any(b <= a for a, b in zip(times, times[1:])):
        raise ValueError(f"keyframe times must increase strictly, got {times}")
    return keyframes


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraSpec(_Model):
    """Camera mode, field of view and sensor effects (see :class:`skinstretch.simulators.sensor_model.CameraModel`)."""

    mode: Literal["full", "half", "strip"] = "full"
    field_of_view_mm: float = Field(10.3, gt=1.0, le=50.0, description="width of the 640-px image on the glass")
    blur_sigma_px: float = Field(0.8, ge=0.0, le=10.0)
    vignetting: float = Field(0.12, ge=0.0, lt=1.0)
    illumination_tilt: float = Field(0.04, gt=-1.0, lt=1.0)
    noise_sigma: float = Field(2.0, ge=0.0, le=50.0, description="read noise, grey levels")
    shot_noise_gain: float = Field(0.05, ge=0.0, le=5.0)
    ridge_level: float = Field(55.0, ge=0.0, le=255.0, description="grey level of a ridge in contact")
    valley_level: float = Field(205.0, ge=0.0, le=255.0, description="grey level of a valley")
    background_level: float = Field(215.0, ge=0.0, le=255.0, description="grey level without contact")
    residue_contrast: float = Field(5.0, ge=0.0, le=60.0, description="grey levels of the latent print on the glass")
    oversample: int = Field(2, ge=1, le=4, description="master print resolution, times the camera's")


class FingerprintSpec(_Model):
    """Statistics of the synthetic print (see :class:`skinstretch.simulators.fingerprint.FingerprintParams`)."""

    ridge_period_mm: float = Field(0.43, ge=0.2, le=1.0)
    period_variation: float = Field(0.06, ge=0.0, lt=0.5)
    orientation_deg: float = 0.0
    cores_mm: list[Pair] = Field(default_factory=lambda: [(0.0, -9.0)])
    deltas_mm: list[Pair] = Field(default_factory=list)
    minutia_density_per_mm2: float = Field(0.2, ge=0.0, le=1.0)
    minutia_spacing_mm: float = Field(0.6, gt=0.2, le=5.0)
    pore_density_per_mm2: float = Field(3.0, ge=0.0, le=10.0)
    pore_diameter_mm: Pair = (0.06, 0.16)
    pore_spacing_mm: float = Field(0.25, gt=0.05)
    pore_minutia_clearance_mm: float = Field(0.3, ge=0.0)
    ridge_sharpness: float = Field(1.5, gt=0.0, le=20.0)
    ridge_contrast_variation: float = Field(0.15, ge=0.0, lt=1.0)
    ridge_texture: float = Field(0.12, ge=0.0, lt=0.5, description="fine mottling of the ridge darkness")

    @field_validator("pore_diameter_mm")
    @classmethod
    def _pore_range(cls, v: Pair) -> Pair:
        if not 0 < v[0] <= v[1] <= 0.3:
            raise ValueError(f"must be (min, max) with 0 < min <= max <= 0.3 mm, got {v}")
        return v


class ContactSpec(_Model):
    """Contact ellipse on the skin (skin coordinates, mm); its semi-axes grow with the force as F^(1/3)."""

    center_mm: Pair = (0.0, 0.0)
    semi_axes_mm_at_1N: Pair = (3.6, 4.4)
    normal_force_N: float = Field(2.0, gt=0.0, le=20.0)
    force_keyframes: list[Pair] = Field(default_factory=list, description="(t_s, force_N) overriding normal_force_N")
    edge_mm: float = Field(0.35, gt=0.0, le=3.0, description="width of the soft contact edge")

    @field_validator("semi_axes_mm_at_1N")
    @classmethod
    def _positive(cls, v: Pair) -> Pair:
        if min(v) <= 0:
            raise ValueError(f"semi-axes must be positive, got {v}")
        return v


class SurfaceSpec(_Model):
    """The contact surface (see :mod:`skinstretch.simulators.surfaces`); varies along s (image y with ideal optics)."""

    kind: Literal["flat", "ridge", "valley"] = "flat"
    width_mm: float = Field(3.0, gt=0.1, le=20.0)
    height_mm: float = Field(0.5, ge=0.0, le=3.0)
    center_mm: float = Field(0.0, description="flat coordinate of the crest or bottom, 0 = centre of view")
    slope_darkening: float = Field(0.45, ge=0.0, le=1.0, description="relative darkening at the steepest slope")
    contact_loss: float = Field(0.0, ge=0.0, le=1.0, description="0 = skin follows the shape, 1 = contact lost")


class MotionSpec(_Model):
    """Bulk motion keyframes (t_s, u_mm, s_mm, theta_deg), interpolated by a monotone cubic."""

    keyframes: list[tuple[float, float, float, float]] = Field(default_factory=lambda: [(0.0, 0.0, 0.0, 0.0)])
    rotation_center_mm: Pair = (0.0, 0.0)
    ramp_s: float = Field(0.1, ge=0.0, le=5.0)

    @field_validator("keyframes")
    @classmethod
    def _increasing(cls, v):
        return _times_increasing(v)


class PlasticSpec(_Model):
    """Plastic distortion (see :class:`skinstretch.simulators.deformation.PlasticDistortion`)."""

    center_mm: Pair = (0.0, 0.0)
    semi_axes_mm: Pair = (3.0, 4.0)
    band_mm: float = Field(2.0, gt=0.0, le=10.0)
    stick: float = Field(0.0, ge=0.0, le=1.0)
    lag_mm: float = Field(0.0, ge=0.0, le=2.0)
    lag_speed_mm_s: float = Field(1.0, gt=0.0)
    stick_slip_mm: float = Field(0.0, ge=0.0, le=1.0)
    stick_slip_period_s: float = Field(0.25, gt=0.0)
    slip_fraction: float = Field(0.15, gt=0.0, lt=1.0)


class MechanicsSpec(_Model):
    """Ridge/valley mechanics: peak strain (sign chosen by the surface: + ridge, - valley)."""

    peak_strain: float = Field(0.0, ge=0.0, lt=0.5)
    sigma_mm: float | None = Field(None, gt=0.0, description="extent; default the surface's Gaussian sigma")
    speed_scale_mm_s: float = Field(0.3, gt=0.0)


class SlipFrontSpec(_Model):
    """A travelling band of compression (or extension) along ``direction_deg``: the partial-slip front that runs
    across the contact at the onset of sliding (see :class:`skinstretch.simulators.deformation.SlipFront`).

    The band sits at ``position_mm`` (measured along the direction from the skin origin, the contact centre by
    default) interpolated linearly between ``keyframes`` ``(t_s, position_mm)``; in it the skin is strained by
    ``amplitude`` along the direction (negative: compression) with a Gaussian profile ``width_mm`` wide at half
    height, relative to where the band started. ``amplitude`` 0 (the default) turns it off.
    """

    amplitude: float = Field(0.0, gt=-0.3, lt=0.3, description="strain in the band (negative = compression)")
    width_mm: float = Field(0.8, gt=0.05, le=10.0, description="full width at half height of the band")
    direction_deg: float = Field(-90.0, description="direction of travel, counter-clockwise on the image from +x "
                                                    "(-90: down the image, +y, the scenes' sliding direction)")
    keyframes: list[Pair] = Field(default_factory=lambda: [(0.0, -6.0), (3.0, 6.0)],
                                  description="(t_s, position_mm) of the band, interpolated linearly")

    @field_validator("keyframes")
    @classmethod
    def _increasing(cls, v):
        return _times_increasing(v)


#: Resolutions (dots per inch) a print image may be given at.
PRINT_DPI_RANGE = (100.0, 10000.0)


class TextureSpec(_Model):
    """A real fingerprint image as the skin's texture instead of the synthetic print (see
    :mod:`skinstretch.simulators.print_texture`). The feature truth of such a scene is unknown (empty); its
    displacement and strain truth stay exact."""

    image: str = Field(description="a built-in print (see skinstretch.simulators.prints.PRINT_NAMES) or an image "
                                   "file (PNG, TIFF, ...; grey, colour or with alpha); a relative path in a scene "
                                   "file is relative to that file")
    dpi: float = Field(500.0, ge=PRINT_DPI_RANGE[0], le=PRINT_DPI_RANGE[1],
                       description="resolution of the image, dots per inch")
    polarity: Literal["auto", "dark_ridges", "bright_ridges"] = Field(
        "auto", description="auto: ridges are dark when the background around the print is bright (ink, live scan)")
    center_mm: Pair | None = Field(None, description="skin point (mm) under the print's centre; default the "
                                                     "contact centre")
    rotation_deg: float = Field(0.0, description="rotation of the print, counter-clockwise on the image")


class Scene(_Model):
    """A complete simulated trial. Every field has a default; YAML files override what they need."""

    name: str = "custom"
    description: str = ""
    n_frames: int = Field(180, ge=1, le=100000)
    camera: CameraSpec = CameraSpec()
    fingerprint: FingerprintSpec = FingerprintSpec()
    contact: ContactSpec = ContactSpec()
    surface: SurfaceSpec = SurfaceSpec()
    motion: MotionSpec = MotionSpec()
    plastic: PlasticSpec = PlasticSpec()
    mechanics: MechanicsSpec = MechanicsSpec()
    slip_front: SlipFrontSpec = SlipFrontSpec()
    texture: TextureSpec | None = Field(None, description="a real print as the texture (default: synthetic)")

    @model_validator(mode="after")
    def _levels(self) -> "Scene":
        if self.camera.ridge_level >= self.camera.valley_level:
            raise ValueError("camera.ridge_level must be darker (lower) than camera.valley_level (FTIR polarity)")
        return self

    def to_yaml(self) -> str:
        """The scene as YAML (round-trips through :func:`load_scene`)."""
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)

    def with_texture(self, image: str | os.PathLike, *, dpi: float | None = None) -> "Scene":
        """This scene with a real print as its texture (``image``: a built-in print name or a file path)."""
        spec = {"image": str(image)}
        if dpi is not None:
            lo, hi = PRINT_DPI_RANGE
            if not lo <= dpi <= hi:  # NaN fails too; named as "dpi" (the command line's --dpi)
                raise InvalidInputError(f"dpi must be between {lo:g} and {hi:g}, got {dpi:g}")
            spec["dpi"] = float(dpi)
        if self.texture is not None:
            spec = {**self.texture.model_dump(), **spec}
        try:
            texture = TextureSpec(**spec)
        except ValidationError as exc:  # e.g. a dpi out of range: one line naming it, no traceback
            raise ConfigError(validation_messages(exc, source=f"print image {image}")) from None
        return self.model_copy(update={"texture": texture})


# ------------------------------------------------------------------------------------------------- loading

_SCENE_DIR = "scenes"


def _builtin_names() -> list[str]:
    folder = resources.files(__package__) / _SCENE_DIR
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


#: Names of the built-in scenes (simulators/scenes/*.yaml).
SCENE_NAMES: tuple[str, ...] = tuple(_builtin_names())


def parse_scene(text: str, *, source: str = "<string>") -> Scene:
    """Validate a scene from YAML text; errors raise ConfigError naming ``source``, the line and the field."""
    return parse_yaml_model(Scene, text, source=source, empty_ok=True)


def load_scene(name_or_path: str | os.PathLike) -> Scene:
    """A built-in scene by name (see :data:`SCENE_NAMES`) or a scene YAML file by path.

    Examples
    --------
    >>> load_scene("ridgeL").surface.kind
    'ridge'
    """
    key = str(name_or_path)
    if key in SCENE_NAMES:
        text = (resources.files(__package__) / _SCENE_DIR / f"{key}.yaml").read_text()
        return parse_scene(text, source=f"built-in scene {key}")
    path = Path(name_or_path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such scene file, and not a built-in scene (known: {', '.join(SCENE_NAMES)})")
    scene = parse_scene(path.read_text(), source=str(path))
    if scene.texture is not None:
        # A texture image named relative to the scene file (a built-in print name stays as it is).
        image = Path(scene.texture.image)
        beside = path.parent / image
        if not image.is_absolute() and not image.exists() and beside.exists():
            scene = scene.with_texture(beside.resolve())
    return scene



"""The feature extraction chain of seed chapter 4 (with 3.5), from one grey frame to a feature table.

smoothing (4.1) -> light (3.5, per frame) -> local average (4.2) -> contact / background (4.3) -> binarization
(4.4) -> blob pores (4.5) -> thinning (4.6) -> skeleton graph and classification (4.7) -> editing (4.8.1-4.8.6,
each switchable) -> sub-pixel positions.

Beyond the seed (measured by ``skinstretch bench --only accuracy``): local statistics at the scale of one ridge
period (``ridge_period_mm``), not 2 mm (:func:`skinstretch.processing.preprocess.ridge_statistics`); the light
divided out of each frame from its upper envelope (:func:`skinstretch.processing.preprocess.flatten_light`); the
background of 4.3 where the FTIR contrast says the skin does not touch the glass
(:func:`skinstretch.processing.preprocess.contact_map`); spurs and bridges judged by the ridges' direction
(:mod:`skinstretch.processing.ridge_flow`); minutiae located from the grey image where the valleys' medial axis
ends or forks (:mod:`skinstretch.processing.feature_localization`); a branch running into the background is a
valley leaving the contact, and features within 0.3 mm of it are deleted (seed 4.8.6).

Every parameter of :class:`ExtractionParams` is in mm, degrees or grey levels, with the seed's values as defaults;
:class:`FeatureExtractor` converts them to pixels once per calibration and reuses that plan for every frame of a
sequence (and can run a sequence on a thread pool: OpenCV and the compiled steps release the GIL).

Feature ids: ``frame_index * 1_000_000 + i`` for the i-th feature of the frame, so ids are unique within a results
file of up to a million features per frame.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, fields
from typing import Iterable, Sequence

import cv2
import numpy as np
from pydantic import field_validator, model_validator

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_filters import clear_of_background, feature_density_mask
from skinstretch.processing.feature_localization import (
    locate_forks,
    locate_minutiae_tips,
    locate_pores_on_ridges,
    refine_pores,
    tip_curvature_centres,
)
from skinstretch.processing.feature_table import KIND_NAMES, FeatureKind, empty_features, make_features
from skinstretch.processing.illumination import apply_illumination_gain, illumination_gain, illumination_map
from skinstretch.processing.parameters import parameters
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.pores import detect_blob_pores, fill_specks
from skinstretch.processing.ridge_flow import ridge_flow
from skinstretch.processing.preprocess import binarize, check_frame, contact_map, flatten_light, ridge_statistics, smooth
from skinstretch.processing.skeleton_editing import GapEvidence, edit_graph
from skinstretch.processing.skeleton_graph import GraphArrays, edit_with_room, graph_features, trace_arrays
from skinstretch.processing.texture_gate import TextureGateParams, texture_verdict
from skinstretch.processing.thinning import thin

__all__ = ["ExtractionParams", "ExtractionResult", "FeatureExtractor", "ReducedFeatureExtractor", "extract_features",
           "FEATURE_ID_STRIDE"]

#: Feature ids are ``frame_index * FEATURE_ID_STRIDE + i``.
FEATURE_ID_STRIDE = 1_000_000

#: Names of the editing steps, in the order of seed Figure 48 (plus "initial").
STEP_NAMES = ("initial", "short_valleys", "healing", "short_spurs", "bridges", "density", "border")


@parameters
class ExtractionParams:
    """Parameters of the extraction chain: lengths in mm, angles in degrees, grey levels 0-255.

    Defaults are the seed's values except where a comment says why (spur length, ridge-scale statistics). Each
    editing step of seed 4.8 can be switched off with its boolean. Invalid values raise InvalidInputError
    naming the field.

    Examples
    --------
    >>> ExtractionParams(heal_broken_valleys=False).heal_max_distance_mm
    0.6
    """

    # 4.1 smoothing: sigma 1 px and a 3 px kernel at the seed's ~62 px/mm.
    smoothing_sigma_mm: float = 0.016
    smoothing_kernel_mm: float = 0.048
    # 4.2 local average, 4.3 background: beyond the seed (its 2 mm mean put whole bands of ridges above or below
    # the threshold over a ridge or valley of the surface: valleyL bifurcation precision 0.26 -> 0.77 with the
    # ridge scale alone), every local statistic is taken at the scale of the typical ridge period (0.43 mm, FACTS);
    # skin whose FTIR contrast is below min_contact of full contact's is out of contact (the background), which is
    # then dilated (seed: "a few morphological dilation operations").
    ridge_period_mm: float = 0.43
    min_contact: float = 0.5
    background_dilation_mm: float = 0.1
    # 4.4 binarization threshold = scale x local average.
    binarization_scale: float = 1.0
    # 4.5 blob pores below 0.25 mm across; smaller blobs than min diameter are noise.
    detect_pores_by_blob: bool = True
    pore_max_diameter_mm: float = 0.25
    pore_min_diameter_mm: float = 0.04
    # 4.7 orientation from the N-th valley pixel.
    orientation_distance_mm: float = 0.16
    # 4.8.1
    remove_short_valleys: bool = True
    short_valley_max_mm: float = 0.2
    # 4.8.2
    heal_broken_valleys: bool = True
    heal_max_distance_mm: float = 0.6
    heal_max_angle_deg: float = 30.0
    # Beyond the seed: a gap is healed only where the image shows no ridge across it, i.e. its line crosses at most
    # this much skin as dark as the ridges around (skeleton_editing.GapEvidence; 0 = heal whatever the image). Two
    # valleys that end facing each other across a ridge of the print are two true endings.
    heal_max_ridge_mm: float = 0.1
    # 4.8.3: the seed's maximum spur length is 1 mm; 0.3 mm here, because on the simulated scenes 1 mm deleted
    # true valley endings joined to a nearby fork (flatL minutiae recall 0.79 -> 1.0 on 12 frames, precision
    # unchanged); thinning and pore spurs are shorter than ~2/3 of a ridge period (0.43 mm).
    remove_short_spurs: bool = True
    spur_min_mm: float = 0.1
    spur_max_mm: float = 0.3
    spur_max_deviation_deg: float = 60.0
    # 4.8.4
    remove_bridges: bool = True
    bridge_min_mm: float = 0.1
    bridge_max_mm: float = 1.0
    bridge_max_deviation_deg: float = 60.0
    # 4.8.5
    filter_feature_density: bool = True
    density_radius_mm: float = 0.25
    density_max_count: int = 3
    # 4.8.6: features within border_dilation_mm of the background dilated by background_dilation_mm, i.e. within
    # their sum of where the skin is out of contact (or of the image edge), Euclidean distance.
    remove_border_features: bool = True
    border_dilation_mm: float = 0.2
    # Beyond the seed (7.2.2): sub-pixel positions of pores (subpixel) and of minutiae (subpixel_minutiae, which
    # needs subpixel too); fork_radius_mm bounds the radius of the disc that locates a bifurcation (about half a
    # ridge period, see locate_forks).
    subpixel: bool = True
    subpixel_minutiae: bool = True
    fork_radius_mm: float = 0.21
    # Minutiae are located on the excess smoothed once more by a Gaussian of this sigma (0.04 mm = 2.5 px at the
    # seed's scale; 0 = off): it averages the camera noise out of the few pixels that decide where a valley ends
    # (flatL frame-to-frame jitter of minutiae 0.119 px without it, 0.099 px with it; pores keep the 4.1 image).
    minutia_smoothing_mm: float = 0.04
    # Frame checks: below black_level everywhere = all black; more than saturated_fraction at 255 = saturated;
    # more than no_finger_fraction background = no finger in view.
    black_level: float = 20.0
    saturated_fraction: float = 0.5
    no_finger_fraction: float = 0.95

    @field_validator("*", mode="before")
    @classmethod
    def _bools_are_bools(cls, v, info):
        # A switch given as 1 or "yes" is a mistake, not True.
        if cls.__dataclass_fields__[info.field_name].type in ("bool", bool) and not isinstance(v, (bool, np.bool_)):
            raise ValueError(f"must be a bool, got {v!r}")
        return v

    @model_validator(mode="after")
    def _check(self) -> "ExtractionParams":
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type in ("bool", bool):
                if not isinstance(v, (bool, np.bool_)):
                    raise InvalidInputError(f"ExtractionParams.{f.name} must be a bool, got {v!r}")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not math.isfinite(v):
                raise InvalidInputError(f"ExtractionParams.{f.name} must be a finite number, got {v!r}")
            if v < 0:
                raise InvalidInputError(f"ExtractionParams.{f.name} must be >= 0, got {v!r}")
        positive = [
            "smoothing_sigma_mm", "ridge_period_mm", "min_contact", "pore_max_diameter_mm", "orientation_distance_mm",
            "short_valley_max_mm", "heal_max_distance_mm", "heal_max_angle_deg", "spur_max_mm", "bridge_max_mm",
            "density_radius_mm", "binarization_scale", "fork_radius_mm",
        ]  # fmt: skip
        for name in positive:
            if getattr(self, name) <= 0:
                raise InvalidInputError(f"ExtractionParams.{name} must be positive, got {getattr(self, name)!r}")
        for name in ("heal_max_angle_deg", "spur_max_deviation_deg", "bridge_max_deviation_deg"):
            if not 0 < getattr(self, name) <= 90:
                raise InvalidInputError(f"ExtractionParams.{name} must be in (0, 90] degrees, got {getattr(self, name)!r}")
        if self.spur_min_mm >= self.spur_max_mm:
            raise InvalidInputError(f"spur_min_mm ({self.spur_min_mm}) must be below spur_max_mm ({self.spur_max_mm})")
        if self.bridge_min_mm >= self.bridge_max_mm:
            raise InvalidInputError(
                f"bridge_min_mm ({self.bridge_min_mm}) must be below bridge_max_mm ({self.bridge_max_mm})"
            )
        if self.pore_min_diameter_mm >= self.pore_max_diameter_mm:
            raise InvalidInputError(
                f"pore_min_diameter_mm ({self.pore_min_diameter_mm}) must be below "
                f"pore_max_diameter_mm ({self.pore_max_diameter_mm})"
            )
        if not isinstance(self.density_max_count, (int, np.integer)) or self.density_max_count < 1:
            raise InvalidInputError(f"density_max_count must be a positive integer, got {self.density_max_count!r}")
        for name in ("saturated_fraction", "no_finger_fraction"):
            if not 0 < getattr(self, name) <= 1:
                raise InvalidInputError(f"ExtractionParams.{name} must be in (0, 1], got {getattr(self, name)!r}")
        if not 0 <= self.black_level <= 255:
            raise InvalidInputError(f"black_level must be a grey level in [0, 255], got {self.black_level!r}")
        if not self.min_contact < 1:
            raise InvalidInputError(f"ExtractionParams.min_contact must be below 1, got {self.min_contact!r}")
        return self

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ExtractionResult:
    """What :func:`extract_features` returns for one frame.

    Attributes
    ----------
    features : FEATURE_DTYPE array
        Valley endings, valley bifurcations and pores after editing (empty when the frame is flagged).
    step_counts : OrderedDict[str, dict[str, int]]
        Feature count per kind after each performed step, in the order of seed Figure 48 ("initial" first).
    background : (H, W) bool
        The background mask of seed 4.3.
    binary : (H, W) uint8
        The binarized frame (valleys and pores = 255), before the blob pores were removed.
    skeleton : (H, W) uint8
        The valley skeleton after editing (1 on the skeleton).
    flags : set of str
        Why the frame gave no features: "all_black", "saturated", "no_finger", or the texture gate's
        "no_texture" / "out_of_focus" (:mod:`skinstretch.processing.texture_gate`). Empty when fine.
    """

    features: np.ndarray
    step_counts: "OrderedDict[str, dict[str, int]]"
    background: np.ndarray
    binary: np.ndarray
    skeleton: np.ndarray
    flags: set = field(default_factory=set)

    @property
    def ok(self) -> bool:
        """True when the frame was processed (no flag raised)."""
        return not self.flags


@dataclass(frozen=True)
class _Plan:
    """Pixel values of the parameters for one calibration (converted once)."""

    sigma: float
    kernel: int
    window: int
    bg_dilation: int
    pore_max: float
    pore_min_area: int
    pore_min: float
    pore_radius: float
    orient_n: int
    short_valley: float
    heal_dist: float
    heal_ridge: float
    gap_window: int
    spur_min: float
    spur_max: float
    bridge_min: float
    bridge_max: float
    density_radius: float
    contact_clearance: float
    open_reach: float
    edge_clearance: float
    minutia_reach: float
    tip_axis: int
    tip_sigma: float
    fork_radius: float
    minutia_sigma: float  # 0 = no extra smoothing
    pore_along: float
    ridge_sigma: float
    cell: int
    flow_sigma: float
    min_glass: float
    fork_reach: float

    @classmethod
    def make(cls, cal: Calibration, p: ExtractionParams) -> "_Plan":
        pore_min = cal.px(p.pore_min_diameter_mm)
        return cls(
            sigma=max(cal.px(p.smoothing_sigma_mm), 0.3),
            kernel=cal.odd_px(p.smoothing_kernel_mm, minimum=3) if p.smoothing_kernel_mm > 0 else 3,
            # The smallest frame: two ridge periods (the ridge-scale statistics and the flow need a few cells).
            window=cal.odd_px(2 * p.ridge_period_mm, minimum=3),
            bg_dilation=cal.px_int(p.background_dilation_mm),
            pore_max=cal.px(p.pore_max_diameter_mm),
            pore_min_area=max(int(math.floor(math.pi / 4 * pore_min * pore_min)), 1),
            pore_min=pore_min,
            pore_radius=max(cal.px(p.pore_max_diameter_mm) / 2, 1.5),
            orient_n=cal.px_int(p.orientation_distance_mm, minimum=2),
            short_valley=cal.px(p.short_valley_max_mm),
            heal_dist=cal.px(p.heal_max_distance_mm),
            heal_ridge=cal.px(p.heal_max_ridge_mm),
            gap_window=cal.px_int(p.ridge_period_mm, minimum=2),
            spur_min=cal.px(p.spur_min_mm),
            spur_max=cal.px(p.spur_max_mm),
            bridge_min=cal.px(p.bridge_min_mm),
            bridge_max=cal.px(p.bridge_max_mm),
            density_radius=cal.px(p.density_radius_mm),
            contact_clearance=cal.px(p.background_dilation_mm + p.border_dilation_mm),
            edge_clearance=cal.px(p.border_dilation_mm),
            # A skeleton branch ending within 0.05 mm (3 px) of the background runs into it: thinning ends a branch
            # cut by the mask one to three pixels inside (skeleton_editing).
            open_reach=max(cal.px(0.05), 1.5),
            # A quarter ridge period (~0.11 mm) covers the skeleton-to-minutia offsets of thinning.
            minutia_reach=max(cal.px(0.15), 3.0),
            # Centre-line length behind a valley ending (one lateral profile per px): 0.3 mm, about two thirds
            # of a ridge period; shorter lines leave the tip's lateral position noisier (flatL ending jitter:
            # 5 px 0.19, 9 px 0.13, 15 px 0.11, 21 px 0.106 px), longer ones follow curved valleys less well.
            tip_axis=max(cal.px_int(0.3), 2),
            # Scale of the derivatives that give a valley tip's curvature: 0.05 mm (3 px). The ending's frame-to-
            # frame jitter on flatL (seed 0, 20 frames) is 0.11 px at 0.04 mm (the minutiae's smoothing), 0.10 px
            # at 0.05 mm, 0.09 px at 0.056 mm but 1.4 px from the skeleton's end (0.5-1 px below); at 0.07 mm the
            # kernel reaches the next valleys.
            tip_sigma=max(cal.px(0.05), 1.0),
            fork_radius=max(cal.px(p.fork_radius_mm), 2.0),
            minutia_sigma=cal.px(p.minutia_smoothing_mm),
            # Half-length of the ridge profiles that locate a pore the editing found (it touches a valley):
            # 0.1 mm, past the largest pore's radius (0.08 mm) so the across-profiles sample the ridge beside it.
            pore_along=max(cal.px(0.1), 3.0),
            ridge_sigma=cal.px(p.ridge_period_mm) / 2,
            cell=max(cal.px_int(p.ridge_period_mm / 8), 1),
            flow_sigma=cal.px(p.ridge_period_mm),
            # Bare glass inside the image spans more than two ridge periods (contact_map).
            min_glass=cal.px(2 * p.ridge_period_mm),
            # The thinning's fork lies within a quarter ridge period of the widest place of the valleys' crotch.
            fork_reach=max(cal.px(p.ridge_period_mm / 4), 2.0),
        )


def _open_to_background(valleys: np.ndarray, background: np.ndarray) -> np.ndarray:
    """The background as the skeleton rules see it (a branch near it is a valley leaving the contact): the
    background, and every valley pixel whose largest disc inside the valleys reaches it.

    The valleys that leave the contact merge along the outline into a bright band (the skin fading out of contact,
    not yet background), and the skeleton runs down the middle of it, half the band's width from the background:
    beyond the few pixels a thinning leaves at a cut valley's tip (``open_reach``), and a fork where a valley meets
    that band was taken for the end of a bridge (flatL seed 9035: a fork 0.3 mm inside the outline, its third
    valley joining the band, deleted in every frame). The medial axis of such a band lies where the valley's disc
    touches the background, whatever the band's width.
    """
    if not background.any():
        return background
    inside = cv2.distanceTransform(valleys, cv2.DIST_L2, 3)  # to the nearest ridge or background pixel
    to_background = cv2.distanceTransform((~background).view(np.uint8), cv2.DIST_L2, 3)
    # The nearest non-valley pixel is a background one (within a pixel: both are distances on one grid).
    return background | ((valleys > 0) & (to_background <= inside + 1.0))


def _counts(kinds: np.ndarray) -> dict[str, int]:
    return {KIND_NAMES[k.value]: int(np.count_nonzero(kinds == k.value)) for k in FeatureKind}


def _graph_counts(row: np.ndarray) -> dict[str, int]:
    """Counts per kind from a row of :func:`skinstretch.processing.skeleton_editing.edit_graph`'s counts (endings, bifurcations, pores)."""
    ends, bifs, pores = row.tolist()
    return {
        KIND_NAMES[FeatureKind.VALLEY_ENDING]: ends,
        KIND_NAMES[FeatureKind.VALLEY_BIFURCATION]: bifs,
        KIND_NAMES[FeatureKind.PORE]: pores,
    }


def _graph_features(g: GraphArrays, orient_n: int):
    """x, y, kind, orientation and size of the graph's minutiae (in node order) then pores (compiled)."""
    return graph_features(g, n_px=orient_n)


def frame_flags(frame: np.ndarray, params: ExtractionParams | None = None) -> set:
    """``{"all_black"}``, ``{"saturated"}`` or an empty set: the frame checks :meth:`FeatureExtractor.extract` makes."""
    return _flags(np.asarray(frame), params or ExtractionParams())


def _flags(frame: np.ndarray, p: ExtractionParams) -> set:
    flags = set()
    brightest = cv2.minMaxLoc(frame)[1]
    if brightest < p.black_level:
        flags.add("all_black")
    elif brightest == 255 and cv2.countNonZero(cv2.compare(frame, 255, cv2.CMP_EQ)) > p.saturated_fraction * frame.size:
        flags.add("saturated")
    return flags


class FeatureExtractor:
    """Extraction for a sequence of frames sharing one calibration and parameter set.

    Parameters
    ----------
    calibration : Calibration
    params : ExtractionParams, optional
    illumination : (H, W) float32, optional
        An illumination map (seed 3.5) to apply to every frame; see :meth:`fit_illumination`.

    Examples
    --------
    >>> import numpy as np
    >>> from skinstretch.processing.pixel_scale import Calibration
    >>> ex = FeatureExtractor(calibration=Calibration(px_per_mm=62.0))
    >>> res = ex.extract(np.zeros((200, 200), np.uint8), frame_index=3)
    >>> res.ok, sorted(res.flags), len(res.features)
    (False, ['all_black'], 0)
    """

    def __init__(self, *, calibration: Calibration, params: ExtractionParams | None = None, illumination=None):
        if not isinstance(calibration, Calibration):
            raise InvalidInputError(f"calibration must be a Calibration, got {type(calibration).__name__}")
        params = ExtractionParams() if params is None else params
        if not isinstance(params, ExtractionParams):
            raise InvalidInputError(f"params must be ExtractionParams, got {type(params).__name__}")
        self.calibration = calibration
        self.params = params
        self._plan = _Plan.make(calibration, params)
        self._gate = TextureGateParams(black_level=params.black_level, saturated_fraction=params.saturated_fraction)
        self.illumination = illumination

    @property
    def illumination(self) -> np.ndarray | None:
        """The illumination map (seed 3.5) applied to every frame, or None."""
        return self._illumination

    @illumination.setter
    def illumination(self, value) -> None:
        if value is None:
            self._illumination = None
            self._gain = None
            return
        value = np.asarray(value, dtype=np.float32)
        if value.ndim != 2 or not np.all(np.isfinite(value)) or value.min() <= 0:
            raise InvalidInputError("illumination must be a 2-D map, finite and positive everywhere")
        self._illumination = value
        # The gain 255 / IM of eq. 3.7 is computed once here, not per frame.
        self._gain = illumination_gain(value)

    # -- seed 3.5 ---------------------------------------------------------------------------------------------
    def fit_illumination(self, frames: Iterable[np.ndarray], *, lowpass_sigma_mm: float = 0.5) -> np.ndarray:
        """Compute the illumination map of a sequence (seed 3.5) and apply it to every later frame."""
        self.illumination = illumination_map(frames, calibration=self.calibration, lowpass_sigma_mm=lowpass_sigma_mm)
        return self.illumination

    # -- one frame --------------------------------------------------------------------------------------------
    def extract(self, frame: np.ndarray, *, frame_index: int = 0) -> ExtractionResult:
        """Extract and edit the features of one frame. See :func:`extract_features`."""
        p, q = self.params, self._plan
        check_frame(frame, min_size=q.window)
        if not isinstance(frame_index, (int, np.integer)) or frame_index < 0:
            raise InvalidInputError(f"frame_index must be a non-negative integer, got {frame_index!r}")
        h, w = frame.shape
        flags = _flags(frame, p)
        if flags:
            return self._empty(frame.shape, flags)
        raw = frame  # the texture gate's input: the illumination gain below clips the background to white
        if self._illumination is not None:
            if self._illumination.shape != frame.shape:
                raise InvalidInputError(
                    f"illumination map shape {self._illumination.shape} differs from the frame's {frame.shape}"
                )
            # Seed eq. 3.7 verbatim, clip at 255 included: the clip makes the background uniformly white, which
            # the variance test of 4.3 relies on (without it valleyL's minutiae precision fell from 0.94 to 0.40).
            frame = apply_illumination_gain(frame, gain=self._gain)
        s = smooth(frame, sigma_px=q.sigma, kernel_px=q.kernel)  # 4.1
        # Beyond the seed: the light's slow changes divided out of every frame (seed 3.5 from the frame alone).
        s = flatten_light(s, cell_px=q.cell, window_px=2 * q.ridge_sigma, sigma_px=q.ridge_sigma)
        stats = ridge_statistics(s, sigma_px=q.ridge_sigma, cell_px=q.cell)  # 4.2 at the ridge scale
        avg = stats.mean
        background, _ = contact_map(stats, shape=frame.shape, min_contact=p.min_contact,  # 4.3
                                    min_extent_px=q.min_glass)
        out_of_contact = background
        if q.bg_dilation > 0:
            d = 2 * q.bg_dilation + 1
            background = cv2.dilate(background.view(np.uint8), cv2.getStructuringElement(cv2.MORPH_RECT, (d, d))).view(bool)
        if np.count_nonzero(background) > p.no_finger_fraction * background.size:
            return self._empty(frame.shape, {"no_finger"}, background=background)
        refused = texture_verdict(raw, px_per_mm=self.calibration.px_per_mm, params=self._gate).reason
        if refused:  # noise, a blank or out-of-focus frame: no print in contact, no features (texture_gate.py)
            return self._empty(frame.shape, {refused}, background=background)
        thr = avg if p.binarization_scale == 1.0 else cv2.multiply(avg, float(p.binarization_scale))
        binary = binarize(s, local_average=thr, background=background)  # 4.4
        # The excess over the threshold weighs pore centres (4.5) and locates minutiae; computed once.
        excess = cv2.subtract(s, thr)
        if p.detect_pores_by_blob:  # 4.5
            blobs = detect_blob_pores(
                binary, grey=excess, max_diameter_px=q.pore_max, min_area_px=q.pore_min_area
            )
            valleys = blobs.binary_without_pores
            # The pore's size for its centring window: the diameter of a disc of its area, which changes by a
            # fraction of a pixel when the blob gains or loses an edge pixel (its bounding box jumps by one).
            pore_x, pore_y, pore_d = blobs.x, blobs.y, 2.0 * np.sqrt(blobs.area_px / math.pi)
        else:
            valleys = binary
            pore_x = pore_y = pore_d = np.zeros(0)
        # Dark specks narrower than the smallest pore inside a valley are noise, as bright ones are (4.5): left,
        # thinning rings them with a tiny loop whose two junctions pass for bifurcations.
        valleys = fill_specks(valleys, max_diameter_px=q.pore_min)
        skeleton = thin(valleys)  # 4.6
        rules = dict(  # 4.8.1-4.8.4, each when switched on
            orientation_px=q.orient_n,
            short_valley_px=q.short_valley if p.remove_short_valleys else None,
            heal=(q.heal_dist, p.heal_max_angle_deg) if p.heal_broken_valleys else None,
            spurs=(q.spur_min, q.spur_max, p.spur_max_deviation_deg) if p.remove_short_spurs else None,
            bridges=(q.bridge_min, q.bridge_max, p.bridge_max_deviation_deg) if p.remove_bridges else None,
        )
        rules["flow"] = ridge_flow(stats.cell_image, cell_px=stats.cell_px, sigma_px=q.flow_sigma)
        rules["background"], rules["open_reach_px"] = _open_to_background(valleys, background), q.open_reach
        if p.heal_broken_valleys and q.heal_ridge > 0:
            rules["gaps"] = GapEvidence(image=s, window_px=q.gap_window, max_ridge_px=q.heal_ridge)
        g, step_rows = edit_with_room(  # 4.7: the skeleton graph (the blob pores after the skeleton's own), edited
            lambda room: trace_arrays(skeleton, pore_x, pore_y, pore_d, room=room),
            lambda g: edit_graph(g, **rules),
        )
        counts: OrderedDict[str, dict[str, int]] = OrderedDict()
        done = (True, p.remove_short_valleys, p.heal_broken_valleys, p.remove_short_spurs, p.remove_bridges)
        for name, on, row in zip(STEP_NAMES, done, step_rows):
            if on:
                counts[name] = _graph_counts(row)
        x, y, kind, orient, size = _graph_features(g, q.orient_n)
        keep = np.ones(x.size, dtype=bool)
        if p.filter_feature_density:  # 4.8.5
            keep &= feature_density_mask(x, y, kind, radius_px=q.density_radius, max_count=int(p.density_max_count))
            counts["density"] = _counts(kind[keep])
        if p.remove_border_features:  # 4.8.6
            # Within 0.2 mm of the background dilated by 0.1 mm (0.3 mm of where the skin is out of contact) or of
            # the image edge.
            keep &= clear_of_background(x, y, out_of_contact, radius_px=q.contact_clearance, edge_px=q.edge_clearance)
            counts["border"] = _counts(kind[keep])
        x, y, kind, orient, size = x[keep], y[keep], kind[keep], orient[keep], size[keep]
        if p.subpixel:
            x, y = self._refine(s, thr, excess, valleys, rules["flow"], x, y, kind, orient, size)
        n = x.size
        features = make_features(
            x,
            y,
            kind,
            frame=frame_index,
            orientation=orient,
            quality=np.where(np.isfinite(orient) | (kind == FeatureKind.PORE), 1.0, 0.5),
            ids=frame_index * FEATURE_ID_STRIDE + np.arange(n, dtype=np.int64),
        )
        return ExtractionResult(
            features=features,
            step_counts=counts,
            background=background,
            binary=binary,
            skeleton=g.skeleton,
            flags=set(),
        )

    def _refine(self, s, thr, excess, valleys, flow, x, y, kind, orient, size):
        q = self._plan
        x = x.copy()
        y = y.copy()
        pores = kind == FeatureKind.PORE
        if pores.any():
            blob = size[pores] > 0
            idx = np.flatnonzero(pores)
            if blob.any():
                # Window: the blob's own radius plus 1.5 px of edge, never more than half the largest pore, so the
                # neighbouring (bright) valleys stay out of it.
                i = idx[blob]
                radius = np.clip(size[i] / 2 + 1.5, 2.0, q.pore_radius)
                x[i], y[i], _ = refine_pores(s, threshold=thr, x=x[i], y=y[i], radius_px=radius)
            if (~blob).any():
                # A pore that touches a valley (found by the editing: short valleys, spur tips, bridges, 4.8.1-4.8.4)
                # has no window of its own: it is located on its ridge instead (locate_pores_on_ridges; valleyL
                # RMSE of these pores 0.8 -> 0.5 px in the band of partial contact, 0.30 -> 0.12 px elsewhere).
                i = idx[~blob]
                x[i], y[i], _ = locate_pores_on_ridges(excess, x=x[i], y=y[i], flow=flow,
                                                       half_period_px=q.ridge_sigma, along_px=q.pore_along)
        ends = kind == FeatureKind.VALLEY_ENDING
        bifs = kind == FeatureKind.VALLEY_BIFURCATION
        if not self.params.subpixel_minutiae or not (ends.any() or bifs.any()):
            return x, y
        forks = excess  # the outline of the valleys, before the minutiae's extra smoothing
        if q.minutia_sigma > 0:
            # Gaussian cut at 1.6 sigma (a 9 px kernel at 2.5 px): 0.33 ms a frame against 0.57 ms for an 11 px
            # one, with the same jitter.
            k = 2 * int(math.ceil(1.6 * q.minutia_sigma)) + 1
            excess = cv2.GaussianBlur(excess, (k, k), q.minutia_sigma)
        # Valley endings: the tip, where the bright valley's centre line falls to the local mean
        # (locate_minutiae_tips), is a smooth function of the image but lies ~3 px beyond the skeleton's ending
        # (6-7 px where the valley is blunt, at the edge of contact, beyond a match radius of 0.1 mm); the skeleton
        # ends at the tip's centre of curvature (tip_curvature_centres, on the excess before the minutiae's
        # smoothing: it smooths at its own scale), as smooth a function of the image (flatL seeds 1000-1009: 1.0 px
        # from the simulator's minutia instead of 3.1 px, frame-to-frame jitter 0.09 px instead of 0.06). Where no
        # tip or no curvature is found, the skeleton's ending stays.
        if ends.any():
            tip = dict(direction_deg=orient[ends], is_ending=np.ones(int(ends.sum()), dtype=bool),
                       reach_px=q.minutia_reach, n_centres=q.tip_axis)
            tx, ty, at_tip = locate_minutiae_tips(excess, x=x[ends], y=y[ends], **tip)
            cx, cy, _, ok = tip_curvature_centres(forks, x=tx, y=ty, sigma_px=q.tip_sigma, max_radius_px=q.minutia_reach)
            ok &= at_tip
            x[ends], y[ends] = np.where(ok, cx, x[ends]), np.where(ok, cy, y[ends])
        # Valley bifurcations: the centre of the largest disc in the valleys near the skeleton's fork (locate_forks).
        if bifs.any():
            rx, ry, _, _ = locate_forks(forks, x=x[bifs], y=y[bifs], reach_px=q.fork_reach,
                                        max_radius_px=q.fork_radius)
            x[bifs], y[bifs] = rx, ry
        return x, y

    def _empty(self, shape, flags, background=None) -> ExtractionResult:
        bg = np.zeros(shape, dtype=bool) if background is None else background
        return ExtractionResult(
            features=empty_features(0),
            step_counts=OrderedDict(),
            background=bg,
            binary=np.zeros(shape, dtype=np.uint8),
            skeleton=np.zeros(shape, dtype=np.uint8),
            flags=set(flags),
        )

    # -- sequences --------------------------------------------------------------------------------------------
    def extract_many(
        self,
        frames: Sequence[np.ndarray],
        *,
        frame_indices: Sequence[int] | None = None,
        workers: int = 2,
    ) -> list[ExtractionResult]:
        """Extract every frame of a sequence, on ``workers`` threads (results in frame order)."""
        if not isinstance(workers, (int, np.integer)) or workers < 1:
            raise InvalidInputError(f"workers must be a positive integer, got {workers!r}")
        indices = list(range(len(frames))) if frame_indices is None else list(frame_indices)
        if len(indices) != len(frames):
            raise InvalidInputError(f"frame_indices has {len(indices)} entries for {len(frames)} frames")
        if workers == 1:
            return [self.extract(f, frame_index=k) for f, k in zip(frames, indices)]
        with ThreadPoolExecutor(max_workers=workers) as pool:
            return list(pool.map(lambda fk: self.extract(fk[0], frame_index=fk[1]), zip(frames, indices)))


def extract_features(
    frame: np.ndarray,
    *,
    calibration: Calibration,
    params: ExtractionParams | None = None,
    frame_index: int = 0,
    illumination: np.ndarray | None = None,
) -> ExtractionResult:
    """Extract valley endings, valley bifurcations and pores from one FTIR frame (seed chapter 4).

    Parameters
    ----------
    frame : (H, W) uint8
        Grey frame, ridges dark and valleys/pores bright; at least two ridge periods on each side.
    calibration : Calibration
        Pixel scale; every parameter in mm is converted through it.
    params : ExtractionParams, optional
        Defaults to the seed's values.
    frame_index : int
        Written in the ``frame`` column and used for ids (``frame_index * 1_000_000 + i``).
    illumination : (H, W) float32, optional
        Illumination map of the sequence (seed 3.5, :func:`skinstretch.processing.illumination.illumination_map`).

    Returns
    -------
    ExtractionResult
        ``.ok`` is False, with ``.flags`` saying why, for all-black, saturated or finger-less frames.

    Raises
    ------
    InvalidInputError
        Wrong dtype or shape, or a frame smaller than two ridge periods.
    """
    return FeatureExtractor(calibration=calibration, params=params, illumination=illumination).extract(
        frame, frame_index=frame_index
    )


#: :class:`ReducedFeatureExtractor` halves a frame only where a ridge period keeps at least this many pixels (at
#: 62 px/mm 13.3 px, as a 31 px/mm camera sees it; the ``conditions`` bench holds the extractor at 30 px/mm).
REDUCED_PERIOD_PX = 12.0


class ReducedFeatureExtractor:
    """:class:`FeatureExtractor` run on each frame halved (area average) where its ridges stay well resolved
    (:data:`REDUCED_PERIOD_PX`), the features' positions returned in the frame's own pixels.

    Finding features costs about a third at the rig's scale, and a caller that registers each feature's window at
    full resolution (the live view) measures the same motion; but the positions are coarser (pores about 0.3 px from
    the truth, twice the ``accuracy`` table's target) and small pores are missed, so the analysis does not use it
    (docs/tuning-log.md, fifth session). ``factor`` is 1 at coarse scales (then it is the plain extractor). The masks
    (``background``, ``binary``, ``skeleton``) are those of the reduced frame; a frame of odd size loses its last
    row or column.
    """

    def __init__(self, *, calibration: Calibration, params: ExtractionParams | None = None) -> None:
        self.factor = calibration.resolvable_reduction(2, min_period_px=REDUCED_PERIOD_PX)
        self.calibration = calibration
        self.extractor = FeatureExtractor(calibration=Calibration(px_per_mm=calibration.px_per_mm / self.factor),
                                          params=params)

    def extract(self, frame: np.ndarray, *, frame_index: int = 0) -> ExtractionResult:
        f = self.factor
        if f == 1:
            return self.extractor.extract(frame, frame_index=frame_index)
        h, w = frame.shape[:2]
        small = cv2.resize(frame[: h - h % f, : w - w % f], (w // f, h // f), interpolation=cv2.INTER_AREA)
        res = self.extractor.extract(small, frame_index=frame_index)
        for axis in ("x", "y"):  # a reduced pixel's centre, in the frame's pixels
            res.features[axis] = res.features[axis] * f + (f - 1) / 2.0
        return res

"""The dense method: displacement and strain over the contact region without features (beyond the seed, 7.2:
"other methods, such as an analysis of the optical flow, could provide better results").

Design (:class:`DenseFlow`), chosen against DIS, Farneback and DeepFlow on fingerprint texture:

1. Both frames are contrast-normalised locally (illumination is fixed to the prism, not to the skin).
2. Coarse global motion by phase correlation of the whole images, then an affine motion by ECC on the top
   pyramid level started from it. Local window methods started at zero lock onto a neighbouring ridge; started
   from the affine motion they are within a fraction of a ridge period.
3. Every node of a regular grid (0.2 mm) in the contact region is registered with a ~0.8 mm window
   (Lucas-Kanade data term), coupled to its neighbours by a membrane term on the deviation from a prior (the
   re-fitted affine motion plus the field's own deviation from it smoothed over about half a window, or the affine
   alone: ``FlowParams.local_prior``), solved by over-relaxed (SOR) sweeps alternating with re-fits of the prior
   (a joint fit of field and prior); Gauss-Newton iterations re-warp the second image. The coupling supplies the
   along-ridge component a single window cannot see (aperture problem); acting on the deviation from such a
   prior, it does not bias uniform strain. The warp is bilinear (OpenCV's bicubic kernel biased the displacement by up
   to 0.04 px depending on its sub-pixel part). The kernels are numba (nogil,
   :mod:`skinstretch.processing.flow_kernels`): the second image warped and the window sums of the gradient
   products at the nodes in one pass down the image, the solver, the composition of fields.
4. Nodes out of contact (a flat window), whose window leaves the second image, or whose residual is far above
   the median (and above a floor, for noise-free images) are flagged invalid, never silently kept.

Strain comes from the grid (:func:`skinstretch.processing.flow_fields.grid_strain`: finite differences) or from
:func:`skinstretch.processing.stretch.triangulation_strain` on the grid's :meth:`FlowField.motion`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import Field, field_validator
from scipy.ndimage import gaussian_filter, map_coordinates

from skinstretch.processing.pixel_scale import RIDGE_PERIOD_MM, Calibration
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.flow_kernels import (
    compose_steps, membrane_bias, membrane_edge_weights, sor, sor_tensor, warped_moments,
)
from skinstretch.processing.global_motion import GlobalMotionEstimator, affine_motion
from skinstretch.processing.measurement_uncertainty import (
    MIN_MATCH, MODEL_SIGMA_PX, RegistrationCheck, Regularisation, registration_check,
)
from skinstretch.processing.parameters import parameters
from skinstretch.processing.displacement_refinement import local_normalize
from skinstretch.processing.texture_gate import TEXTURE_REASONS, texture_verdict
from skinstretch.processing.span_registration import SpanFrames
from skinstretch.processing.tracking import MotionSample


@parameters
class FlowParams:
    """Options of :class:`DenseFlow`, in mm and grey levels (the evidence behind the defaults: docs/tuning-log.md).

    Parameters
    ----------
    grid_step_mm, window_mm, window_px : float, float, int or None
        Largest grid spacing (mm; at most a quarter of the window); side of the registration window (mm, about two
        ridge periods: the resolution knob, ``bench --only star``), in pixels (odd, >= 7) when ``window_px`` given.
    pyramid_levels : int or None
        Pyramid levels of the first registration; None: as many as keep a ridge period >= 6 px on the top level.
    min_contrast, smoothness, sor_omega : float
        Grey-level standard deviation of a node in contact; coupling weight of neighbours (relative to the median
        data weight); SOR over-relaxation factor in (0, 2).
    refine_iterations, solver_sweeps, prior_refits : int
        Gauss-Newton iterations per level; SOR sweeps per iteration; affine prior re-fits per iteration.
    max_residual_ratio, residual_floor, model_sigma_px : float
        A node whose residual exceeds this multiple of the median, and this floor (grey levels), is invalid; the
        error a residual does not show (px per axis), added in quadrature to each node's predicted standard error.
    clg_levels, normalize_sigma_mm : int, float or None
        Pyramid levels on which the coupled registration also runs after the affine start (0: full resolution only);
        local contrast normalisation scale (mm; :func:`..displacement_refinement.local_normalize`).
    adaptive, local_prior, texture_gate, refine_spans : bool
        Adaptive regularization (:meth:`DenseFlow._adapt`); a pair's membrane tied to the affine plus its own smoothed
        deviation (the analysis plan turns it off over a shape); refuse frames without fingerprint texture; a longer
        span's composed fields refined by registering its own two frames (:class:`SpanRefiner`).
    """

    grid_step_mm: float = Field(0.2, gt=0)
    window_mm: float = Field(0.8, gt=0)
    window_px: int | None = Field(None, ge=7)
    pyramid_levels: int | None = Field(None, ge=0, le=5)
    min_contrast: float = Field(8.0, ge=0)
    smoothness: float = Field(1.5, ge=0)
    refine_iterations: int = Field(3, ge=1)
    solver_sweeps: int = Field(15, ge=1)
    sor_omega: float = Field(1.8, gt=0, lt=2)
    prior_refits: int = Field(4, ge=1)
    max_residual_ratio: float = Field(3.0, gt=0)
    residual_floor: float = Field(2.0, ge=0)
    clg_levels: int = Field(0, ge=0, le=5)
    normalize_sigma_mm: float | None = Field(0.15, gt=0)
    adaptive: bool = True
    local_prior: bool = True
    texture_gate: bool = True
    refine_spans: bool = True
    model_sigma_px: float = Field(MODEL_SIGMA_PX, ge=0)

    @field_validator("window_px")
    @classmethod
    def _odd_window(cls, v: int | None) -> int | None:
        if v is not None and v % 2 == 0:
            raise ValueError(f"must be odd (a window centred on its node), got {v}")
        return v


@dataclass(frozen=True)
class FlowField:
    """Displacement on a grid of frame a, to frame b. ``displacement`` is NaN exactly where ``valid`` is False.

    ``status`` says why nodes are invalid in bulk: "ok", or e.g. "no contact" when no node has texture.
    ``frame_flags`` names, per frame of the pair, why it was refused (""  when it was not): a reason of
    :func:`skinstretch.processing.texture_gate.texture_verdict` ("all_black", "saturated", "no_texture",
    "out_of_focus", or "no contact" when a frame the gate refused has no node in contact either; no node is then
    valid and ``global_shift`` is NaN), or "no contact" for a frame a without a node in contact.
    """

    frame_a: int
    frame_b: int
    grid_x: np.ndarray  # (GX,) px
    grid_y: np.ndarray  # (GY,) px
    displacement: np.ndarray  # (GY, GX, 2) px
    valid: np.ndarray  # (GY, GX) bool
    global_shift: np.ndarray  # (2,) px
    n_outliers: int  # nodes in contact flagged invalid (residual too high or window out of the image)
    status: str = "ok"
    frame_flags: tuple[str, str] = ("", "")
    sigma: np.ndarray | None = None  # (GY, GX) px: each valid node's predicted standard error per axis, else NaN
    match: np.ndarray | None = None  # (GY, GX): each valid node's window match after the motion, else NaN

    def motion(self, *, stride: int = 1) -> MotionSample:
        """The valid nodes (every ``stride``-th along each axis) as a :class:`MotionSample`; ids = flat node index."""
        if stride < 1:
            raise InvalidInputError(f"stride must be >= 1, got {stride!r}")
        gy, gx = self.valid.shape
        rows, cols = np.meshgrid(np.arange(0, gy, stride), np.arange(0, gx, stride), indexing="ij")
        rows, cols = rows.ravel(), cols.ravel()
        ok = self.valid[rows, cols]
        rows, cols = rows[ok], cols[ok]
        pts = np.column_stack([self.grid_x[cols], self.grid_y[rows]])
        sigma = None if self.sigma is None else self.sigma[rows, cols]
        match = None if self.match is None else self.match[rows, cols]
        doubt = self.status.removeprefix("doubted: ") if self.status.startswith("doubted: ") else ""
        return MotionSample(self.frame_a, self.frame_b, pts, self.displacement[rows, cols], rows * gx + cols, sigma,
                            match, doubt)

    def dense(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Displacement at every pixel of an image of ``shape`` (H, W): ``(u, v)`` float32 px, bilinear between
        nodes (in float64), NaN outside the grid and wherever one of the four surrounding nodes is invalid."""
        h, w = int(shape[0]), int(shape[1])
        gx, gy = self.grid_x, self.grid_y
        u, v = np.full((h, w), np.nan, np.float32), np.full((h, w), np.nan, np.float32)
        if gx.size < 2 or gy.size < 2:
            return u, v
        x = np.arange(w, dtype=np.float64)
        y = np.arange(h, dtype=np.float64)
        cols = (x >= gx[0]) & (x <= gx[-1])
        rows = (y >= gy[0]) & (y <= gy[-1])
        fc = (x[cols] - gx[0]) / (gx[1] - gx[0])
        fr = (y[rows] - gy[0]) / (gy[1] - gy[0])
        j0 = np.minimum(fc.astype(np.int64), gx.size - 2)
        i0 = np.minimum(fr.astype(np.int64), gy.size - 2)
        tx, ty = (fc - j0)[None, :], (fr - i0)[:, None]
        ok = self.valid
        good = ok[i0][:, j0] & ok[i0][:, j0 + 1] & ok[i0 + 1][:, j0] & ok[i0 + 1][:, j0 + 1]
        for c, out in ((0, u), (1, v)):
            f = np.where(ok, self.displacement[..., c], 0.0)
            top = f[i0][:, j0] * (1 - tx) + f[i0][:, j0 + 1] * tx
            bottom = f[i0 + 1][:, j0] * (1 - tx) + f[i0 + 1][:, j0 + 1] * tx
            val = top * (1 - ty) + bottom * ty
            out[np.ix_(rows, cols)] = np.where(good, val, np.nan)
        return u, v

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear displacement at ``points`` (n, 2); returns (displacement, valid) with NaN where not valid
        (outside the grid or next to an invalid node)."""
        return self._bilinear(self.displacement, points)

    def sigma_at(self, points: np.ndarray) -> np.ndarray:
        """The nodes' predicted standard error (px) at ``points`` (n, 2), bilinear; NaN where :meth:`sample` is, and
        everywhere when the field has none."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if self.sigma is None:
            return np.full(points.shape[0], np.nan)
        return self._bilinear(self.sigma[..., None], points)[0][:, 0]

    def _bilinear(self, values: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``values`` (GY, GX, k) bilinear at ``points``; (out (n, k), ok (n,)), NaN where not ok."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        gx, gy = self.grid_x, self.grid_y
        step_x = gx[1] - gx[0] if gx.size > 1 else 1.0
        step_y = gy[1] - gy[0] if gy.size > 1 else 1.0
        fc = (points[:, 0] - gx[0]) / step_x
        fr = (points[:, 1] - gy[0]) / step_y
        inside = (fc >= 0) & (fc <= gx.size - 1) & (fr >= 0) & (fr <= gy.size - 1)
        coords = np.vstack([fr, fc])
        bad = (~self.valid).astype(np.float64)
        near_bad = map_coordinates(bad, coords, order=1, mode="nearest") > 1e-9
        field = np.where(self.valid[..., None], values, 0.0)
        out = np.stack([map_coordinates(field[..., i], coords, order=1, mode="nearest")
                        for i in range(values.shape[-1])], axis=1)
        ok = inside & ~near_bad
        out[~ok] = np.nan
        return out, ok


def window_px(params: FlowParams, calibration: Calibration) -> int:
    """The registration window of ``params`` in pixels: ``window_px`` when given, else ``window_mm`` (odd)."""
    return int(params.window_px) if params.window_px is not None else calibration.odd_px(params.window_mm, minimum=7)


_HELPER: list[ThreadPoolExecutor] = []
_HELPER_LOCK = threading.Lock()


def _helper_pool() -> ThreadPoolExecutor:
    """One worker thread shared by all :class:`DenseFlow` instances (created on first use)."""
    with _HELPER_LOCK:
        if not _HELPER:
            _HELPER.append(ThreadPoolExecutor(1, thread_name_prefix="dense-flow"))
        return _HELPER[0]


@dataclass(frozen=True)
class _Prepared:
    """One frame made ready for :class:`DenseFlow`: the grey image, its normalised pyramid (full resolution
    first, float32) and, when it is the first frame of a pair, its nodes in contact; or only the reason the texture
    gate refused it."""

    raw: np.ndarray
    pyramid: list[np.ndarray]
    contact: np.ndarray | None
    refused: str = ""


class DenseFlow:
    """Grid displacement between two frames: phase correlation, affine ECC start, coupled registration.

    Parameters
    ----------
    calibration : Calibration
    params : FlowParams, optional

    Examples
    --------
    >>> import numpy as np, cv2
    >>> rng = np.random.default_rng(2)
    >>> a = cv2.GaussianBlur((rng.random((200, 240)) * 255).astype(np.float32), (0, 0), 2.5)
    >>> a = cv2.normalize(a, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    >>> m = np.float32([[1, 0, 3.25], [0, 1, -1.5]])
    >>> b = cv2.warpAffine(a, m, (240, 200), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    >>> f = DenseFlow(calibration=Calibration(px_per_mm=62.0)).compute(a, b)
    >>> d = f.displacement[f.valid]
    >>> bool(np.abs(np.median(d, axis=0) - [3.25, -1.5]).max() < 0.05)
    True
    """

    def __init__(self, *, calibration: Calibration, params: FlowParams | None = None) -> None:
        self.params = params or FlowParams()
        self.calibration = calibration
        self._win = window_px(self.params, calibration)
        # The grid is never coarser than a quarter of the window (0.2 mm for the default 0.8 mm window).
        self._step = max(2, min(calibration.px_int(self.params.grid_step_mm), int(round(self._win / 4))))
        # Coarse levels and the global estimate keep the ridges resolvable at any pixel scale (aliased ridges lock
        # the affine start onto a wrong ridge: a print at 20 px/mm moved by tens of pixels).
        self._levels = (calibration.resolvable_halvings(5) if self.params.pyramid_levels is None
                        else int(self.params.pyramid_levels))
        self._estimator = GlobalMotionEstimator(downsample=calibration.resolvable_reduction(2))

    @property
    def window_px(self) -> int:
        """Side of the registration window in pixels."""
        return self._win

    @property
    def grid_step_px(self) -> int:
        """Spacing of the measurement grid in pixels."""
        return self._step

    def regularisation(self, *, span: bool = False) -> Regularisation:
        """How the membrane couples the nodes (their errors' correlation): a pair's (its local prior, if on) or a
        refined span's (``span``: affine prior, ``_SPAN_SMOOTHNESS``), at a node of median texture (data weight half
        the median trace of the gradient products, against which the membrane weight is set); the model term is
        each node's own."""
        smoothness = self.params.smoothness * (_SPAN_SMOOTHNESS if span else 1.0)
        prior = _PRIOR_SIGMA_NODES if self.params.local_prior and not span else None
        return Regularisation(float(self.grid_step_px), self.window_px / self.grid_step_px, 2.0 * smoothness, prior,
                              float(self.params.model_sigma_px))

    def grid(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Grid node coordinates (x, y) for images of ``shape``: nodes whose window fits in the image."""
        h, w = shape
        half = self._win // 2
        gx = np.arange(half, w - half, self._step, dtype=np.float64)
        gy = np.arange(half, h - half, self._step, dtype=np.float64)
        return gx, gy

    def span_frames(self, frame: Callable[[int], np.ndarray], *, keep: int = 0) -> SpanFrames:
        """Frames ``frame(j)`` prepared once for this flow's refiners (:class:`SpanRefiner`,
        :class:`ReferenceRefiner`, which may share them), dropped ``keep`` frames after a span has passed them."""
        return SpanFrames(frame, lambda image: self._prepare(self._frame([image], 0)), keep=keep)

    def compute(
        self,
        image_a: np.ndarray,
        image_b: np.ndarray,
        *,
        frame_a: int = 0,
        frame_b: int = 1,
        initial_shift: np.ndarray | None = None,
        initial: FlowField | None = None,
    ) -> FlowField:
        """Displacement field from ``image_a`` to ``image_b`` (2-D grey images of the same shape).

        ``initial`` (a field on this flow's grid for these images, e.g. composed from shorter steps with
        :func:`compose_fields`) replaces the global start (phase correlation and affine ECC) and the coarse levels:
        the registration refines it."""
        a = _gray(image_a, "image_a")
        b = _gray(image_b, "image_b")
        if a.shape != b.shape:
            raise InvalidInputError(f"images differ in shape: {a.shape} vs {b.shape}")
        self._check_shape(a.shape)
        # The second core prepares frame b meanwhile (the kernels release the GIL).
        fb = _helper_pool().submit(self._prepare, b, contact=False)
        fa = self._prepare(a)
        return self._register(fa, fb.result(), frame_a, frame_b, initial_shift, initial)

    def compute_spans(
        self,
        frames: Sequence[np.ndarray],
        fields: Sequence[FlowField],
        *,
        span: int,
        first_frame: int = 0,
        threads: int = 2,
        refine: bool = True,
    ) -> list[FlowField]:
        """Fields from frame k to frame k + ``span`` for every k, given the consecutive fields of the same frames
        (:meth:`compute_sequence`): each is the consecutive fields composed along the skin points
        (:func:`compose_fields`), refined by registering frame k to frame k + span directly (``initial``).

        Composing alone adds up every step's smoothing bias; the direct registration sees the whole span's
        deformation at once, which the adaptive regularization resolves. ``refine=False`` returns the
        compositions: for frames that carry patterns fixed to the glass (a ridge or valley surface), which a direct
        registration over a span partly follows."""
        n = len(frames)
        span = int(span)
        if span < 1:
            raise InvalidInputError(f"span must be >= 1, got {span!r}")
        if len(fields) != max(n - 1, 0):
            raise InvalidInputError(f"need the {max(n - 1, 0)} consecutive fields of the {n} frames, got {len(fields)}")
        if int(threads) < 1:
            raise InvalidInputError(f"threads must be >= 1, got {threads!r}")
        if span == 1:
            return list(fields)
        starts = list(range(n - span))
        if not refine:
            return [compose_fields(fields[k : k + span]) for k in starts]
        out: list[FlowField | None] = [None] * len(starts)

        def run(i0: int, i1: int) -> None:
            refiner = SpanRefiner(self, lambda j: frames[j - first_frame])
            for i in range(i0, i1):
                out[i] = refiner.refine(fields[starts[i] : starts[i] + span])

        n_threads = max(1, min(int(threads), len(starts)))
        bounds = np.linspace(0, len(starts), n_threads + 1).round().astype(int)
        if n_threads <= 1:
            run(0, len(starts))
        else:
            with ThreadPoolExecutor(n_threads) as pool:
                for job in [pool.submit(run, int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]:
                    job.result()
        return [f for f in out if f is not None]

    def compute_sequence(
        self,
        frames: Sequence[np.ndarray],
        *,
        first_frame: int = 0,
        threads: int = 2,
        on_field: Callable[[FlowField], None] | None = None,
    ) -> list[FlowField]:
        """Fields between consecutive frames (k, k + 1), the same as :meth:`compute` on each pair, faster:
        each frame is normalised once, and ``threads`` threads each take a contiguous run of pairs (the kernels
        release the GIL). ``on_field`` is called with each field as it is done (any order, e.g. a progress bar);
        frame numbers start at ``first_frame``."""
        n = len(frames)
        if int(threads) < 1:
            raise InvalidInputError(f"threads must be >= 1, got {threads!r}")
        if n < 2:
            return []
        out: list[FlowField | None] = [None] * (n - 1)

        def run(k0: int, k1: int) -> None:  # pairs k0 .. k1 - 1
            prev = None
            for k in range(k0, k1):
                if prev is None:
                    prev = self._prepare(self._frame(frames, k))
                cur = self._prepare(self._frame(frames, k + 1))
                if cur.raw.shape != prev.raw.shape:
                    raise InvalidInputError(f"frame {k + 1} has shape {cur.raw.shape}, frame {k} {prev.raw.shape}")
                f = self._register(prev, cur, first_frame + k, first_frame + k + 1, None)
                out[k] = f
                if on_field is not None:
                    on_field(f)
                prev = cur

        n_threads = max(1, min(int(threads), n - 1))
        bounds = np.linspace(0, n - 1, n_threads + 1).round().astype(int)
        if n_threads == 1:
            run(0, n - 1)
        else:
            with ThreadPoolExecutor(n_threads) as pool:
                for job in [pool.submit(run, int(k0), int(k1)) for k0, k1 in zip(bounds[:-1], bounds[1:])]:
                    job.result()
        return [f for f in out if f is not None]

    def _frame(self, frames: Sequence[np.ndarray], k: int) -> np.ndarray:
        image = _gray(frames[k], f"frame {k}")
        self._check_shape(image.shape)
        return image

    def _check_shape(self, shape: tuple[int, ...]) -> None:
        gx, gy = self.grid(shape)
        if gx.size < 2 or gy.size < 2:
            raise InvalidInputError(f"images of shape {shape} are too small for a {self._win} px window grid")

    def _prepare(self, image: np.ndarray, *, contact: bool = True) -> _Prepared:
        """What one frame contributes to any pair: its normalised pyramid and (as first frame) its contact nodes."""
        refused = texture_verdict(image, px_per_mm=self.calibration.px_per_mm).reason if self.params.texture_gate else ""
        gx, gy = self.grid(image.shape)
        nodes = None
        if contact or refused in TEXTURE_REASONS:
            # Contact: local grey-level spread over the window at each node (FTIR: no contact -> no ridges).
            af = image.astype(np.float32)
            k = (self._win, self._win)
            mean = cv2.boxFilter(af, -1, k)
            sq = cv2.boxFilter(af * af, -1, k)
            spread = np.sqrt(np.maximum(sq - mean * mean, 0.0))
            rr, cc = np.meshgrid(gy.astype(int), gx.astype(int), indexing="ij")
            # A node is in contact when (almost) all of its window shows ridges.
            low = cv2.boxFilter((spread < self.params.min_contrast).astype(np.float32), -1, k)
            nodes = low[rr, cc] <= 0.05
        if refused:  # no print in contact (texture_gate.py): nothing to register, whatever the other frame holds
            no_contact = refused in TEXTURE_REASONS and not nodes.any()  # FTIR without contact: plain bright
            return _Prepared(image, [], None, "no contact" if no_contact else refused)
        norm = image
        if self.params.normalize_sigma_mm is not None:
            # Illumination is fixed to the prism, not the skin: normalise local contrast (see local_normalize).
            norm = local_normalize(image, sigma_px=self.calibration.px(self.params.normalize_sigma_mm))
        pyramid = [norm.astype(np.float32)]
        for _ in range(self._levels):
            pyramid.append(cv2.pyrDown(pyramid[-1]))
        return _Prepared(image, pyramid, nodes)

    def _register(
        self, fa: _Prepared, fb: _Prepared, frame_a: int, frame_b: int, initial_shift: np.ndarray | None,
        initial: FlowField | None = None,
    ) -> FlowField:
        gx, gy = self.grid(fa.raw.shape)
        gyn, gxn = gy.size, gx.size
        if fa.refused or fb.refused:
            return FlowField(frame_a, frame_b, gx, gy, np.full((gyn, gxn, 2), np.nan), np.zeros((gyn, gxn), bool),
                             np.full(2, np.nan), 0, fa.refused or fb.refused, (fa.refused, fb.refused))
        contact = fa.contact
        gxx, gyy = np.meshgrid(gx, gy)
        span = initial is not None  # refining a composed span (compute_spans)
        global_check = False  # the field is checked against a reliable global estimate of this pair's own
        if initial is not None:
            if initial.valid.shape != (gyn, gxn):
                raise InvalidInputError(f"initial field is on a {initial.valid.shape} grid, this flow's is {(gyn, gxn)}")
            shift = np.asarray(initial.global_shift, dtype=np.float64)
        elif initial_shift is None:
            estimate = self._estimator.estimate(fa.raw, fb.raw)
            shift, global_check = estimate.shift, estimate.reliable
        else:
            shift = np.asarray(initial_shift, dtype=np.float64).reshape(2)
        if not np.any(contact):
            return FlowField(frame_a, frame_b, gx, gy, np.full((gyn, gxn, 2), np.nan), np.zeros((gyn, gxn), bool),
                             shift, 0, "no contact", ("no contact", ""))
        pa, pb = fa.pyramid, fb.pyramid
        top = self._levels
        affine = None if initial is not None else affine_motion(pa[top], pb[top], shift / 2.0**top)
        if initial is not None:
            # Start from the given field; its invalid nodes from the affine fitted to its valid ones.
            ok = initial.valid
            if ok.sum() < 3:
                return FlowField(frame_a, frame_b, gx, gy, np.full((gyn, gxn, 2), np.nan),
                                 np.zeros((gyn, gxn), bool), shift, 0, "initial field has fewer than 3 valid nodes")
            design = np.column_stack([gxx[ok], gyy[ok], np.ones(int(ok.sum()))])
            coef, *_ = np.linalg.lstsq(design, initial.displacement[ok], rcond=None)
            fill = np.stack([gxx, gyy, np.ones_like(gxx)], axis=-1) @ coef
            field = np.where(ok[..., None], initial.displacement, fill)
        elif affine is None:
            field = np.tile(shift.astype(np.float64), (gyn, gxn, 1))
        else:
            # The affine was fitted at the top level: scale its translation back to full resolution.
            f = 2.0**top
            m = affine
            field = np.stack(
                [
                    (m[0, 0] - 1) * gxx + m[0, 1] * gyy + m[0, 2] * f,
                    m[1, 0] * gxx + (m[1, 1] - 1) * gyy + m[1, 2] * f,
                ],
                axis=-1,
            )
        prior = field.copy()
        # Coarse to fine: the same nodes, the same window in pixels of each level (a wider skin area up top).
        levels = 0 if initial is not None else min(top, int(self.params.clg_levels))
        for level in range(levels, -1, -1):
            f = 2.0**level
            field, level_prior, lam, system = self._clg(pa[level], pb[level], gx / f, gy / f, field / f, contact,
                                                        prior / f, span=span)
            field = field * f
        if self.params.adaptive:
            field, weakened = self._adapt(system, field, level_prior, lam, span=span)
            lam = lam * (1.0 - (1.0 - _SHARP) * weakened)  # each node's membrane (across the detail), for its sigma
        system.residuals(field)
        residual = system.abs_residual
        med = float(np.median(residual[contact]))
        valid = contact & (residual <= max(self.params.max_residual_ratio * med, self.params.residual_floor) + 1e-6)
        # A node whose window leaves the second image cannot be registered there (the outer nodes' windows touch
        # the image's edge: a solver's rounding, 1e-4 px outwards, does not count).
        h, w = fa.raw.shape
        half = self._win // 2 - _EDGE_TOLERANCE_PX
        tx, ty = gxx + field[..., 0], gyy + field[..., 1]
        valid &= (tx >= half) & (tx <= w - 1 - half) & (ty >= half) & (ty <= h - 1 - half)
        n_out = int((contact & ~valid).sum())
        disp = np.where(valid[..., None], field, np.nan)
        status = "ok" if valid.any() else "no node registered"
        check = system.check(lam, self.regularisation(span=span), field=field)
        if valid.any():
            # A self-check: right registrations leave windows alike; a field locked onto wrong ridges does not.
            match = float(np.median(check.match[valid]))
            # ...and the whole image's phase correlation and the field agree within a ridge period.
            departure = float(np.hypot(*(np.median(field[valid], axis=0) - shift)))
            if not match >= MIN_MATCH:
                status = (f"doubted: the frames do not match after the measured motion (median window match "
                          f"{match:.2f} < {MIN_MATCH})")
            elif global_check and departure > self.calibration.px(RIDGE_PERIOD_MM):
                status = (f"doubted: the field departs {departure:.1f} px from the frames' global shift (more than a "
                          "ridge period)")
        return FlowField(frame_a, frame_b, gx, gy, disp, valid, shift, n_out, status,
                         sigma=np.where(valid, check.sigma, np.nan), match=np.where(valid, check.match, np.nan))

    def _clg(self, a, b, gx, gy, field, contact, prior, *, span=False):
        """Gauss-Newton on all nodes at once: windowed brightness constancy at each node (Lucas-Kanade) plus a
        membrane term tying each node's deviation from a ``prior`` to its neighbours', solved by SOR sweeps
        alternating with re-fits of the prior. The neighbour term carries the along-ridge component, which one
        window cannot see (aperture problem), from the pores and minutiae nearby.

        The prior is the global affine fitted to the field plus, for a pair (``local_prior``), the field's own
        deviation from it smoothed over ``_PRIOR_SIGMA_NODES`` (:func:`_local_prior`): the membrane then acts on
        the detail finer than about half a window (noise) and no longer pulls a smoothly curved field (a fingertip
        turning, its sides lagging) towards the affine. Either way it leaves uniform strain and rotation unbiased,
        borders included.

        ``span``: refining a composed span (:meth:`compute_spans`), with ``_SPAN_ITERATIONS`` iterations, a
        membrane ``_SPAN_SMOOTHNESS`` times a pair's and the affine prior alone.

        Returns the field, the last affine prior and the membrane weight (what :meth:`_adapt` continues from)."""
        sys_ = _LinearSystem(self, a, b, gx, gy, contact)
        nx, ny = sys_.node_x, sys_.node_y
        # The affine's least-squares fit to the contact nodes is a fixed linear map of their field: made once.
        fit = np.linalg.pinv(np.column_stack([nx[contact], ny[contact], np.ones(int(contact.sum()))]))
        full = np.stack([nx, ny, np.ones_like(nx)], axis=-1)
        lam = 0.0
        iterations = _SPAN_ITERATIONS if span else int(self.params.refine_iterations)
        smoothness = self.params.smoothness * (_SPAN_SMOOTHNESS if span else 1.0)

        local = None if span or not self.params.local_prior else _LocalPrior(contact)

        def fit_prior():
            affine = full @ (fit @ field[contact])
            return affine if local is None else local(affine, field)

        for _ in range(iterations):
            # Re-fit the affine prior to the current field (and again between solves below): the sweeps move the
            # smooth (affine) part of the field slowly, so a biased start would otherwise persist under a strong
            # smoothness term.
            prior = fit_prior()
            sys_.linearise(field)
            lam = smoothness * sys_.median_weight()
            for r in range(int(self.params.prior_refits)):
                if r:
                    prior = fit_prior()
                field = sor(field, prior, sys_.gxx, sys_.gxy, sys_.gyy, sys_.rx, sys_.ry, contact, lam,
                             int(self.params.solver_sweeps), float(self.params.sor_omega))
        return field, prior, lam, sys_

    def _adapt(self, sys_: "_LinearSystem", field, prior, lam, *, span: bool = False):
        """Adaptive (locally varying) regularization: where the data ask for detail the membrane smooths away,
        weaken it there.

        Linearised at the smooth field, the same system is solved with a membrane ``_SHARP`` times weaker (the
        *sharp* field). Where the sharp field explains a larger share of the local image residual than noise
        would (``Delta^T G Delta``, the data energy the change buys, over the residual energy ``sum It^2``, both
        summed over ~2 nodes around, times the window area; noise alone gives ~1-2), the membrane weight falls
        towards the sharp one (linearly between ``_ADAPT_FROM`` and ``_ADAPT_TO``) across the level lines of the
        sharp field's deviation from the prior, and along them only as far as that detail has no single direction
        (:func:`_anisotropic_membrane`), and ``_ADAPT_ITERATIONS`` Gauss-Newton iterations re-solve with that
        locally varying, anisotropic membrane. Smoothing along the detail costs no resolution and removes noise
        (the `star` and `ablation` benches; tuning log "Moved from docstrings"). A brightness change the
        motion cannot explain mostly raises the residual, not the explained share, so it is left smoothed; over a
        span of frames, though, the skin moves far enough through glass-fixed patterns (ridge, valley) for the sharp field
        to follow them (see :meth:`compute_spans`). Nothing changes where no node qualifies (the iterations are
        skipped), and never near the image border.

        ``span``: refining a field composed over a longer span (:meth:`compute_spans`), with
        ``_SPAN_ADAPT_ITERATIONS`` iterations.
        """
        contact = sys_.contact
        sys_.linearise(field, with_residual=True)
        if not np.any(contact & (sys_.inb > 0)):
            return field, np.zeros(contact.shape)
        sharp = sor(field, prior, sys_.gxx, sys_.gxy, sys_.gyy, sys_.rx, sys_.ry, contact, _SHARP * lam,
                     2 * int(self.params.solver_sweeps), float(self.params.sor_omega))
        delta = sharp - field
        cw = contact.astype(np.float64)
        q = (sys_.gxx * delta[..., 0] ** 2 + 2.0 * sys_.gxy * delta[..., 0] * delta[..., 1]
             + sys_.gyy * delta[..., 1] ** 2) * cw
        explained = gaussian_filter(q, _ADAPT_SIGMA_NODES) / np.maximum(
            gaussian_filter(sys_.residual * cw, _ADAPT_SIGMA_NODES), 1e-9) * float(self._win**2)
        # Not near the image border, where a window's data run into the mirrored padding (nor where a node has no
        # data, its window out of the second image): there the smooth field holds.
        weight = np.clip((explained - _ADAPT_FROM) / (_ADAPT_TO - _ADAPT_FROM), 0.0, 1.0) * cw * sys_.inner(field)
        if not np.any(weight > 0):
            return field, weight
        edges = membrane_edge_weights(*_anisotropic_membrane(sharp - prior, weight, lam))
        field = field + weight[..., None] * delta
        for _ in range(_SPAN_ADAPT_ITERATIONS if span else _ADAPT_ITERATIONS):
            sys_.linearise(field)
            field = sor_tensor(field, prior, sys_.gxx, sys_.gxy, sys_.gyy, sys_.rx, sys_.ry, contact, *edges,
                               2 * int(self.params.solver_sweeps), float(self.params.sor_omega))
        return field, weight


# The flow's tuned constants, one line each; the sweeps that chose them are in docs/tuning-log.md ("Dense flow").
#: The sharp field's membrane weight relative to the smooth one (:meth:`DenseFlow._adapt`).
_SHARP = 0.03
#: How far (px) a node's window may reach past the image's edge in the second image and still count as inside.
_EDGE_TOLERANCE_PX = 0.01
#: Gauss-Newton iterations of a span's smooth stage (one left a strongly curved span short of its fixed point).
_SPAN_ITERATIONS = 2
#: A span's membrane weight relative to a pair's: its bias grows with the span's non-affine motion, its noise not.
_SPAN_SMOOTHNESS = 0.3
#: A pair's local prior: the field's deviation from the affine smoothed over this many grid steps (half a window).
_PRIOR_SIGMA_NODES = 2.0
#: Gauss-Newton iterations with the adaptive, locally varying membrane (a span, a pair).
_SPAN_ADAPT_ITERATIONS = 2
_ADAPT_ITERATIONS = 2
#: The explained-residual share (times the window area) from which the membrane weight starts to fall, and at which
#: it is the sharp one; smoothed over this many nodes.
_ADAPT_FROM = 8.0
_ADAPT_TO = 12.0
_ADAPT_SIGMA_NODES = 2.0
#: SOR sweeps (times ``solver_sweeps``) of each smoothing that estimates the membrane's bias (converged at 2).
_BIAS_SWEEPS = 2


class _LocalPrior:
    """``affine`` plus the deviation of ``field`` from it, Gaussian-smoothed over ``_PRIOR_SIGMA_NODES`` grid steps
    among the contact nodes only (normalised convolution: nodes out of contact neither count nor pull). The
    smoothing is ``scipy.ndimage.gaussian_filter`` (zero beyond the grid) as two small matrices, and the
    normalisation, which depends on the contact alone, is made once."""

    def __init__(self, contact: np.ndarray) -> None:
        self.weight = contact.astype(np.float64)
        self.rows, self.cols = (_gaussian_matrix(n, _PRIOR_SIGMA_NODES) for n in contact.shape)
        self.norm = np.maximum(self.rows @ self.weight @ self.cols.T, 1e-9)

    def __call__(self, affine: np.ndarray, field: np.ndarray) -> np.ndarray:
        dev = (field - affine) * self.weight[..., None]
        smooth = [self.rows @ dev[..., c] @ self.cols.T / self.norm for c in range(2)]
        return affine + np.stack(smooth, axis=-1)


def _gaussian_matrix(n: int, sigma: float) -> np.ndarray:
    """The (n, n) matrix of ``scipy.ndimage.gaussian_filter1d`` along an axis of n samples, ``mode="constant"``
    (its kernel: truncated at 4 sigma, normalised to sum 1)."""
    radius = int(4.0 * sigma + 0.5)
    x = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * x * x / sigma**2)
    kernel /= kernel.sum()
    i = np.arange(n)
    offset = i[None, :] - i[:, None]
    return np.where(np.abs(offset) <= radius, kernel[np.clip(offset + radius, 0, 2 * radius)], 0.0)


def _anisotropic_membrane(deviation: np.ndarray, weight: np.ndarray, lam: float):
    """The membrane tensor ``D`` (``Dxx, Dxy, Dyy`` per node) of the adaptive regularization: weakened by
    ``weight`` (towards ``_SHARP * lam``) across the level lines of the sharp field's ``deviation`` from the affine
    prior, and along them only as much as the deviation is not one-dimensional there.

    The detail the data ask for (a star's fringes, a slip front's band) varies across its level lines and hardly
    along them: smoothing along them costs no resolution and removes noise. The direction and the coherence
    ``c = (mu1 - mu2) / (mu1 + mu2)`` come from the structure tensor of both components' gradients, smoothed over
    ``_ADAPT_SIGMA_NODES``; where the detail has no single direction (``c`` = 0) the membrane is weakened alike in
    every direction."""
    jxx = np.zeros(weight.shape)
    jxy = np.zeros(weight.shape)
    jyy = np.zeros(weight.shape)
    for c in range(2):
        dy, dx = np.gradient(deviation[..., c])
        jxx += dx * dx
        jxy += dx * dy
        jyy += dy * dy
    jxx, jxy, jyy = (gaussian_filter(j, _ADAPT_SIGMA_NODES) for j in (jxx, jxy, jyy))
    spread = np.sqrt((jxx - jyy) ** 2 + 4.0 * jxy**2)
    coherence = spread / np.maximum(jxx + jyy, 1e-300)
    phi = 0.5 * np.arctan2(2.0 * jxy, jxx - jyy)  # direction of the strongest change (across the level lines)
    cos, sin = np.cos(phi), np.sin(phi)
    across = lam * (1.0 - weight) + _SHARP * lam * weight
    along = lam * (1.0 - weight * (1.0 - coherence)) + _SHARP * lam * weight * (1.0 - coherence)
    return (across * cos**2 + along * sin**2, (across - along) * cos * sin, across * sin**2 + along * cos**2)


class _LinearSystem:
    """The data term of one pyramid level, linearised about a field: per node, the window sums of the gradient
    products ``G`` (``gxx, gxy, gyy``) and the right-hand side ``G u - b`` (``rx, ry``) of brightness constancy
    against the second image warped by the field (:func:`~skinstretch.processing.flow_kernels.warped_moments`, over
    the box of nodes in contact), and optionally the residual energy ``sum It^2``. Nodes whose window leaves the
    second image get no data term (they follow their neighbours and are flagged invalid at the end)."""

    def __init__(self, flow: "DenseFlow", a: np.ndarray, b: np.ndarray, gx: np.ndarray, gy: np.ndarray,
                 contact: np.ndarray) -> None:
        h, w = a.shape
        self.flow, self.a, self.b, self.gx, self.gy, self.contact = flow, a, b, gx, gy, contact
        self.shape = (h, w)
        self.half = flow.window_px // 2
        self.rows = np.clip(np.round(gy).astype(np.int64), 0, h - 1)
        self.cols = np.clip(np.round(gx).astype(np.int64), 0, w - 1)
        r, c = np.nonzero(contact.any(axis=1))[0], np.nonzero(contact.any(axis=0))[0]
        self.box = (int(r[0]), int(r[-1]) + 1, int(c[0]), int(c[-1]) + 1) if r.size else (0, 0, 0, 0)
        self.node_x, self.node_y = np.meshgrid(gx, gy)
        self._texture: np.ndarray | None = None

    def _moments(self, field: np.ndarray) -> np.ndarray:
        gx, gy = self.gx, self.gy
        return warped_moments(self.a, self.b, np.ascontiguousarray(field, dtype=np.float64), gx[0], gy[0],
                              gx[1] - gx[0], gy[1] - gy[0], self.rows, self.cols, self.half, *self.box)

    def linearise(self, field: np.ndarray, *, with_residual: bool = False) -> None:
        # Window sums of Ix^2, IxIy, Iy^2, IxIt, IyIt (gradients of the mean of both images), It^2, |It|.
        m = self._moments(field)
        h, w = self.shape
        half = self.half
        tx, ty = self.node_x + field[..., 0], self.node_y + field[..., 1]
        inb = ((tx >= half) & (tx <= w - 1 - half) & (ty >= half) & (ty <= h - 1 - half)).astype(np.float64)
        self.inb = inb
        self.gxx, self.gxy, self.gyy, bx, by = (m[i] * inb for i in range(5))
        u0 = np.ascontiguousarray(field, dtype=np.float64)
        self.rx = self.gxx * u0[..., 0] + self.gxy * u0[..., 1] - bx
        self.ry = self.gxy * u0[..., 0] + self.gyy * u0[..., 1] - by
        if with_residual:
            self._residuals(m)

    def residuals(self, field: np.ndarray) -> None:
        """The windows' residuals at ``field`` (for :meth:`check`), the gradient products as last linearised."""
        self._residuals(self._moments(field))

    def _residuals(self, m: np.ndarray) -> None:
        self.residual = m[5] * self.inb
        self.abs_residual = m[6] / float((2 * self.half + 1) ** 2)

    def check(self, membrane=None, regularisation: Regularisation | None = None, *,
              field: np.ndarray | None = None) -> RegistrationCheck:
        """Each node's :func:`registration_check` (gradient products, residual and texture variances; the
        ``membrane`` weight and ``regularisation`` that smoothed the field); given the solved ``field``, each
        sigma also holds, in quadrature, what the membrane's smoothing biases there
        (:func:`~skinstretch.processing.flow_kernels.membrane_bias`)."""
        n = float((2 * self.half + 1) ** 2)
        if self._texture is None:
            # Each node's window inside the image (the full-resolution level: nodes at least half a window in).
            half, r, c = self.half, self.rows[:, None], self.cols[None, :]
            total, squares = cv2.integral2(self.a, sdepth=cv2.CV_64F, sqdepth=cv2.CV_64F)
            h, w = self.shape
            r0, r1 = np.maximum(r - half, 0), np.minimum(r + half + 1, h)
            c0, c1 = np.maximum(c - half, 0), np.minimum(c + half + 1, w)
            mean, sq = ((ii[r1, c1] - ii[r0, c1] - ii[r1, c0] + ii[r0, c0]) / n for ii in (total, squares))
            self._texture = np.maximum(sq - mean * mean, 0.0)
        check = registration_check(self.gxx, self.gxy, self.gyy, self.residual / max(n - 2.0, 1.0), self._texture,
                                   model_sigma_px=self.flow.params.model_sigma_px, membrane=membrane,
                                   regularisation=regularisation)
        if field is None or membrane is None:
            return check
        bias = membrane_bias(field, membrane, self.contact, self.node_x, self.node_y, self.gxx, self.gxy, self.gyy,
                             sweeps=_BIAS_SWEEPS * int(self.flow.params.solver_sweeps),
                             omega=float(self.flow.params.sor_omega))
        return RegistrationCheck(np.sqrt(check.sigma ** 2 + bias ** 2), check.match)

    def inner(self, field: np.ndarray) -> np.ndarray:
        """Nodes whose window, in both images, stays one grid step (and 2 px) away from the image border."""
        h, w = self.shape
        m = self.half + max(self.flow.grid_step_px, 2)
        out = np.ones(field.shape[:2], bool)
        for x, y in ((self.node_x, self.node_y), (self.node_x + field[..., 0], self.node_y + field[..., 1])):
            out &= (x >= m) & (x <= w - 1 - m) & (y >= m) & (y <= h - 1 - m)
        return out

    def median_weight(self) -> float:
        """Median data weight (trace of G) over the contact nodes with data (1 when there are none)."""
        ok = self.contact & (self.inb > 0)
        return float(np.median((self.gxx + self.gyy)[ok])) if ok.any() else 1.0


class SpanRefiner:
    """Refines spans one at a time, as consecutive fields arrive (a streaming analysis, or
    :meth:`DenseFlow.compute_spans`): the fields of frames k..k + s composed (:func:`compose_fields`), then
    registered from frame k to frame k + s directly. ``frame(j)`` gives frame j (the fields' frame numbers), each
    prepared once (``frames``: :meth:`DenseFlow.span_frames`, which a :class:`ReferenceRefiner` may share)."""

    def __init__(self, flow: DenseFlow, frame: Callable[[int], np.ndarray], *, frames: SpanFrames | None = None) -> None:
        self.flow = flow
        self._frames = frames if frames is not None else flow.span_frames(frame)
        self.seconds = 0.0  # spent in refine (the stage's share of the analysis' time)

    def refine(self, fields: Sequence[FlowField]) -> FlowField:
        """The span from ``fields[0].frame_a`` to ``fields[-1].frame_b`` (consecutive fields, in order)."""
        if not fields:
            raise InvalidInputError("a span needs at least one field")
        t0 = time.perf_counter()
        k0, k1 = int(fields[0].frame_a), int(fields[-1].frame_b)
        prev, curr = self._frames.pair(k0, k1)
        out = self.flow._register(prev, curr, k0, k1, None, compose_fields(fields))
        self.seconds += time.perf_counter() - t0
        return out


class ReferenceRefiner(SpanRefiner):
    """DIC's reference frame: the field from a reference frame to frame k composed with the field k -> k + 1 and
    registered from the reference frame to k + 1 directly (:meth:`advance`): the steps' biases do not add up as a
    chain's do. The reference frame stays prepared; frame k + 1 comes from ``frames`` (shared with a
    :class:`SpanRefiner`, it is prepared once for both), which then drops frames more than its ``keep`` before it."""

    def __init__(self, flow: DenseFlow, frame: Callable[[int], np.ndarray], *, frames: SpanFrames | None = None) -> None:
        super().__init__(flow, frame, frames=frames)
        self._reference: tuple[int, object] | None = None

    def advance(self, reference: FlowField, field: FlowField) -> tuple[FlowField, FlowField]:
        """(the estimate to carry on, what was measured) from ``reference.frame_a`` to ``field.frame_b``, which
        follows ``reference.frame_b``. A node not measured at frame b (a refused or occluded frame) keeps its last
        displacement in the estimate, to be registered again at the next frame; a field with no valid node (a
        frame the flow refused) is taken as no motion, for the registration to find it."""
        if not field.valid.any():
            field = FlowField(field.frame_a, field.frame_b, field.grid_x, field.grid_y,
                              np.zeros_like(field.displacement), np.ones_like(field.valid), np.zeros(2), 0)
        t0 = time.perf_counter()
        k0, k1 = int(reference.frame_a), int(field.frame_b)
        if self._reference is None or self._reference[0] != k0:
            self._reference = (k0, self._frames.get(k0))
        curr, _ = self._frames.pair(k1, k1)
        measured = self.flow._register(self._reference[1], curr, k0, k1, None, compose_fields([reference, field]))
        self.seconds += time.perf_counter() - t0
        keep = measured.valid | reference.valid
        disp = np.where(measured.valid[..., None], measured.displacement, reference.displacement)
        return FlowField(reference.frame_a, field.frame_b, reference.grid_x, reference.grid_y,
                         np.where(keep[..., None], disp, np.nan), keep, measured.global_shift, 0), measured


def compose_fields(fields: Sequence[FlowField]) -> FlowField:
    """The displacement from the first field's frame to the last field's second frame on the first field's grid,
    following each node's skin point through the fields in turn (bilinear, :meth:`FlowField.sample`); a node
    whose point is lost on the way (outside a grid, next to an invalid node) is invalid."""
    if not fields:
        raise InvalidInputError("compose_fields needs at least one field")
    first = fields[0]
    gxx, gyy = np.meshgrid(first.grid_x, first.grid_y)
    start = np.column_stack([gxx.ravel(), gyy.ravel()])
    ok = first.valid.ravel().copy()
    p = start + np.nan_to_num(first.displacement.reshape(-1, 2))
    for f in fields[1:]:
        gx, gy = f.grid_x, f.grid_y
        compose_steps(p, ok, f.displacement[None], f.valid[None], float(gx[0]), float(gy[0]),
                      float(gx[1] - gx[0]) if gx.size > 1 else 1.0, float(gy[1] - gy[0]) if gy.size > 1 else 1.0)
    disp = np.where(ok[:, None], p - start, np.nan).reshape(first.displacement.shape)
    valid = ok.reshape(first.valid.shape)
    shift = sum((np.asarray(f.global_shift, dtype=np.float64) for f in fields), np.zeros(2))
    return FlowField(first.frame_a, fields[-1].frame_b, first.grid_x, first.grid_y, disp, valid, shift,
                     int((~valid).sum() - (~first.valid).sum()), "ok" if valid.any() else "no node followed through")


def _gray(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2:
        raise InvalidInputError(f"{name} must be a 2-D grey image, got shape {image.shape}")
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    return image

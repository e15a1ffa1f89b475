"""The dense method: displacement and strain over the contact region without features (beyond the seed, 7.2:
"other methods, such as an analysis of the optical flow, could provide better results").

Design (:class:`DenseFlow`), chosen against DIS, Farneback and DeepFlow on fingerprint texture:

1. Both frames are contrast-normalised locally (illumination is fixed to the prism, not to the skin).
2. Coarse global motion by phase correlation of the whole images, then an affine motion by ECC on the top
   pyramid level started from it. Local window methods started at zero lock onto a neighbouring ridge; started
   from the affine motion they are within a fraction of a ridge period.
3. Every node of a regular grid (0.2 mm) in the contact region is registered with a ~0.8 mm window
   (Lucas-Kanade data term), coupled to its neighbours by a membrane term on the deviation from the (re-fitted)
   affine motion, solved by over-relaxed (SOR) sweeps alternating with re-fits of the affine (a joint fit of
   field and affine); Gauss-Newton iterations re-warp the second image. The
   coupling supplies the along-ridge component a single window cannot see (aperture problem); acting on the
   deviation from an affine, it does not bias uniform strain. The warp is bilinear: OpenCV's bicubic kernel
   (a = -0.75) biased the displacement by up to 0.04 px depending on its sub-pixel part, bilinear by < 0.01 px
   (a noiseless rendering shifted in Fourier space, independent noise added). The kernels are numba (nogil):
   window sums of the five gradient products in one pass down the image, the remap coordinates, the solver.
4. Nodes out of contact (a flat window), whose window leaves the second image, or whose residual is far above
   the median are flagged invalid, never silently kept.

Strain comes from the grid (:func:`grid_strain`: small-strain tensor by finite differences) or from
:func:`skinstretch.processing.stretch.triangulation_strain` on the grid's :meth:`FlowField.motion`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from pydantic import Field, field_validator
from scipy.ndimage import map_coordinates

from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.global_motion import GlobalMotionEstimator
from skinstretch.processing.parameters import parameters
from skinstretch.processing.displacement_refinement import local_normalize
from skinstretch.processing.texture_gate import TEXTURE_REASONS, texture_verdict
from skinstretch.processing.tracking import MotionSample


@parameters
class FlowParams:
    """Options of :class:`DenseFlow`, in mm and grey levels.

    Parameters
    ----------
    grid_step_mm : float
        Spacing of the measurement grid.
    window_px : int or None
        The window's side in pixels (odd, >= 7) instead of ``window_mm`` (None: from ``window_mm``).
    window_mm : float
        Side of the registration window (about two ridge periods). With ``smoothness`` 1.5 it beats 0.6 mm / 1.0
        in edge strain on the seed's scenes (and DeepFlow's, on the same pairs); wider windows do better still
        inside the field but err by up to 0.25 px at its border under a large shift plus 2 % strain.
    pyramid_levels : int
        Pyramid levels above full resolution for the first registration.
    min_contrast : float
        Minimum local grey-level standard deviation for a node to count as in contact (FTIR: no contact = no
        ridges = flat bright image).
    smoothness : float
        Weight of the coupling between neighbouring nodes, relative to the median data weight.
    refine_iterations, solver_sweeps : int
        Gauss-Newton iterations per pyramid level, and over-relaxed (SOR) sweeps of the coupled system per
        iteration.
    sor_omega : float
        Over-relaxation factor of those sweeps, in (0, 2); 1 is Gauss-Seidel.
    prior_refits : int
        Per Gauss-Newton iteration, how many times the affine prior is re-fitted to the field and the coupled
        system re-solved (``solver_sweeps`` each). Along the ridges the data barely constrain the field, so
        there it follows the prior: with a single fit per iteration a wrong start in uniform strain (e.g.
        0.2 % along the ridges after ECC) persists.
    max_residual_ratio : float
        A node whose registration residual exceeds this multiple of the median is flagged invalid.
    clg_levels : int
        Pyramid levels above full resolution on which the coupled registration also runs, coarse to fine, after
        the affine start (0: full resolution only, enough after the affine start on the seed's scenes).
    normalize_sigma_mm : float or None
        Local contrast normalisation scale (see :func:`skinstretch.processing.displacement_refinement.local_normalize`).
    """

    grid_step_mm: float = Field(0.2, gt=0)
    window_mm: float = Field(0.8, gt=0)
    window_px: int | None = Field(None, ge=7)
    pyramid_levels: int = Field(2, ge=0, le=5)
    min_contrast: float = Field(8.0, ge=0)
    smoothness: float = Field(1.5, ge=0)
    refine_iterations: int = Field(3, ge=1)
    solver_sweeps: int = Field(15, ge=1)
    sor_omega: float = Field(1.8, gt=0, lt=2)
    prior_refits: int = Field(4, ge=1)
    max_residual_ratio: float = Field(3.0, gt=0)
    clg_levels: int = Field(0, ge=0, le=5)
    normalize_sigma_mm: float | None = Field(0.15, gt=0)

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
        return MotionSample(self.frame_a, self.frame_b, pts, self.displacement[rows, cols], rows * gx + cols)

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear displacement at ``points`` (n, 2); returns (displacement, valid) with NaN where not valid
        (outside the grid or next to an invalid node)."""
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
        field = np.where(self.valid[..., None], self.displacement, 0.0)
        out = np.stack([map_coordinates(field[..., i], coords, order=1, mode="nearest") for i in range(2)], axis=1)
        ok = inside & ~near_bad
        out[~ok] = np.nan
        return out, ok


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
        self._step = max(2, calibration.px_int(self.params.grid_step_mm))
        self._win = self.params.window_px or calibration.odd_px(self.params.window_mm, minimum=7)
        self._estimator = GlobalMotionEstimator()

    def grid(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Grid node coordinates (x, y) for images of ``shape``: nodes whose window fits in the image."""
        h, w = shape
        half = self._win // 2
        gx = np.arange(half, w - half, self._step, dtype=np.float64)
        gy = np.arange(half, h - half, self._step, dtype=np.float64)
        return gx, gy

    def compute(
        self,
        image_a: np.ndarray,
        image_b: np.ndarray,
        *,
        frame_a: int = 0,
        frame_b: int = 1,
        initial_shift: np.ndarray | None = None,
    ) -> FlowField:
        """Displacement field from ``image_a`` to ``image_b`` (2-D grey images of the same shape)."""
        a = _gray(image_a, "image_a")
        b = _gray(image_b, "image_b")
        if a.shape != b.shape:
            raise InvalidInputError(f"images differ in shape: {a.shape} vs {b.shape}")
        self._check_shape(a.shape)
        # The second core prepares frame b meanwhile (the kernels release the GIL).
        fb = _helper_pool().submit(self._prepare, b, contact=False)
        fa = self._prepare(a)
        return self._register(fa, fb.result(), frame_a, frame_b, initial_shift)

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
        refused = texture_verdict(image, px_per_mm=self.calibration.px_per_mm).reason
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
        for _ in range(int(self.params.pyramid_levels)):
            pyramid.append(cv2.pyrDown(pyramid[-1]))
        return _Prepared(image, pyramid, nodes)

    def _register(
        self, fa: _Prepared, fb: _Prepared, frame_a: int, frame_b: int, initial_shift: np.ndarray | None
    ) -> FlowField:
        gx, gy = self.grid(fa.raw.shape)
        if fa.refused or fb.refused:
            return FlowField(frame_a, frame_b, gx, gy, np.full((gy.size, gx.size, 2), np.nan),
                             np.zeros((gy.size, gx.size), bool), np.full(2, np.nan), 0, fa.refused or fb.refused,
                             (fa.refused, fb.refused))
        if initial_shift is None:
            shift = self._estimator.estimate(fa.raw, fb.raw).shift
        else:
            shift = np.asarray(initial_shift, dtype=np.float64).reshape(2)
        contact = fa.contact
        gyn, gxn = gy.size, gx.size
        if not np.any(contact):
            return FlowField(frame_a, frame_b, gx, gy, np.full((gyn, gxn, 2), np.nan), np.zeros((gyn, gxn), bool),
                             shift, 0, "no contact", ("no contact", ""))
        pa, pb = fa.pyramid, fb.pyramid
        top = int(self.params.pyramid_levels)
        # The smoothness term acts on the deviation from this global affine motion (see _clg).
        affine = _affine_init(pa[top], pb[top], shift / 2.0**top)
        gxx, gyy = np.meshgrid(gx, gy)
        if affine is None:
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
        for level in range(min(top, int(self.params.clg_levels)), -1, -1):
            f = 2.0**level
            field = self._clg(pa[level], pb[level], gx / f, gy / f, field / f, contact, prior / f) * f
        residual = self._residual(pa[0], pb[0], gx, gy, field)
        med = float(np.median(residual[contact]))
        valid = contact & (residual <= self.params.max_residual_ratio * med + 1e-6)
        # A node whose window leaves the second image cannot be registered there.
        h, w = fa.raw.shape
        half = self._win // 2
        tx, ty = gxx + field[..., 0], gyy + field[..., 1]
        valid &= (tx >= half) & (tx <= w - 1 - half) & (ty >= half) & (ty <= h - 1 - half)
        n_out = int((contact & ~valid).sum())
        disp = np.where(valid[..., None], field, np.nan)
        status = "ok" if valid.any() else "no node registered"
        return FlowField(frame_a, frame_b, gx, gy, disp, valid, shift, n_out, status)

    def _warp(self, b, gx, gy, field):
        """``b`` sampled (bilinear) at each pixel plus the grid field (bilinear between nodes, constant beyond)."""
        h, w = b.shape
        mx, my = _warp_maps(np.ascontiguousarray(field, dtype=np.float64), gx[0], gy[0], gx[1] - gx[0],
                            gy[1] - gy[0], h, w)
        return cv2.remap(b, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)

    def _clg(self, a, b, gx, gy, field, contact, prior):
        """Gauss-Newton on all nodes at once: windowed brightness constancy at each node (Lucas-Kanade) plus a
        membrane term tying each node's deviation from the global affine ``prior`` to its neighbours', solved by
        SOR sweeps alternating with re-fits of the affine. The neighbour term carries the along-ridge component, which one window cannot see
        (aperture problem), from the pores and minutiae nearby; acting on the deviation from the affine, it
        leaves uniform strain and rotation unbiased, borders included."""
        h, w = a.shape
        half = self._win // 2
        # Images padded (mirrored) so that every node's window and its 3x3 gradient stencil lie inside.
        pad = half + 1
        rows = np.clip(np.round(gy).astype(np.int64), 0, h - 1) + pad
        cols = np.clip(np.round(gx).astype(np.int64), 0, w - 1) + pad
        a_pad = cv2.copyMakeBorder(a, pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
        gxx_, gyy_ = np.meshgrid(gx, gy)
        design = np.column_stack([gxx_[contact], gyy_[contact], np.ones(int(contact.sum()))])
        full = np.stack([gxx_, gyy_, np.ones_like(gxx_)], axis=-1)
        for _ in range(int(self.params.refine_iterations)):
            # Re-fit the affine prior to the current field (and again between solves below): the sweeps move the
            # smooth (affine) part of the field slowly, so a biased start would otherwise persist under a strong
            # smoothness term.
            coef, *_ = np.linalg.lstsq(design, field[contact], rcond=None)
            prior = full @ coef
            bw = cv2.copyMakeBorder(self._warp(b, gx, gy, field), pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
            # Window sums of Ix^2, IxIy, Iy^2, IxIt, IyIt (gradients of the mean of both images).
            m = _window_moments(a_pad + bw, bw - a_pad, rows, cols, half)
            # Nodes whose window leaves the second image compare against border padding: no data term there
            # (they follow their neighbours and are flagged invalid at the end).
            tx, ty = gx[None, :] + field[..., 0], gy[:, None] + field[..., 1]
            inb = ((tx >= half) & (tx <= w - 1 - half) & (ty >= half) & (ty <= h - 1 - half)).astype(np.float64)
            gxx, gxy, gyy, bx, by = (m[i] * inb for i in range(5))
            lam = self.params.smoothness * float(np.median((gxx + gyy)[contact & (inb > 0)] if (inb > 0).any() else 1.0))
            u0 = np.ascontiguousarray(field, dtype=np.float64)
            # right-hand side of the linearised data term: G u0 - b
            rx = gxx * u0[..., 0] + gxy * u0[..., 1] - bx
            ry = gxy * u0[..., 0] + gyy * u0[..., 1] - by
            field = u0
            for r in range(int(self.params.prior_refits)):
                if r:
                    coef, *_ = np.linalg.lstsq(design, field[contact], rcond=None)
                    prior = full @ coef
                field = _sor(field, prior, gxx, gxy, gyy, rx, ry, contact, lam, int(self.params.solver_sweeps),
                             float(self.params.sor_omega))
        return field

    def _residual(self, a, b, gx, gy, field):
        """Mean absolute difference of ``a`` and the warped ``b`` over each node's window (nodes lie inside)."""
        bw = self._warp(b, gx, gy, field)
        half = self._win // 2
        rr = np.round(gy).astype(np.int64)[:, None]
        cc = np.round(gx).astype(np.int64)[None, :]
        ii = cv2.integral(cv2.absdiff(bw, a), sdepth=cv2.CV_64F)
        lo_r, hi_r, lo_c, hi_c = rr - half, rr + half + 1, cc - half, cc + half + 1
        return (ii[hi_r, hi_c] - ii[lo_r, hi_c] - ii[hi_r, lo_c] + ii[lo_r, lo_c]) / float(self._win**2)


def _affine_init(a: np.ndarray, b: np.ndarray, shift: np.ndarray) -> np.ndarray | None:
    """Affine motion between two (downsampled) images by ECC, started from a translation; None if it fails.

    Returns the 2x3 matrix mapping frame-a points to frame-b points (at the resolution of ``a``)."""
    warp = np.array([[1, 0, shift[0]], [0, 1, shift[1]]], dtype=np.float32)
    try:
        # ECC's warp maps template (a) coordinates into the input image (b).
        _, warp = cv2.findTransformECC(
            a, b, warp, cv2.MOTION_AFFINE, (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4), None, 3
        )
    except cv2.error:
        return None
    if not np.all(np.isfinite(warp)) or np.abs(warp[:, :2] - np.eye(2)).max() > 0.3:
        return None
    return warp.astype(np.float64)


@numba.njit(cache=True, nogil=True)
def _warp_maps(field, gx0, gy0, step_x, step_y, h, w):
    """Remap coordinates (x + u, y + v) of every pixel, (u, v) bilinear between grid nodes, constant beyond."""
    gyn, gxn = field.shape[0], field.shape[1]
    mx = np.empty((h, w), np.float32)
    my = np.empty((h, w), np.float32)
    row_u = np.empty(gxn)
    row_v = np.empty(gxn)
    j0s = np.empty(w, np.int64)
    txs = np.empty(w)
    for x in range(w):
        fx = min(max((x - gx0) / step_x, 0.0), gxn - 1.0)
        j0 = min(int(fx), gxn - 2)
        j0s[x] = j0
        txs[x] = fx - j0
    for y in range(h):
        fy = min(max((y - gy0) / step_y, 0.0), gyn - 1.0)
        i0 = min(int(fy), gyn - 2)
        ty = fy - i0
        for j in range(gxn):
            row_u[j] = field[i0, j, 0] * (1 - ty) + field[i0 + 1, j, 0] * ty
            row_v[j] = field[i0, j, 1] * (1 - ty) + field[i0 + 1, j, 1] * ty
        for x in range(w):
            j0 = j0s[x]
            tx = txs[x]
            mx[y, x] = x + row_u[j0] * (1 - tx) + row_u[j0 + 1] * tx
            my[y, x] = y + row_v[j0] * (1 - tx) + row_v[j0 + 1] * tx
    return mx, my


@numba.njit(cache=True, nogil=True)
def _window_moments(s, d, rows, cols, half):
    """Window sums at nodes (rows x cols, window 2 half + 1) of Ix^2, IxIy, Iy^2, IxIt, IyIt, with (Ix, Iy) the
    3x3 Sobel gradient of ``s / 2`` (scaled to grey levels per pixel) and It = ``d``; returns (5, rows, cols).

    One pass down the image keeps running column sums and stores them at each node row's window edges (every
    pixel's products are computed once); ``rows`` must be increasing and the windows inside the (padded) image."""
    w = s.shape[1]
    nr, nc = rows.size, cols.size
    lo = np.zeros((nr, 5, w))
    hi = np.zeros((nr, 5, w))
    acc = np.zeros((5, w))
    k_lo = 0
    k_hi = 0
    for y in range(rows[0] - half, rows[nr - 1] + half + 1):
        while k_lo < nr and rows[k_lo] - half == y:
            lo[k_lo] = acc
            k_lo += 1
        for x in range(1, w - 1):
            gx = ((s[y - 1, x + 1] - s[y - 1, x - 1]) + 2.0 * (s[y, x + 1] - s[y, x - 1])
                  + (s[y + 1, x + 1] - s[y + 1, x - 1])) * 0.0625
            gy = ((s[y + 1, x - 1] - s[y - 1, x - 1]) + 2.0 * (s[y + 1, x] - s[y - 1, x])
                  + (s[y + 1, x + 1] - s[y - 1, x + 1])) * 0.0625
            t = d[y, x]
            acc[0, x] += gx * gx
            acc[1, x] += gx * gy
            acc[2, x] += gy * gy
            acc[3, x] += gx * t
            acc[4, x] += gy * t
        while k_hi < nr and rows[k_hi] + half == y:
            hi[k_hi] = acc
            k_hi += 1
    out = np.zeros((5, nr, nc))
    prefix = np.zeros(w + 1)
    for i in range(nr):
        for k in range(5):
            run = 0.0
            for x in range(w):
                run += hi[i, k, x] - lo[i, k, x]
                prefix[x + 1] = run
            for j in range(nc):
                out[k, i, j] = prefix[cols[j] + half + 1] - prefix[cols[j] - half]
    return out


@numba.njit(cache=True, nogil=True)
def _sor(u0, prior, gxx, gxy, gyy, rx, ry, contact, lam, sweeps, omega):
    """Block successive over-relaxation of the coupled system at contact nodes: per node, the 2x2 data term
    ``G`` plus ``lam`` times the number of contact neighbours, right-hand side ``r + lam * (sum of the
    neighbours' deviation from the prior + n * own prior)``, solved with the neighbours' latest values and
    over-relaxed by ``omega``. Nodes out of contact keep ``u0``. (Plain Jacobi needs hundreds of sweeps to carry
    the along-ridge component across the grid; SOR reaches the same solution in a few dozen.)"""
    gy_n, gx_n = contact.shape
    u = u0.copy()
    for _ in range(sweeps):
        for i in range(gy_n):
            for j in range(gx_n):
                if not contact[i, j]:
                    continue
                sx = 0.0
                sy = 0.0
                n = 0
                if i > 0 and contact[i - 1, j]:
                    sx += u[i - 1, j, 0] - prior[i - 1, j, 0]
                    sy += u[i - 1, j, 1] - prior[i - 1, j, 1]
                    n += 1
                if i < gy_n - 1 and contact[i + 1, j]:
                    sx += u[i + 1, j, 0] - prior[i + 1, j, 0]
                    sy += u[i + 1, j, 1] - prior[i + 1, j, 1]
                    n += 1
                if j > 0 and contact[i, j - 1]:
                    sx += u[i, j - 1, 0] - prior[i, j - 1, 0]
                    sy += u[i, j - 1, 1] - prior[i, j - 1, 1]
                    n += 1
                if j < gx_n - 1 and contact[i, j + 1]:
                    sx += u[i, j + 1, 0] - prior[i, j + 1, 0]
                    sy += u[i, j + 1, 1] - prior[i, j + 1, 1]
                    n += 1
                sx += n * prior[i, j, 0]
                sy += n * prior[i, j, 1]
                ax = gxx[i, j] + lam * n
                ay = gyy[i, j] + lam * n
                c = gxy[i, j]
                px = rx[i, j] + lam * sx
                py = ry[i, j] + lam * sy
                det = ax * ay - c * c
                if abs(det) < 1e-12:
                    det = 1e-12
                ux = (ay * px - c * py) / det
                uy = (ax * py - c * px) / det
                u[i, j, 0] += omega * (ux - u[i, j, 0])
                u[i, j, 1] += omega * (uy - u[i, j, 1])
    return u


def grid_strain(field: FlowField) -> tuple[np.ndarray, np.ndarray]:
    """Small-strain tensor (exx, eyy, exy) of a flow field by central differences on its grid.

    Returns ``(strain (GY, GX, 3), ok (GY, GX))``; strain is NaN exactly where ``ok`` is False (a node or one of
    its four neighbours invalid, or on the border).
    """
    d = field.displacement
    v = field.valid
    sx = field.grid_x[1] - field.grid_x[0]
    sy = field.grid_y[1] - field.grid_y[0]
    out = np.full(d.shape[:2] + (3,), np.nan)
    ok = np.zeros(v.shape, bool)
    ok[1:-1, 1:-1] = v[1:-1, 1:-1] & v[1:-1, 2:] & v[1:-1, :-2] & v[2:, 1:-1] & v[:-2, 1:-1]
    dudx = (d[1:-1, 2:, 0] - d[1:-1, :-2, 0]) / (2 * sx)
    dvdy = (d[2:, 1:-1, 1] - d[:-2, 1:-1, 1]) / (2 * sy)
    dudy = (d[2:, 1:-1, 0] - d[:-2, 1:-1, 0]) / (2 * sy)
    dvdx = (d[1:-1, 2:, 1] - d[1:-1, :-2, 1]) / (2 * sx)
    inner = np.stack([dudx, dvdy, 0.5 * (dudy + dvdx)], axis=-1)
    sub = out[1:-1, 1:-1]
    sub[ok[1:-1, 1:-1]] = inner[ok[1:-1, 1:-1]]
    return out, ok


def sample_dense_flow(flow: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bilinear sample of a dense (H, W, 2) flow (e.g. from OpenCV) at ``points`` (n, 2) x, y px."""
    flow = np.asarray(flow, dtype=np.float32)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise InvalidInputError(f"flow must have shape (H, W, 2), got {flow.shape}")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    coords = np.vstack([p[:, 1], p[:, 0]])
    return np.stack([map_coordinates(flow[..., i], coords, order=1, mode="nearest") for i in range(2)], axis=1)


def _gray(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2:
        raise InvalidInputError(f"{name} must be a 2-D grey image, got shape {image.shape}")
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    return image

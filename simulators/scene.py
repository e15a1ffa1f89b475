"""Rendering scenes: a fingertip sliding on a contact surface, as FTIR video with exact ground truth.

A :class:`~skinstretch.simulators.scene_description.Scene` (pydantic, loaded from YAML; re-exported here with
:func:`load_scene`, :func:`parse_scene` and :data:`SCENE_NAMES`) describes the camera, the print, the contact, the
surface, the motion and the deformation. :class:`SceneRenderer` renders any frame on demand and the ground truth
of the whole sequence; :func:`render_session` and :func:`simulate_to_file` render a whole scene.

Rendering (how frame k is made)
-------------------------------
1. Every image pixel is mapped to the contact surface with ``optics.image_to_surface`` (once, it never changes).
2. The surface point is mapped back to the skin point now there by inverting ``x = X + d_k(X)``
   (:meth:`skinstretch.simulators.deformation.FrameDeformation.inverse`, Newton's method) on a node grid every 8 px, which
   is interpolated to every pixel by separable Catmull-Rom splines (error <= 0.005 px, ~0.0003 px RMS, in the
   sliding scenes, up to 0.013 px in the last frames of the rotating ``flat1``; see the bench).
3. The print is sampled at the skin point from a master image rendered once in skin coordinates at
   ``oversample`` times the camera resolution, with bicubic ``cv2.remap`` (positions quantised to 1/32 of a
   master pixel, i.e. 1/64 px with the default ``oversample = 2``). The print is the synthetic one
   (:mod:`skinstretch.simulators.fingerprint`) or, with ``texture``, a real print image
   (:mod:`skinstretch.simulators.print_texture`; no feature truth then, the rest of the truth is the same).
4. Contact (an ellipse on the skin that grows with the normal force as ``F^(1/3)``, Hertz, with a soft edge,
   times the glass-fixed loss of contact of the surface, times a real print's coverage of the skin) blends the
   print with the bright background; the surface slope darkens the light (seed 3.2, 7.2), the camera adds
   vignetting, blur, noise and quantisation.

Steps 2-4 run on two fixed bands of image rows, in two threads when :attr:`SceneRenderer.threads` is 2 (the compiled
kernels of :mod:`skinstretch.simulators.scene_kernels` and ``cv2.remap`` release the GIL); the noise of frame k
comes from its own seeded stream. A frame is therefore the same bytes whatever the number of threads and the order
in which frames are rendered.

The true features are placed with the same field: ``p_k = surface_to_image(P + d_k(P))``.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from skinstretch.drivers.camera_modes import CameraMode, camera_mode as _camera_mode
from skinstretch.drivers.session_file import SessionTruth, write_session
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.progress import progress_bar
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.sensor_model import CameraModel
from skinstretch.simulators.deformation import (
    DeformationModel,
    FrameDeformation,
    MotionProfile,
    PlasticDistortion,
    RidgeMechanics,
    SlipFront,
    green_lagrange,
)
from skinstretch.simulators.fingerprint import Fingerprint, FingerprintParams
from skinstretch.simulators.ideal_optics import IdealOptics, Optics
from skinstretch.simulators.print_texture import RealPrintTexture, load_print
from skinstretch.simulators.scene_description import (  # noqa: F401 - re-exported: the scene API lives here too
    SCENE_NAMES,
    CameraSpec,
    ContactSpec,
    FingerprintSpec,
    MechanicsSpec,
    MotionSpec,
    PlasticSpec,
    Scene,
    SlipFrontSpec,
    SurfaceSpec,
    TextureSpec,
    load_scene,
    parse_scene,
)
from skinstretch.simulators.scene_kernels import N_BANDS, compose_radiance, node_maps, row_bands, run_bands
from skinstretch.simulators.surfaces import RuledSurface

log = logging.getLogger(__name__)

_NODE_STEP_PX = 8
_TRUTH_GRID_PX = 8.0
_NO_COVERAGE = np.ones((1, 1), np.float32)  # compose_radiance's "no coverage map" (a synthetic print)

#: What the truth's ``feature_truth`` attribute says for a real print (see :mod:`print_texture`).
FEATURE_TRUTH_UNKNOWN = "unknown: real print texture (only displacement, trajectories and strain can be scored)"


@dataclass
class RenderedSession:
    """A rendered sequence in memory: what :func:`skinstretch.drivers.session_file.write_session` takes, plus the truth."""

    frames: np.ndarray
    timestamps: np.ndarray
    camera_mode: CameraMode
    calibration: Calibration
    truth: SessionTruth
    metadata: dict[str, Any] = field(default_factory=dict)


def _fingerprint_params(spec: FingerprintSpec) -> FingerprintParams:
    return FingerprintParams(
        ridge_period_mm=spec.ridge_period_mm,
        period_variation=spec.period_variation,
        orientation_deg=spec.orientation_deg,
        cores_mm=tuple(tuple(c) for c in spec.cores_mm),
        deltas_mm=tuple(tuple(d) for d in spec.deltas_mm),
        minutia_density_per_mm2=spec.minutia_density_per_mm2,
        minutia_spacing_mm=spec.minutia_spacing_mm,
        pore_density_per_mm2=spec.pore_density_per_mm2,
        pore_diameter_mm=tuple(spec.pore_diameter_mm),
        pore_spacing_mm=spec.pore_spacing_mm,
        pore_minutia_clearance_mm=spec.pore_minutia_clearance_mm,
        ridge_sharpness=spec.ridge_sharpness,
        ridge_contrast_variation=spec.ridge_contrast_variation,
        ridge_texture=spec.ridge_texture,
    )


def _deformation_model(scene: Scene, surface: RuledSurface) -> DeformationModel:
    p = scene.plastic
    mech = scene.mechanics
    peak = mech.peak_strain * surface.sign if surface.height_mm > 0 else 0.0
    return DeformationModel(
        motion=MotionProfile.from_keyframes(scene.motion.keyframes),
        plastic=PlasticDistortion(
            center_mm=tuple(p.center_mm),
            semi_axes_mm=tuple(p.semi_axes_mm),
            band_mm=p.band_mm,
            stick=p.stick,
            lag_mm=p.lag_mm,
            lag_speed_mm_s=p.lag_speed_mm_s,
            stick_slip_mm=p.stick_slip_mm,
            stick_slip_period_s=p.stick_slip_period_s,
            slip_fraction=p.slip_fraction,
        ),
        mechanics=RidgeMechanics(
            peak_strain=peak,
            center_s_mm=float(surface.arc_length(surface.center_mm)),
            sigma_mm=mech.sigma_mm or surface.sigma_mm,
            speed_scale_mm_s=mech.speed_scale_mm_s,
        ),
        slip_front=SlipFront(
            amplitude=scene.slip_front.amplitude,
            width_mm=scene.slip_front.width_mm,
            direction_deg=scene.slip_front.direction_deg,
            keyframes=tuple(tuple(k) for k in scene.slip_front.keyframes),
        ),
        rotation_center_mm=tuple(scene.motion.rotation_center_mm),
        ramp_s=scene.motion.ramp_s,
    )


class SceneRenderer:
    """Renders the frames and the ground truth of a scene.

    Parameters
    ----------
    scene : Scene
    seed : int
        Seeds the print, the features and the noise; the same seed gives the same frames, in any order.
    noise : float, optional
        Read noise in grey levels, overriding ``scene.camera.noise_sigma``; ``noise=0`` also turns shot noise off
        (a noiseless rendering).
    optics : Optics, optional
        How the surface is seen; default :class:`IdealOptics` at the scene's field of view.

    Attributes
    ----------
    n_frames, camera_mode, calibration, optics, fingerprint, deformation
    threads : int
        Threads that render the two row bands of a frame (default 2, or 1 on a one-core machine). The frames are the
        same whatever its value.
    """

    def __init__(self, scene: Scene, *, seed: int = 0, noise: float | None = None, optics: Optics | None = None):
        if not isinstance(scene, Scene):
            raise InvalidInputError(f"scene must be a Scene (see load_scene), got {type(scene).__name__}")
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InvalidInputError(f"seed must be a non-negative integer, got {seed!r}")
        if noise is not None and not (np.isfinite(noise) and noise >= 0):
            raise InvalidInputError(f"noise must be a non-negative number of grey levels, got {noise!r}")
        self.scene = scene
        self.seed = int(seed)
        self.camera_mode: CameraMode = _camera_mode(scene.camera.mode)
        w, h = self.camera_mode.width, self.camera_mode.height
        if optics is None:
            optics = IdealOptics(width=w, height=h, scale_px_per_mm=w / scene.camera.field_of_view_mm)
        elif (optics.width, optics.height) != (w, h):
            raise InvalidInputError(f"optics is {optics.width}x{optics.height} px but camera mode {self.camera_mode.name} is {w}x{h}")
        self.optics = optics
        self.calibration = Calibration(px_per_mm=float(optics.px_per_mm))
        self.n_frames = scene.n_frames
        self.noise_sigma = scene.camera.noise_sigma if noise is None else float(noise)
        cam = scene.camera
        self.camera = CameraModel(
            blur_sigma_px=cam.blur_sigma_px,
            vignetting=cam.vignetting,
            illumination_tilt=cam.illumination_tilt,
            noise_sigma=self.noise_sigma,
            shot_noise_gain=0.0 if noise == 0 else cam.shot_noise_gain,
        )
        self.surface = RuledSurface(
            kind=scene.surface.kind,
            width_mm=scene.surface.width_mm,
            height_mm=scene.surface.height_mm,
            center_mm=scene.surface.center_mm,
        )
        self.deformation = _deformation_model(scene, self.surface)
        self._frame_cache: dict[int, FrameDeformation] = {}
        print_seq = np.random.SeedSequence(self.seed, spawn_key=(0,))

        # 1. Constant per-pixel geometry: node grid (every 8 px) and full-resolution glass-fixed factors.
        # Node (i, j) sits at pixel (8 (j - 1), 8 (i - 1)): one node before the first pixel and two after the last,
        # as the Catmull-Rom interpolation of the maps needs (see _node_maps).
        nx = (w - 1) // _NODE_STEP_PX + 4
        ny = (h - 1) // _NODE_STEP_PX + 4
        gx, gy = np.meshgrid((np.arange(nx) - 1.0) * _NODE_STEP_PX, (np.arange(ny) - 1.0) * _NODE_STEP_PX)
        self._nodes_surface = optics.image_to_surface(np.stack([gx, gy], -1).astype(np.float64))
        self._bands = row_bands(h, N_BANDS)
        self.threads = min(N_BANDS, os.cpu_count() or 1)
        fx, fy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pix_surface = optics.image_to_surface(np.stack([fx, fy], -1))
        s_pix = pix_surface[..., 1]
        shade = 1.0 - scene.surface.slope_darkening * (
            np.abs(self.surface.slope_at_arc(s_pix)) / self.surface.max_slope if self.surface.max_slope > 0 else 0.0
        )
        self._gain = (shade * self.camera.illumination(h, w)).astype(np.float32)
        self._surface_contact_px = self._surface_contact(s_pix).astype(np.float32)

        # 2. The skin ever seen: inverse-map the image border (half a pixel outside the pixel centres, a point every
        # 4 px) in every frame. The print covers it with a margin, so its size (and a seed's print) depends on it.
        bx = np.arange(int(np.ceil((w - 0.5) / 4)) + 1) * 4.0 - 0.5
        by = np.arange(int(np.ceil((h - 0.5) / 4)) + 1) * 4.0 - 0.5
        edge = np.stack(np.meshgrid(bx, by), -1)
        border = optics.image_to_surface(np.concatenate([edge[0], edge[-1], edge[:, 0], edge[:, -1]]))
        lo, hi = border.min(0), border.max(0)
        for k in range(self.n_frames):
            X = self._deform(k).inverse(border)
            lo, hi = np.minimum(lo, X.min(0)), np.maximum(hi, X.max(0))
        margin = 0.5
        bounds = (lo[0] - margin, hi[0] + margin, lo[1] - margin, hi[1] + margin)

        # 3. The print and its master image (skin coordinates, oversampled).
        self._master_step = 1.0 / (self.calibration.px_per_mm * cam.oversample)
        self._master_u0, self._master_s0 = bounds[0], bounds[2]
        shape = (
            int(np.ceil((bounds[3] - bounds[2]) / self._master_step)) + 1,
            int(np.ceil((bounds[1] - bounds[0]) / self._master_step)) + 1,
        )
        grid = dict(u0=bounds[0], s0=bounds[2], step_mm=self._master_step, shape=shape)
        self._coverage_master: np.ndarray | None = None
        self.print_coverage: float | None = None  # a real print: fraction of the contact in view it covers
        if scene.texture is None:
            self.fingerprint: Fingerprint | RealPrintTexture = Fingerprint.generate(
                _fingerprint_params(scene.fingerprint), bounds_mm=bounds, rng=np.random.default_rng(print_seq))
        else:
            tex = scene.texture
            self.fingerprint = RealPrintTexture(
                load_print(tex.image, dpi=tex.dpi, polarity=tex.polarity),
                center_mm=scene.contact.center_mm if tex.center_mm is None else tex.center_mm,
                rotation_deg=tex.rotation_deg,
            )
            self._coverage_master = self.fingerprint.render_coverage(**grid)
        self._master = self.fingerprint.render(**grid)
        if self._coverage_master is not None:
            self._log_coverage()

        # 4. Background: bright glass with the faint latent print the finger left where it first touched.
        residue = cv2.remap(self._master, self._maps(0), None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        self._background = (cam.background_level - cam.residue_contrast * (1.0 - residue)).astype(np.float32)

    def _log_coverage(self) -> None:
        """How much of the contact in view (frame 0) the real print covers; the rest renders out of contact."""
        X = self._nodes_surface
        contact = self._ellipse_contact(X, 0.0) >= 0.5
        if not contact.any():
            return
        covered = float(np.mean(self.fingerprint.coverage_at(X[contact]) >= 0.5))
        msg = ("print %s covers %.0f %% of the contact in view; skin beyond the print renders out of contact (no "
               "ridges) and is not in the truth")
        (log.warning if covered < 0.9 else log.info)(msg, self.fingerprint.image.name, 100 * covered)
        self.print_coverage = covered

    # ---------------------------------------------------------------- helpers
    def time_of(self, k: int) -> float:
        """Time (s) of frame k from the start of the sequence."""
        return k * self.camera_mode.period_s

    def _deform(self, k: int) -> FrameDeformation:
        d = self._frame_cache.get(k)
        if d is None:
            d = self.deformation.at(self.time_of(k))
            if len(self._frame_cache) < 4096:
                self._frame_cache[k] = d
        return d

    def force_at(self, t_s: float) -> float:
        """Normal force (N) at time t_s."""
        kf = self.scene.contact.force_keyframes
        if not kf:
            return self.scene.contact.normal_force_N
        t, f = np.asarray(kf, dtype=np.float64).T
        return float(np.interp(t_s, t, f))

    def _surface_contact(self, s: np.ndarray) -> np.ndarray:
        """Glass-fixed contact factor in [0, 1]: 1 - contact_loss where the skin cannot follow the shape."""
        loss = self.scene.surface.contact_loss
        if loss == 0 or self.surface.kind == "flat" or self.surface.height_mm == 0:
            return np.ones_like(s)
        z = self.surface.flat_coordinate(s) - self.surface.center_mm
        sig = self.surface.sigma_mm
        if self.surface.kind == "ridge":
            # Just past the crest (in the mean sliding direction) the skin lifts off the falling slope.
            ks = np.asarray(self.scene.motion.keyframes, dtype=np.float64)
            direction = 1.0 if ks[-1, 2] >= ks[0, 2] else -1.0
            prof = np.exp(-0.5 * ((z - direction * 0.8 * sig) / (0.45 * sig)) ** 2)
        else:
            prof = np.exp(-0.5 * (z / (0.5 * sig)) ** 2)  # the skin does not reach the bottom of the valley
        return 1.0 - loss * prof

    def _ellipse_contact(self, X: np.ndarray, t_s: float) -> np.ndarray:
        # Same formula as compose_radiance (compiled); both must agree.
        c = self.scene.contact
        a, b = self._contact_axes(t_s)
        du, ds = X[..., 0] - c.center_mm[0], X[..., 1] - c.center_mm[1]
        inside_mm = (1.0 - np.sqrt((du / a) ** 2 + (ds / b) ** 2)) * 0.5 * (a + b)
        q = np.clip(inside_mm / c.edge_mm + 0.5, 0.0, 1.0)
        return q * q * (3.0 - 2.0 * q)

    def _contact_at(self, X: np.ndarray, x_surface: np.ndarray, t_s: float) -> np.ndarray:
        c = self._ellipse_contact(X, t_s) * self._surface_contact(x_surface[..., 1])
        if self._coverage_master is not None:
            c = c * self.fingerprint.coverage_at(X)
        return c

    def _row_maps(self, d: FrameDeformation, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
        """Master-image column and row maps (float32, contiguous) of image rows ``r0:r1``: the exact inverse at the
        nodes those rows need, Catmull-Rom in between."""
        n0 = r0 // _NODE_STEP_PX  # row r uses node rows r // step .. r // step + 3 (Catmull-Rom)
        n1 = (r1 - 1) // _NODE_STEP_PX + 4
        X = d.inverse(self._nodes_surface[n0:n1])
        return node_maps(X, self._master_u0, self._master_s0, 1.0 / self._master_step, r0, r1,
                          self.camera_mode.width, n0, _NODE_STEP_PX)

    def _maps(self, k: int) -> np.ndarray:
        """(H, W, 2) float32: master-image column and row of the skin seen at each pixel (Catmull-Rom from nodes)."""
        d = self._deform(k)
        out = np.empty((self.camera_mode.height, self.camera_mode.width, 2), dtype=np.float32)
        for r0, r1 in self._bands:
            mx, my = self._row_maps(d, r0, r1)
            out[r0:r1, :, 0] = mx
            out[r0:r1, :, 1] = my
        return out

    def _radiance_rows(self, k: int):
        """A function (r0, r1, out) writing the radiance of rows r0:r1 of frame k into ``out`` (float32)."""
        cam = self.scene.camera
        c = self.scene.contact
        d = self._deform(k)
        a, b = self._contact_axes(self.time_of(k))
        consts = (
            np.float32(cam.ridge_level), np.float32(cam.valley_level),
            float(self._master_u0 - c.center_mm[0]), float(self._master_s0 - c.center_mm[1]),
            float(self._master_step), float(a), float(b), float(c.edge_mm),
        )

        def rows(r0: int, r1: int, out: np.ndarray) -> None:
            mx, my = self._row_maps(d, r0, r1)
            # Separate x / y maps: cv2's cubic remap is twice as fast with them as with one 2-channel map.
            v = cv2.remap(self._master, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
            cov = _NO_COVERAGE
            if self._coverage_master is not None:
                cov = cv2.remap(self._coverage_master, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                borderValue=0)
            compose_radiance(v, cov, mx, my, self._surface_contact_px[r0:r1], self._gain[r0:r1], self._background[r0:r1],
                     *consts, out)

        return rows

    def _contact_axes(self, t_s: float) -> tuple[float, float]:
        c = self.scene.contact
        scale = self.force_at(t_s) ** (1.0 / 3.0)
        return c.semi_axes_mm_at_1N[0] * scale, c.semi_axes_mm_at_1N[1] * scale

    # ---------------------------------------------------------------- frames
    def radiance(self, k: int, *, threads: int | None = None) -> np.ndarray:
        """Noise-free, unblurred scene radiance of frame k in grey levels (float32, H x W).

        The row bands of the image are rendered by up to ``threads`` threads (default :attr:`threads`); the result
        does not depend on it.
        """
        self._check_frame(k)
        rows = self._radiance_rows(k)
        out = np.empty((self.camera_mode.height, self.camera_mode.width), dtype=np.float32)
        run_bands(lambda band: rows(*band, out[band[0] : band[1]]), self._bands,
                   self.threads if threads is None else threads)
        return out

    def render_frame(self, k: int, *, threads: int | None = None) -> np.ndarray:
        """Frame k as the camera delivers it: uint8 (H, W), ``camera.apply(radiance(k), rng_k)``. Deterministic for
        (scene, seed, noise, k), whatever the order of the calls and the number of ``threads`` (default
        :attr:`threads`)."""
        self._check_frame(k)
        h, w = self.camera_mode.height, self.camera_mode.width
        # Noise stream of frame k: its own child of the seed, so any frame renders alone, in any order.
        rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(1, int(k))))
        idx = self.camera.noise_indices(rng, (h, w))
        rows = self._radiance_rows(k)
        halo = self.camera.blur_halo_px
        out = np.empty((h, w), dtype=np.uint8)

        def band(bd: tuple[int, int]) -> None:
            # Each band renders the rows its blur needs beyond it (a few, computed twice) and finishes its rows.
            r0, r1 = bd
            e0, e1 = max(r0 - halo, 0), min(r1 + halo, h)
            rad = np.empty((e1 - e0, w), dtype=np.float32)
            rows(e0, e1, rad)
            out[r0:r1] = self.camera.apply_rows(rad, r0 - e0, r1 - e0, None if idx is None else idx[r0:r1])

        run_bands(band, self._bands, self.threads if threads is None else threads)
        return out

    def _check_frame(self, k: int) -> None:
        if not isinstance(k, (int, np.integer)) or not 0 <= k < self.n_frames:
            raise InvalidInputError(f"frame index k must be an integer in [0, {self.n_frames}), got {k!r}")

    # ---------------------------------------------------------------- truth
    def feature_positions(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Image positions (F, 2) px of every true feature in frame k, and their visibility (F,)."""
        self._check_frame(k)
        _, _, P = self.fingerprint.features()
        x_surf = self._deform(k).forward(P)
        xy = self.optics.surface_to_image(x_surf)
        w, h = self.camera_mode.width, self.camera_mode.height
        in_view = (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
        return xy, in_view & (self._contact_at(P, x_surf, self.time_of(k)) >= 0.5)

    def truth(self, n_frames: int | None = None) -> SessionTruth:
        """Ground truth of the first ``n_frames`` frames (default all)."""
        n = self.n_frames if n_frames is None else int(n_frames)
        if not 1 <= n <= self.n_frames:
            raise InvalidInputError(f"n_frames must be in [1, {self.n_frames}], got {n_frames!r}")
        ids, kinds, P = self.fingerprint.features()
        w, h = self.camera_mode.width, self.camera_mode.height
        grid_x = np.arange(0.0, w, _TRUTH_GRID_PX)
        grid_y = np.arange(0.0, h, _TRUTH_GRID_PX)
        G = np.stack(np.meshgrid(grid_x, grid_y), -1)
        X = self.optics.image_to_surface(G)
        img0 = self.optics.surface_to_image(X)
        fx = np.zeros((n, len(ids)))
        fy = np.zeros((n, len(ids)))
        fv = np.zeros((n, len(ids)), dtype=bool)
        disp = np.zeros((n, len(grid_y), len(grid_x), 2), dtype=np.float32)
        valid = np.zeros((n, len(grid_y), len(grid_x)), dtype=bool)
        strain = np.zeros((n, len(grid_y), len(grid_x), 3), dtype=np.float32)
        rigid = np.zeros((n, 3))
        center = np.asarray(self.scene.motion.rotation_center_mm, dtype=np.float64)
        c_img = self.optics.surface_to_image(center)
        # The grid points and the features go through the deformation together (one call per frame, not two; the
        # same values as feature_positions, point by point).
        ng = X.shape[0] * X.shape[1]
        XP = np.concatenate([X.reshape(-1, 2), P])
        for k in range(n):
            D = self._deform(k)
            d, hgrad = D.displacement(XP, with_gradient=True)
            x_surf = XP + d
            xk = self.optics.surface_to_image(x_surf)
            inview = (xk[:, 0] >= 0) & (xk[:, 0] <= w - 1) & (xk[:, 1] >= 0) & (xk[:, 1] <= h - 1)
            seen = inview & (self._contact_at(XP, x_surf, self.time_of(k)) >= 0.5)
            fx[k], fy[k], fv[k] = xk[ng:, 0], xk[ng:, 1], seen[ng:]
            disp[k] = xk[:ng].reshape(X.shape) - img0
            valid[k] = seen[:ng].reshape(X.shape[:2])
            strain[k] = green_lagrange(hgrad[:ng].reshape(X.shape[:2] + (2, 2)))
            tx, ty = self.optics.surface_to_image(center + D.t_b) - c_img
            rigid[k] = (tx, ty, D.theta_b)
        return SessionTruth(
            feature_id=ids,
            feature_kind=kinds,
            feature_x=fx,
            feature_y=fy,
            feature_visible=fv,
            grid_x=grid_x,
            grid_y=grid_y,
            displacement=disp,
            displacement_valid=valid,
            rigid=rigid,
            rigid_center=np.asarray(c_img, dtype=np.float64),
            strain=strain,
            attrs=self._attrs(),
        )

    def _attrs(self) -> dict[str, Any]:
        return {
            "scene": self.scene.name,
            "scene_yaml": self.scene.to_yaml(),
            "seed": self.seed,
            "noise_sigma": float(self.noise_sigma),
            "px_per_mm": self.calibration.px_per_mm,
            "optics": type(self.optics).__name__,
            "surface": self.surface.kind,
            "strain_axes": "surface (u, s) = image (x, y) axes; physical skin strain, optics-independent",
            **self._texture_attrs(),
        }

    def _texture_attrs(self) -> dict[str, Any]:
        if self.scene.texture is None:
            return {"texture": "synthetic", "feature_truth": "exact"}
        img = self.fingerprint.image
        return {
            "texture": img.name,
            "texture_sha256": img.sha256,
            "texture_dpi": float(img.px_per_mm * 25.4),
            "texture_polarity": img.polarity,
            "texture_ridge_period_mm": float(img.ridge_period_mm),
            "texture_contact_coverage": float("nan") if self.print_coverage is None else self.print_coverage,
            "feature_truth": FEATURE_TRUTH_UNKNOWN,
        }


def _validate_n(scene: Scene | str | os.PathLike, n_frames: int | None) -> Scene:
    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)
    if n_frames is None:
        return scene
    if not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise InvalidInputError(f"n_frames must be a positive integer, got {n_frames!r}")
    return scene.model_copy(update={"n_frames": int(n_frames)})


def render_session(
    scene: Scene | str | os.PathLike,
    *,
    n_frames: int | None = None,
    seed: int = 0,
    noise: float | None = None,
    optics: Optics | None = None,
    progress: bool = False,
    workers: int = 1,
) -> RenderedSession:
    """Render a whole scene (a :class:`Scene`, a built-in name or a YAML path) in memory, with its truth.

    ``workers`` threads render frames concurrently, each frame in one thread; with ``workers=1`` each frame's two
    row bands are rendered in two threads instead (the result does not depend on it).
    """
    scene = _validate_n(scene, n_frames)
    if not isinstance(workers, (int, np.integer)) or workers < 1:
        raise InvalidInputError(f"workers must be a positive integer, got {workers!r}")
    r = SceneRenderer(scene, seed=seed, noise=noise, optics=optics)
    n = r.n_frames
    frames = np.empty((n, r.camera_mode.height, r.camera_mode.width), dtype=np.uint8)
    bar = progress_bar(n, enabled=progress, desc=f"simulate {scene.name}")

    inner = None if workers == 1 else 1  # frame-level threads replace the row-band threads of one frame

    def one(k: int) -> None:
        frames[k] = r.render_frame(k, threads=inner)  # frames are independent and seeded by index: any order
        bar.update(1)

    if workers == 1:
        for k in range(n):
            one(k)
    else:
        # The compiled kernels, cv2 and numpy's generators release the GIL, so threads overlap.
        with ThreadPoolExecutor(max_workers=int(workers)) as pool:
            list(pool.map(one, range(n)))
    bar.close()
    timestamps = np.arange(n) * r.camera_mode.period_s
    metadata = {
        "simulated": True,
        "scene": scene.name,
        "seed": int(seed),
        "noise_sigma": float(r.noise_sigma),
        "surface": scene.surface.kind,
        "description": scene.description,
        "texture": "synthetic" if scene.texture is None else scene.texture.image,
    }
    return RenderedSession(frames, timestamps, r.camera_mode, r.calibration, r.truth(), metadata)


def simulate_to_file(
    scene: Scene | str | os.PathLike,
    path: str | os.PathLike,
    *,
    n_frames: int | None = None,
    seed: int = 0,
    noise: float | None = None,
    optics: Optics | None = None,
    progress: bool = False,
    overwrite: bool = False,
    workers: int = 1,
) -> Path:
    """Render a scene and write it as a session file (with its truth); returns the path."""
    s = render_session(scene, n_frames=n_frames, seed=seed, noise=noise, optics=optics, progress=progress,
                       workers=workers)
    return write_session(
        path,
        s.frames,
        timestamps=s.timestamps,
        camera_mode=s.camera_mode,
        calibration=s.calibration,
        metadata=s.metadata,
        truth=s.truth,
        overwrite=overwrite,
    )

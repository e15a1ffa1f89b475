"""A synthetic FTIR fingerprint with exact ground truth: phase-field ridges, spiral minutiae and pores.

The print lives in *skin coordinates* (mm, the frame-0 surface position of each skin point, see
:mod:`skinstretch.simulators.deformation`).

Ridges (Larkin & Fletcher 2007)
-------------------------------
``phi = phi_c + sum_n p_n atan2(s - s_n, u - u_n)`` with ``p_n = +/-1``. ``phi_c`` is the continuous phase
whose gradient follows ``2 pi / lambda(X)`` times the normal of a Sherlock-Monro orientation field
``theta = theta_inf + 1/2 [sum arg(z - c_i) - sum arg(z - d_j)]`` (cores ``c_i``, deltas ``d_j``), obtained by a
least-squares (DCT Poisson) integration on a 0.04 mm grid. The period ``lambda`` varies smoothly by
``period_variation`` around ``ridge_period_mm``. Cores and deltas must lie *outside* the rendered skin region: the
phase of a loop core is not a smooth function, so a core inside the field would render as a blurred patch.

FTIR polarity (seed 3.2): ridges touch the glass and are DARK; valleys and pores are BRIGHT. Here ridge centres
are ``phi = 0 (mod 2 pi)`` and valley centres ``phi = pi``.

Minutiae
--------
Each spiral point is exactly one minutia: one line ends at P and the line of opposite phase forks there. With
``g`` the gradient of the phase of all *other* terms, the spiral adds a line on the side ``e_p = p (g_s, -g_u)/|g|``,
so the ending line leaves P along ``e_p`` with phase ``phi_rest(P) + p angle(e_p)``. Each point is moved along
``g`` until that phase is ``pi`` (a valley ends at P: :attr:`FeatureKind.VALLEY_ENDING`) or ``0`` (a ridge ends
at P and the valley forks: :attr:`FeatureKind.VALLEY_BIFURCATION`), which makes the kind exact and the
configuration clean. The true *position* is then read off the valley skeleton of a fine local rendering (see
:meth:`Fingerprint._skeleton_positions`); kinds and positions are verified at camera resolution in
tests/test_sim_fingerprint.py.

Pores
-----
Bright discs of diameter ``pore_diameter_mm`` placed on ridge centre lines (Newton projection onto
``phi = 0 mod 2 pi``), at least ``pore_minutia_clearance_mm`` from every minutia and ``pore_spacing_mm`` from
each other, so the truth is unambiguous.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np
from pydantic import Field, model_validator
from scipy import sparse
from scipy.fft import dctn, idctn
from scipy.ndimage import convolve, gaussian_filter, label

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import (
    FiniteFloat,
    NonNegativeFloat,
    PositiveFloat,
    Probability,
    validated_dataclass,
)
from skinstretch.processing.feature_table import FeatureKind

_GRID_MM = 0.04
_GRID_MARGIN_MM = 1.0


@validated_dataclass
class FingerprintParams:
    """Statistics of a synthetic print (defaults from FACTS: 0.43 mm period, ~0.2 minutiae and ~3 pores / mm^2)."""

    ridge_period_mm: FiniteFloat = Field(default=0.43, ge=0.2, le=1.0)
    period_variation: FiniteFloat = Field(default=0.06, ge=0, lt=0.5)
    orientation_deg: FiniteFloat = 0.0
    cores_mm: tuple[tuple[FiniteFloat, FiniteFloat], ...] = ((0.0, -9.0),)
    deltas_mm: tuple[tuple[FiniteFloat, FiniteFloat], ...] = ()
    minutia_density_per_mm2: NonNegativeFloat = 0.2
    minutia_spacing_mm: PositiveFloat = 0.6
    pore_density_per_mm2: NonNegativeFloat = 3.0
    pore_diameter_mm: tuple[PositiveFloat, PositiveFloat] = (0.06, 0.16)
    pore_spacing_mm: PositiveFloat = 0.25
    pore_minutia_clearance_mm: NonNegativeFloat = 0.3
    ridge_sharpness: PositiveFloat = 1.5
    ridge_contrast_variation: Probability = 0.15
    ridge_texture: FiniteFloat = 0.12

    @model_validator(mode="after")
    def _consistent(self) -> "FingerprintParams":
        lo, hi = self.pore_diameter_mm
        if not lo <= hi <= 0.3:
            raise InvalidInputError(f"pore_diameter_mm must satisfy 0 < min <= max <= 0.3, got {self.pore_diameter_mm}")
        if not 0 <= self.ridge_texture + self.ridge_contrast_variation < 1:
            raise InvalidInputError("ridge_texture + ridge_contrast_variation must be in [0, 1)")
        return self


def _wrap(a: np.ndarray | float) -> np.ndarray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _catmull_rom_matrix(grid0: float, step: float, n: int, coords: np.ndarray):
    """Sparse (len(coords), n) matrix of Catmull-Rom weights interpolating a regular grid at ``coords``."""
    t = (np.asarray(coords, dtype=np.float64) - grid0) / step
    i = np.floor(t).astype(np.int64)
    f = t - i
    w = np.stack(
        [
            ((-0.5 * f + 1.0) * f - 0.5) * f,
            (1.5 * f - 2.5) * f * f + 1.0,
            ((-1.5 * f + 2.0) * f + 0.5) * f,
            (0.5 * f - 0.5) * f * f,
        ],
        axis=-1,
    )
    rows = np.repeat(np.arange(t.size), 4)
    cols = np.clip(i[:, None] - 1 + np.arange(4)[None, :], 0, n - 1).ravel()
    return sparse.csr_matrix((w.ravel(), (rows, cols)), shape=(t.size, n))


@numba.njit(parallel=True, cache=True, fastmath=False)
def _spiral_cosine(phic, u, s, grid_of_row, mu, ms, mp):  # pragma: no cover - compiled
    """cos(phi_c + sum p atan2(...)) on the rows of one or more regular grids, via a product of unit phasors (no
    atan2 per pixel). Row r of ``phic`` (R, nx) lies at skin ``s[r]`` and has the columns ``u[grid_of_row[r]]``
    (``u`` is (G, nx)). Each row's phasors are updated spiral by spiral over the whole row (SIMD-friendly)."""
    nrows, nx = phic.shape
    out = np.empty((nrows, nx), dtype=np.float32)
    nm = mu.shape[0]
    for i in numba.prange(nrows):
        ur = u[grid_of_row[i]]
        ar = np.ones(nx)
        ai = np.zeros(nx)
        for n in range(nm):
            zi = s[i] - ms[n]
            if mp[n] < 0:
                zi = -zi
            m = mu[n]
            for j in range(nx):
                zr = ur[j] - m
                tr = ar[j] * zr - ai[j] * zi
                ai[j] = ar[j] * zi + ai[j] * zr
                ar[j] = tr
            if n % 16 == 15:
                for j in range(nx):
                    mag = np.sqrt(ar[j] * ar[j] + ai[j] * ai[j])
                    if mag > 0.0:
                        ar[j] /= mag
                        ai[j] /= mag
        for j in range(nx):
            mag = np.sqrt(ar[j] * ar[j] + ai[j] * ai[j])
            c = np.cos(phic[i, j])
            sn = np.sin(phic[i, j])
            if mag > 0.0:
                out[i, j] = (c * ar[j] - sn * ai[j]) / mag
            else:
                out[i, j] = 0.0
    return out


@dataclass
class Fingerprint:
    """A generated print over a skin region: phase grid, minutiae and pores, all in skin mm.

    Use :meth:`generate`. ``minutia_xy`` (M, 2), ``minutia_polarity`` (M,), ``minutia_kind`` (M,) and
    ``pore_xy`` (P, 2), ``pore_radius_mm`` (P,) are the ground truth; :meth:`features` gives them with ids.
    """

    params: FingerprintParams
    bounds_mm: tuple[float, float, float, float]
    grid_u0: float
    grid_s0: float
    phase_grid: np.ndarray
    contrast_grid: np.ndarray
    minutia_xy: np.ndarray
    spiral_xy: np.ndarray
    minutia_skeleton_found: np.ndarray
    minutia_polarity: np.ndarray
    minutia_kind: np.ndarray
    pore_xy: np.ndarray
    pore_radius_mm: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------------ generation
    @classmethod
    def generate(
        cls, params: FingerprintParams, *, bounds_mm: tuple[float, float, float, float], rng: np.random.Generator
    ) -> "Fingerprint":
        """Generate a print covering ``bounds_mm = (u_min, u_max, s_min, s_max)`` of skin."""
        u_min, u_max, s_min, s_max = (float(b) for b in bounds_mm)
        if not (u_max > u_min and s_max > s_min):
            raise InvalidInputError(f"bounds_mm must be (u_min, u_max, s_min, s_max) with max > min, got {bounds_mm}")
        gu0, gs0 = u_min - _GRID_MARGIN_MM, s_min - _GRID_MARGIN_MM
        nu = int(np.ceil((u_max - u_min + 2 * _GRID_MARGIN_MM) / _GRID_MM)) + 1
        ns = int(np.ceil((s_max - s_min + 2 * _GRID_MARGIN_MM) / _GRID_MM)) + 1
        uu = gu0 + _GRID_MM * np.arange(nu)
        ss = gs0 + _GRID_MM * np.arange(ns)
        U, S = np.meshgrid(uu, ss)
        phase = _integrate_phase(params, U, S, rng, centre=((u_min + u_max) / 2, (s_min + s_max) / 2))
        # Ridge darkness varies: slowly (pressure, moisture) and finely (the mottled contact of real FTIR ridges).
        contrast = _smooth_noise(rng, U.shape, sigma_px=0.25 / _GRID_MM)
        texture = _smooth_noise(rng, U.shape, sigma_px=0.05 / _GRID_MM)
        contrast = 1.0 - params.ridge_contrast_variation * (0.5 + 0.5 * contrast) - params.ridge_texture * (0.5 + 0.5 * texture)
        fp = cls(
            params=params,
            bounds_mm=(u_min, u_max, s_min, s_max),
            grid_u0=gu0,
            grid_s0=gs0,
            phase_grid=phase,
            contrast_grid=contrast.astype(np.float32),
            minutia_xy=np.zeros((0, 2)),
            spiral_xy=np.zeros((0, 2)),
            minutia_skeleton_found=np.zeros(0, dtype=bool),
            minutia_polarity=np.zeros(0, dtype=np.int8),
            minutia_kind=np.zeros(0, dtype=np.int8),
            pore_xy=np.zeros((0, 2)),
            pore_radius_mm=np.zeros(0),
        )
        fp._place_minutiae(rng)
        fp._place_pores(rng)
        return fp

    def _place_minutiae(self, rng: np.random.Generator) -> None:
        p = self.params
        u_min, u_max, s_min, s_max = self.bounds_mm
        area = (u_max - u_min) * (s_max - s_min)
        target = int(rng.poisson(p.minutia_density_per_mm2 * area)) if p.minutia_density_per_mm2 > 0 else 0
        pts = _dart_throw(rng, target, self.bounds_mm, p.minutia_spacing_mm, margin=0.2)
        m = len(pts)
        pol = rng.choice(np.array([-1, 1], dtype=np.int8), size=m)
        kind = rng.integers(0, 2, size=m).astype(np.int8)  # 0 valley ending, 1 valley bifurcation
        pts = np.asarray(pts, dtype=np.float64).reshape(m, 2)
        pts = self._adjust_minutiae(pts, pol, kind)
        keep = np.ones(m, dtype=bool)
        for n in range(m):
            if not keep[n]:
                continue
            d = np.hypot(*(pts - pts[n]).T)
            d[n] = np.inf
            keep[(d < 0.8 * p.minutia_spacing_mm) & keep] = False  # drop the later one of a pair that drifted together
        if m:
            keep &= (pts[:, 0] >= u_min) & (pts[:, 0] <= u_max) & (pts[:, 1] >= s_min) & (pts[:, 1] <= s_max)
        if (~keep).any():
            # Removing spirals changes the phase at the others: adjust the survivors again.
            pts, pol, kind = pts[keep], pol[keep], kind[keep]
            pts = self._adjust_minutiae(pts, pol, kind)
        self.spiral_xy, self.minutia_polarity, self.minutia_kind = pts, pol, kind
        self.minutia_xy, self.minutia_skeleton_found = self._skeleton_positions()

    def _skeleton_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Where the valley skeleton has its ending / junction next to each spiral point (skin mm).

        The seed locates minutiae on the skeleton of the binarised print (seed 4.6). A valley ending's skeleton
        stops short of the spiral point, and a valley fork's junction lies behind the ridge tip (about 0.15 mm for
        the default period). Each minutia's true position is therefore taken from the skeleton of a local rendering
        at 4 um per pixel (the same brightness profile as :meth:`render`, without pores), binarised at the ridge/valley
        mid-level and thinned
        (skimage ``skeletonize``). ``minutia_skeleton_found`` is False where the expected skeleton point was not
        found within 0.3 mm; the spiral point is used then.
        """
        from skimage.morphology import skeletonize

        m = len(self.spiral_xy)
        out = self.spiral_xy.copy()
        found = np.zeros(m, dtype=bool)
        step, half = 0.004, 0.4
        offs = np.arange(-half, half + step / 2, step)
        n = offs.size
        kernel = np.ones((3, 3))
        # phi_c of every local grid, then the spiral phasors of all of them in one parallel call.
        grids = [self._phase_c_grid(u0=pu + offs[0], s0=ps + offs[0], step_mm=step, shape=(n, n), with_contrast=True)
                 for pu, ps in self.spiral_xy]
        cos_all = self._spiral_cosine(np.concatenate([g[0] for g in grids]), [g[2] for g in grids],
                                      [g[3] for g in grids]) if m else None
        for i in range(m):
            pu, ps = self.spiral_xy[i]
            cosphi, contrast = cos_all[i * n : (i + 1) * n], grids[i][1]
            valley = self._brightness(cosphi, contrast) > 0.5
            sk = skeletonize(valley)
            nb = convolve(sk.astype(np.int32), kernel.astype(np.int32), mode="constant") - 1
            want = (nb == 1) if self.minutia_kind[i] == FeatureKind.VALLEY_ENDING else (nb >= 3)
            lab, nlab = label(sk & want, structure=np.ones((3, 3)))
            if nlab == 0:
                continue
            centres = np.array([np.argwhere(lab == j + 1).mean(axis=0) for j in range(nlab)])  # (row, col)
            d = np.hypot(offs[0] + centres[:, 1] * step - 0.0, offs[0] + centres[:, 0] * step - 0.0)
            j = int(np.argmin(d))
            if d[j] <= 0.3:
                out[i] = (pu + offs[0] + centres[j, 1] * step, ps + offs[0] + centres[j, 0] * step)
                found[i] = True
        return out, found

    def _adjust_minutiae(self, pts: np.ndarray, pol: np.ndarray, kind: np.ndarray) -> np.ndarray:
        """Move each spiral point along the phase gradient until the line ending at it is a valley (phase pi) or a
        ridge (phase 0, the valley forks). Jacobi iteration; moves are below lambda / 2."""
        pts = pts.copy()
        m = len(pts)
        if m == 0:
            return pts
        target = np.where(kind == FeatureKind.VALLEY_ENDING, np.pi, 0.0)
        h = 1e-4
        for _ in range(60):
            phi = self._phase_c(pts)
            gu = (self._phase_c(pts + [h, 0]) - self._phase_c(pts - [h, 0])) / (2 * h)
            gs = (self._phase_c(pts + [0, h]) - self._phase_c(pts - [0, h])) / (2 * h)
            du = pts[:, None, 0] - pts[None, :, 0]
            ds = pts[:, None, 1] - pts[None, :, 1]
            r2 = du * du + ds * ds
            np.fill_diagonal(r2, 1.0)
            off = ~np.eye(m, dtype=bool)
            phi = phi + np.sum(np.where(off, pol[None, :] * np.arctan2(ds, du), 0.0), axis=1)
            gu = gu - np.sum(np.where(off, pol[None, :] * ds / r2, 0.0), axis=1)
            gs = gs + np.sum(np.where(off, pol[None, :] * du / r2, 0.0), axis=1)
            # The line that ends at P leaves it along e_p = p (g_s, -g_u) / |g| (the side where the spiral adds
            # a line), and its phase is phi_rest(P) + p * angle(e_p).
            ending_phase = phi + pol * np.arctan2(-pol * gu, pol * gs)
            delta = _wrap(target - ending_phase)
            pts += (delta / (gu * gu + gs * gs))[:, None] * np.column_stack([gu, gs])
            if np.max(np.abs(delta)) < 1e-10:
                break
        return pts

    def _place_pores(self, rng: np.random.Generator) -> None:
        p = self.params
        u_min, u_max, s_min, s_max = self.bounds_mm
        area = (u_max - u_min) * (s_max - s_min)
        n_try = int(rng.poisson(p.pore_density_per_mm2 * area * 1.6)) if p.pore_density_per_mm2 > 0 else 0
        cand = np.column_stack([rng.uniform(u_min, u_max, n_try), rng.uniform(s_min, s_max, n_try)])
        for _ in range(4):  # Newton onto the nearest ridge centre line (phi = 0 mod 2 pi)
            phi, grad = self.phase_and_gradient(cand)
            cand = cand + (_wrap(-phi) / np.sum(grad * grad, axis=1))[:, None] * grad
        phi, grad = self.phase_and_gradient(cand)
        ok = np.abs(_wrap(phi)) < 1e-3
        ok &= (cand[:, 0] >= u_min) & (cand[:, 0] <= u_max) & (cand[:, 1] >= s_min) & (cand[:, 1] <= s_max)
        for ref in (self.minutia_xy, self.spiral_xy):
            if len(ref):
                dm = np.min(np.hypot(cand[:, None, 0] - ref[None, :, 0], cand[:, None, 1] - ref[None, :, 1]), axis=1)
                ok &= dm >= p.pore_minutia_clearance_mm
        # The local period must be near nominal, i.e. not near a phase singularity.
        ok &= np.abs(2 * np.pi / np.hypot(*grad.T) / p.ridge_period_mm - 1.0) < 0.35
        target = int(round(p.pore_density_per_mm2 * area))
        chosen: list[int] = []
        for idx in np.flatnonzero(ok):
            if len(chosen) >= target:
                break
            if chosen:
                c = cand[chosen]
                if np.min(np.hypot(c[:, 0] - cand[idx, 0], c[:, 1] - cand[idx, 1])) < p.pore_spacing_mm:
                    continue
            chosen.append(int(idx))
        lo, hi = p.pore_diameter_mm
        self.pore_xy = cand[chosen].reshape(-1, 2)
        self.pore_radius_mm = rng.uniform(lo / 2, hi / 2, len(chosen))

    # ------------------------------------------------------------------ phase evaluation
    def _phase_c(self, pts: np.ndarray) -> np.ndarray:
        """phi_c at points (Catmull-Rom, the same interpolant :meth:`render` uses)."""
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        ns, nu = self.phase_grid.shape
        tu = (pts[:, 0] - self.grid_u0) / _GRID_MM
        ts = (pts[:, 1] - self.grid_s0) / _GRID_MM
        iu, is_ = np.floor(tu).astype(int), np.floor(ts).astype(int)
        fu, fs = tu - iu, ts - is_

        def w(f):
            return np.stack(
                [((-0.5 * f + 1.0) * f - 0.5) * f, (1.5 * f - 2.5) * f * f + 1.0, ((-1.5 * f + 2.0) * f + 0.5) * f, (0.5 * f - 0.5) * f * f],
                axis=-1,
            )

        wu, ws = w(fu), w(fs)
        out = np.zeros(len(pts))
        for a in range(4):
            ra = np.clip(is_ - 1 + a, 0, ns - 1)
            for b in range(4):
                cb = np.clip(iu - 1 + b, 0, nu - 1)
                out += ws[:, a] * wu[:, b] * self.phase_grid[ra, cb]
        return out

    def _phase_and_gradient(self, pts, spirals, polarity, *, skip: int = -1, with_gradient: bool = True):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        h = 1e-4
        phi = self._phase_c(pts)
        if with_gradient:
            gu = (self._phase_c(pts + [h, 0]) - self._phase_c(pts - [h, 0])) / (2 * h)
            gs = (self._phase_c(pts + [0, h]) - self._phase_c(pts - [0, h])) / (2 * h)
        for n in range(len(spirals)):
            if n == skip:
                continue
            du = pts[:, 0] - spirals[n, 0]
            ds = pts[:, 1] - spirals[n, 1]
            phi = phi + polarity[n] * np.arctan2(ds, du)
            if with_gradient:
                r2 = du * du + ds * ds
                gu = gu - polarity[n] * ds / r2
                gs = gs + polarity[n] * du / r2
        return phi, (np.column_stack([gu, gs]) if with_gradient else None)

    def phase_and_gradient(self, pts: np.ndarray, *, with_gradient: bool = True):
        """Full phase ``phi`` (unwrapped only locally) and its gradient (rad/mm) at skin points (K, 2)."""
        return self._phase_and_gradient(pts, self.spiral_xy, self.minutia_polarity, with_gradient=with_gradient)

    # ------------------------------------------------------------------ rendering
    def render(self, *, u0: float, s0: float, step_mm: float, shape: tuple[int, int]) -> np.ndarray:
        """Bright-valley image of the print on a regular skin grid, float32 in [0, 1] (0 = ridge centre).

        Pixel ``(i, j)`` is the skin point ``(u0 + j * step_mm, s0 + i * step_mm)``.
        """
        ny, nx = shape
        su = u0 + step_mm * np.arange(nx)
        sv = s0 + step_mm * np.arange(ny)
        cosphi, contrast = self._cos_phase_grid(u0=u0, s0=s0, step_mm=step_mm, shape=shape, with_contrast=True)
        img = self._brightness(cosphi, contrast)
        # Pores: bright discs with a soft (one 15 um) edge, drawn over the ridge.
        edge = 0.015
        for (pu, ps), r in zip(self.pore_xy, self.pore_radius_mm):
            j0 = int(np.floor((pu - r - 3 * edge - u0) / step_mm))
            i0 = int(np.floor((ps - r - 3 * edge - s0) / step_mm))
            n = int(np.ceil(2 * (r + 3 * edge) / step_mm)) + 2
            i1, j1 = min(max(i0, 0) + n, ny), min(max(j0, 0) + n, nx)
            i0, j0 = max(i0, 0), max(j0, 0)
            if i1 <= i0 or j1 <= j0:
                continue
            uu = su[j0:j1][None, :] - pu
            vv = sv[i0:i1][:, None] - ps
            d = np.sqrt(uu * uu + vv * vv)
            disc = (0.5 - 0.5 * np.tanh((d - r) / edge)).astype(np.float32)
            np.maximum(img[i0:i1, j0:j1], disc * 0.95, out=img[i0:i1, j0:j1])
        return np.clip(img, 0.0, 1.0).astype(np.float32)

    def _brightness(self, cosphi: np.ndarray, contrast: np.ndarray) -> np.ndarray:
        """Bright-valley profile: 0 at a full-contrast ridge centre, 1 at a valley centre."""
        g = self.params.ridge_sharpness
        ridge = 0.5 + 0.5 * np.tanh(g * cosphi) / np.tanh(g)  # 1 at ridge centres, 0 at valley centres
        return 1.0 - ridge * contrast

    def _cos_phase_grid(self, *, u0, s0, step_mm, shape, with_contrast=False):
        """cos(phi) (float32) on a regular skin grid, and optionally the ridge contrast there."""
        phic, contrast, u, s = self._phase_c_grid(u0=u0, s0=s0, step_mm=step_mm, shape=shape, with_contrast=with_contrast)
        return self._spiral_cosine(phic, [u], [s]), contrast

    def _phase_c_grid(self, *, u0, s0, step_mm, shape, with_contrast=False):
        """phi_c (float64) on a regular skin grid, the ridge contrast there (or None), and the grid's columns and
        rows (skin mm)."""
        ny, nx = shape
        ns, nu = self.phase_grid.shape
        u = float(u0) + float(step_mm) * np.arange(nx)
        s = float(s0) + float(step_mm) * np.arange(ny)
        wu = _catmull_rom_matrix(self.grid_u0, _GRID_MM, nu, u)
        ws = _catmull_rom_matrix(self.grid_s0, _GRID_MM, ns, s)
        # Separable Catmull-Rom in float64 (cv2.remap would quantise positions to 1/32 px, too coarse for phase).
        phic = np.ascontiguousarray((wu @ (ws @ self.phase_grid).T).T)
        contrast = None
        if with_contrast:
            contrast = (wu @ (ws @ self.contrast_grid.astype(np.float64)).T).T.astype(np.float32)
        return phic, contrast, u, s

    def _spiral_cosine(self, phic: np.ndarray, us: list[np.ndarray], ss: list[np.ndarray]) -> np.ndarray:
        """cos(phi) on grids g with columns us[g] and rows ss[g] (all the same width), given phi_c there, stacked
        row-wise in ``phic``."""
        grid_of_row = np.repeat(np.arange(len(ss)), [len(r) for r in ss])
        return _spiral_cosine(
            np.ascontiguousarray(phic), np.stack(us), np.concatenate(ss), grid_of_row,
            self.spiral_xy[:, 0].copy(), self.spiral_xy[:, 1].copy(), self.minutia_polarity.astype(np.int64),
        )

    # ------------------------------------------------------------------ truth
    def features(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (F,), kinds (F,), skin positions (F, 2) mm): minutiae first, then pores; ids are 0..F-1."""
        xy = np.concatenate([self.minutia_xy.reshape(-1, 2), self.pore_xy.reshape(-1, 2)])
        kinds = np.concatenate([self.minutia_kind, np.full(len(self.pore_xy), FeatureKind.PORE, dtype=np.int8)])
        return np.arange(len(xy), dtype=np.int64), kinds.astype(np.int8), xy


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], *, sigma_px: float) -> np.ndarray:
    """Smooth random field scaled to [-1, 1]."""
    f = gaussian_filter(rng.standard_normal(shape), sigma_px, mode="reflect")
    f -= f.mean()
    m = np.max(np.abs(f))
    return f / m if m > 0 else f


def _dart_throw(rng, count, bounds, spacing, *, margin):
    u_min, u_max, s_min, s_max = bounds
    pts: list[tuple[float, float]] = []
    tries = 0
    while len(pts) < count and tries < 50 * max(count, 1):
        tries += 1
        q = (rng.uniform(u_min + margin, u_max - margin), rng.uniform(s_min + margin, s_max - margin))
        if all((q[0] - a) ** 2 + (q[1] - b) ** 2 >= spacing**2 for a, b in pts):
            pts.append(q)
    return pts


def _integrate_phase(params: FingerprintParams, U, S, rng, *, centre) -> np.ndarray:
    """Least-squares phase whose gradient is 2 pi / lambda times the Sherlock-Monro ridge normal (DCT Poisson)."""
    z = U + 1j * S
    c0 = complex(*centre)
    theta = np.full(U.shape, np.deg2rad(params.orientation_deg))
    # Each arg() has its branch cut on the ray from the singular point pointing away from the region.
    for sign, points in ((0.5, params.cores_mm), (-0.5, params.deltas_mm)):
        for cu, cs in points:
            c = complex(cu, cs)
            direction = (c0 - c) / abs(c0 - c) if c0 != c else 1.0
            theta = theta + sign * (np.angle((z - c) / direction) + np.angle(direction))
    period = params.ridge_period_mm * (1.0 + params.period_variation * _smooth_noise(rng, U.shape, sigma_px=2.5 / _GRID_MM))
    k = 2 * np.pi / period
    gu, gs = -np.sin(theta) * k, np.cos(theta) * k
    h = _GRID_MM
    # Normal equations of min |D phi - g|^2 with forward differences D: D^T D phi = D^T g. D^T D is the Neumann
    # Laplacian, diagonalised by the DCT-II; D^T g carries the boundary flux, hence the linear part of the phase.
    rx = 0.5 * (gu[:, 1:] + gu[:, :-1])
    ry = 0.5 * (gs[1:, :] + gs[:-1, :])
    b = np.zeros_like(gu)
    b[:, :-1] -= rx
    b[:, 1:] += rx
    b[:-1, :] -= ry
    b[1:, :] += ry
    b /= h
    ny, nx = b.shape
    f = dctn(b, type=2, norm="ortho")
    ly = (2 - 2 * np.cos(np.pi * np.arange(ny) / ny)) / (h * h)
    lx = (2 - 2 * np.cos(np.pi * np.arange(nx) / nx)) / (h * h)
    denom = ly[:, None] + lx[None, :]
    denom[0, 0] = 1.0
    f = f / denom
    f[0, 0] = 0.0
    phi = idctn(f, type=2, norm="ortho")
    return phi + rng.uniform(0, 2 * np.pi)

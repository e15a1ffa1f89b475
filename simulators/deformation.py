"""Motion and deformation of the fingertip skin: a forward Lagrangian field, its inverse and its gradient.

Everything here is in millimetres on the unrolled contact surface (``u``, ``s``; see :mod:`skinstretch.simulators.ideal_optics`).
A skin point is named by where it is in frame 0 (its *skin coordinate* ``X``); in frame k it is at
``x = X + d_k(X)``. Frame 0 is the reference: ``d_0 = 0`` exactly.

What is modelled
----------------
1. **Bulk motion** ``B_k`` (the finger's bone and the skin far from the contact centre): a rigid motion,
   translation ``m(t)`` and rotation ``theta(t)`` (degrees, counter-clockwise on the image) about a centre,
   interpolated from keyframes with a monotone cubic (PCHIP), so the velocity profile is smooth.
2. **Plastic distortion** (Cappelli, Maio & Maltoni 2001): a close-contact ellipse of skin moves with a different
   rigid motion ``A_k`` (it sticks: it follows the bulk only by ``1 - stick`` and lags behind the bulk sliding
   direction by ``lag``), and the transition band of width ``band_mm`` outside the ellipse blends the two:
   ``y = A(X) + brake(dist(X)) * (B(X) - A(X))`` with ``brake(d) = (1 - cos(pi d / band)) / 2`` on ``[0, band]``.
   ``dist`` is the elliptical radius minus one, times the mean semi-axis (an approximation of the distance to the
   ellipse that is exact on its axes). The lag grows with speed (``tanh(|v| / v0)``) and, optionally, carries a
   stick-slip sawtooth: the contact centre sticks while the bulk drags it, then slips back within
   ``slip_fraction`` of each period (the seed, 6.3.3, suggests stick-slip as a source of the deformation seen
   on flat surfaces).
3. **Ridge/valley mechanics** (seed 6.3.2, 7.1): between consecutive frames the seed sees the skin *approaching* a
   ridge compress and the skin that has *passed* it expand (the reverse for a valley), i.e. the skin slows down as it
   crosses a ridge (and speeds up across a valley). Modelled as a lag along ``s`` that every skin point accumulates
   while it travels across the glass-fixed shape: with ``y`` the skin point's position after the bulk motion and the
   plastic distortion (``y = X`` in frame 0),
   ``W(X) = -a (G(y_s) - G(X_s))``, ``G(s) = integral of g``, ``g(s) = exp(-(s - s_c)^2 / (2 sigma_m^2))``.
   A step ``dy`` of the finger moves skin at the shape by ``(1 - a g) dy``: the change in stretch between two frames
   is ``-a g'(s) dy``, negative (compression) one ``sigma_m`` before the shape in the sliding direction and positive
   (expansion) one ``sigma_m`` past it, whichever way the finger slides; skin on the shape is compressed by ``a``
   relative to skin that has not reached it. ``a`` (``peak_strain``) is positive for a ridge, negative for a
   valley. ``W`` depends only on where the skin point is and where it started, so it is the same whatever the
   frame order, and it is zero in frame 0. The lag per mm of travel does not depend on the sliding speed
   (rate-independent friction); ``speed_scale_mm_s`` is accepted for scene files and not used.
4. **Slip front** (optional): the partial-slip front that runs across the contact at the onset of sliding, as a band
   of uniaxial strain ``A`` (negative: compression) along a unit direction ``n``, Gaussian across (``sigma``),
   centred at ``c(t)`` along ``n`` and travelling with it: ``d_f(X) = n A (F(n.X - c(t)) - F(n.X - c(0)))`` with
   ``F(z) = integral of exp(-z^2 / 2 sigma^2)``, i.e. strain ``A (g(n.X - c(t)) - g(n.X - c(0)))`` along ``n``: a
   compression band where the front is now and, relative to frame 0, the opposite where it started (start it
   outside the contact); between two frames, compression ahead of the front and extension behind it. Skin the
   front has passed is shifted by ``-A sigma sqrt(2 pi)`` along ``n`` (forward, for a compression) against skin it
   has not reached. It is added
   to the rigid + plastic part (skin coordinates), so it is exactly zero in frame 0.
All time-dependent non-rigid terms are multiplied by a ramp ``smoothstep(t / ramp_s)`` so frame 0 is undeformed.

What is not modelled
--------------------
Normal (out-of-plane) deformation and the bulging of the finger pad, visco-elastic creep, the dependence of
the sticking area on the friction coefficient, inertia, incompressibility (area is not conserved), skin
folding, the change of the mechanics with normal force. The field is smooth: the slip front is a smooth band, not
the discontinuity of slip a real front may carry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np
from pydantic import Field, model_validator
from scipy.interpolate import PchipInterpolator
from scipy.special import erf as _erf

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import FiniteFloat, PositiveFloat, validated_dataclass


def rotation_matrix(theta_deg: float) -> np.ndarray:
    """Rotation by ``theta_deg`` counter-clockwise *on the image* (x right, y down), as a (2, 2) matrix."""
    t = np.deg2rad(theta_deg)
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, s], [-s, c]])


def _rotation_minus_identity(theta_deg: float) -> np.ndarray:
    # cos(0) - 1 and sin(0) are exactly 0, so a pure translation has an exactly zero displacement gradient.
    t = np.deg2rad(theta_deg)
    return np.array([[np.cos(t) - 1.0, np.sin(t)], [-np.sin(t), np.cos(t) - 1.0]])


def _smoothstep(x: np.ndarray | float) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True)
class MotionProfile:
    """Bulk motion of the finger from keyframes ``(t_s, u_mm, s_mm, theta_deg)``; held constant outside them.

    Examples
    --------
    >>> m = MotionProfile.from_keyframes([(0.0, 0.0, 0.0, 0.0), (3.0, 0.0, 6.0, 0.0)])
    >>> m.pose(1.5)[1]
    3.0
    """

    t: np.ndarray
    u: np.ndarray
    s: np.ndarray
    theta: np.ndarray
    _splines: dict = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_keyframes(cls, keyframes) -> "MotionProfile":
        k = np.asarray(keyframes, dtype=np.float64)
        if k.ndim != 2 or k.shape[1] != 4 or k.shape[0] < 1:
            raise InvalidInputError(f"keyframes must be a list of (t_s, u_mm, s_mm, theta_deg), got shape {k.shape}")
        if not np.all(np.isfinite(k)):
            raise InvalidInputError("keyframes must be finite")
        if k.shape[0] > 1 and np.any(np.diff(k[:, 0]) <= 0):
            raise InvalidInputError(f"keyframe times must increase strictly, got {k[:, 0].tolist()}")
        return cls(t=k[:, 0], u=k[:, 1], s=k[:, 2], theta=k[:, 3])

    def _interp(self, values: np.ndarray, t: np.ndarray, nu: int = 0) -> np.ndarray:
        if self.t.size == 1:
            return np.full_like(t, values[0] if nu == 0 else 0.0)
        inside = np.clip(t, self.t[0], self.t[-1])
        key = id(values)
        spline = self._splines.get(key)
        if spline is None:
            spline = self._splines[key] = PchipInterpolator(self.t, values, extrapolate=False)
        out = spline(inside, nu)
        if nu:
            out = np.where((t < self.t[0]) | (t > self.t[-1]), 0.0, out)
        return out

    def pose(self, t_s: float) -> tuple[float, float, float]:
        """(u_mm, s_mm, theta_deg) of the bulk at time ``t_s``."""
        t = np.array([float(t_s)])
        return tuple(float(self._interp(v, t)[0]) for v in (self.u, self.s, self.theta))  # type: ignore[return-value]

    def velocity(self, t_s: float) -> tuple[float, float]:
        """(du/dt, ds/dt) in mm/s at time ``t_s``."""
        t = np.array([float(t_s)])
        return float(self._interp(self.u, t, 1)[0]), float(self._interp(self.s, t, 1)[0])


@validated_dataclass
class PlasticDistortion:
    """Cappelli-style sticking ellipse (skin coordinates, mm) and how it lags the bulk motion."""

    center_mm: tuple[FiniteFloat, FiniteFloat] = (0.0, 0.0)
    semi_axes_mm: tuple[PositiveFloat, PositiveFloat] = (3.0, 4.0)
    band_mm: PositiveFloat = 2.0
    stick: FiniteFloat = Field(default=0.0, ge=0, le=1)
    lag_mm: FiniteFloat = 0.0
    lag_speed_mm_s: PositiveFloat = 1.0
    stick_slip_mm: FiniteFloat = 0.0
    stick_slip_period_s: PositiveFloat = 0.25
    slip_fraction: FiniteFloat = Field(default=0.15, gt=0, lt=1)


@validated_dataclass
class RidgeMechanics:
    """Skin slowed across a shape centred at arc length ``center_s_mm`` (see module doc): compression before it and
    expansion after it between consecutive frames (reversed for a negative ``peak_strain``, a valley)."""

    peak_strain: FiniteFloat = Field(default=0.0, gt=-0.5, lt=0.5)
    center_s_mm: FiniteFloat = 0.0
    sigma_mm: PositiveFloat = 0.75
    speed_scale_mm_s: PositiveFloat = 0.3


@validated_dataclass
class SlipFront:
    """A band of uniaxial strain ``amplitude`` (negative: compression) travelling along ``direction_deg``
    (counter-clockwise on the image from +x), Gaussian across with ``width_mm`` full width at half height, at
    ``position_mm`` along the direction interpolated linearly between ``keyframes`` ``(t_s, position_mm)``.
    ``amplitude`` 0 turns it off (see the module doc, 4.)."""

    amplitude: FiniteFloat = Field(default=0.0, gt=-0.3, lt=0.3)
    width_mm: PositiveFloat = 0.8
    direction_deg: FiniteFloat = -90.0
    keyframes: tuple[tuple[FiniteFloat, FiniteFloat], ...] = Field(default=((0.0, 0.0),), min_length=1)

    @model_validator(mode="after")
    def _times_increase(self) -> "SlipFront":
        times = [t for t, _ in self.keyframes]
        if any(b <= a for a, b in zip(times, times[1:])):
            raise InvalidInputError(f"keyframe times must increase strictly, got {times}")
        return self

    @property
    def sigma_mm(self) -> float:
        """Gaussian sigma of the band (``width_mm`` is its full width at half height)."""
        return self.width_mm / (2.0 * math.sqrt(2.0 * math.log(2.0)))

    @property
    def direction(self) -> np.ndarray:
        """Unit vector (u, s) of the direction of travel."""
        return rotation_matrix(self.direction_deg) @ np.array([1.0, 0.0])

    def position(self, t_s: float) -> float:
        """Position (mm along the direction) of the band at time ``t_s``; held constant outside the keyframes."""
        k = np.asarray(self.keyframes, dtype=np.float64)
        return float(np.interp(float(t_s), k[:, 0], k[:, 1]))


@dataclass(frozen=True)
class FrameDeformation:
    """The deformation of one frame: ``forward`` maps skin coordinates (frame-0 mm) to current mm."""

    theta_a: float
    theta_b: float
    t_a: np.ndarray
    t_b: np.ndarray
    center: np.ndarray
    ellipse_center: np.ndarray
    semi_axes: np.ndarray
    band: float
    mech_a: float
    mech_center: float
    mech_sigma: float
    front_a: float = 0.0
    front_n: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0]))
    front_c: float = 0.0
    front_c0: float = 0.0
    front_sigma: float = 1.0
    _ra: np.ndarray = field(init=False, repr=False)
    _rb: np.ndarray = field(init=False, repr=False)
    _rai: np.ndarray = field(init=False, repr=False)
    _rbi: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_ra", rotation_matrix(self.theta_a))
        object.__setattr__(self, "_rb", rotation_matrix(self.theta_b))
        object.__setattr__(self, "_rai", _rotation_minus_identity(self.theta_a))
        object.__setattr__(self, "_rbi", _rotation_minus_identity(self.theta_b))

    # -- pieces
    def _brake(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """brake(dist(X)) and its gradient wrt X."""
        a, b = self.semi_axes
        du = X[..., 0] - self.ellipse_center[0]
        ds = X[..., 1] - self.ellipse_center[1]
        re = np.sqrt((du / a) ** 2 + (ds / b) ** 2)
        rmean = 0.5 * (a + b)
        dist = (re - 1.0) * rmean
        q = np.clip(dist / self.band, 0.0, 1.0)
        beta = 0.5 * (1.0 - np.cos(np.pi * q))
        inband = (q > 0.0) & (q < 1.0)
        dbeta = np.where(inband, 0.5 * np.pi / self.band * np.sin(np.pi * q), 0.0) * rmean
        safe = np.where(re > 0, re, 1.0)
        grad = np.stack([dbeta * du / (a * a) / safe, dbeta * ds / (b * b) / safe], axis=-1)
        return beta, grad

    def _g(self, s: np.ndarray) -> np.ndarray:
        z = (s - self.mech_center) / self.mech_sigma
        return np.exp(-0.5 * z * z)

    def _G(self, s: np.ndarray) -> np.ndarray:
        """Integral of :meth:`_g` (up to a constant, which cancels in the lag)."""
        return self.mech_sigma * np.sqrt(0.5 * np.pi) * _erf((s - self.mech_center) / (self.mech_sigma * np.sqrt(2.0)))

    def _intermediate(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Displacement and displacement gradient of the rigid + plastic part and the slip front (before the ridge
        mechanics)."""
        rel = X - self.center
        da = rel @ self._rai.T + self.t_a
        diff = rel @ (self._rb - self._ra).T + (self.t_b - self.t_a)
        beta, gbeta = self._brake(X)
        d = da + beta[..., None] * diff
        h = self._rai + beta[..., None, None] * (self._rb - self._ra) + diff[..., :, None] * gbeta[..., None, :]
        if self.front_a != 0.0:
            n = self.front_n
            z = X @ n
            sig = self.front_sigma
            big_f = sig * np.sqrt(0.5 * np.pi) * (_erf((z - self.front_c) / (sig * np.sqrt(2.0)))
                                                  - _erf((z - self.front_c0) / (sig * np.sqrt(2.0))))
            g = np.exp(-0.5 * ((z - self.front_c) / sig) ** 2) - np.exp(-0.5 * ((z - self.front_c0) / sig) ** 2)
            d = d + self.front_a * big_f[..., None] * n
            h = h + self.front_a * g[..., None, None] * np.outer(n, n)
        return d, h

    # -- public
    def displacement(self, X: np.ndarray, *, with_gradient: bool = False):
        """Displacement ``d(X)`` (mm, shape of X) and optionally its gradient ``H[..., i, j] = d d_i / d X_j``."""
        X = np.asarray(X, dtype=np.float64)
        d, h = self._intermediate(X)
        if self.mech_a == 0.0:
            return (d, h) if with_gradient else d
        ys = X[..., 1] + d[..., 1]
        d = d.copy()
        d[..., 1] -= self.mech_a * (self._G(ys) - self._G(X[..., 1]))
        if not with_gradient:
            return d
        # dW/dX_j = -a (g(y_s) dy_s/dX_j - g(X_s) delta_sj), with dy_s/dX_j = delta_sj + H[s, j].
        gy, g0 = self._g(ys), self._g(X[..., 1])
        h = h.copy()
        h[..., 1, 0] -= self.mech_a * gy * h[..., 1, 0]
        h[..., 1, 1] -= self.mech_a * (gy * (1.0 + h[..., 1, 1]) - g0)
        return d, h

    def forward(self, X: np.ndarray) -> np.ndarray:
        """Current position ``X + d(X)`` of skin points ``X`` (mm)."""
        X = np.asarray(X, dtype=np.float64)
        return X + self.displacement(X)

    def inverse(self, x: np.ndarray, *, iterations: int = 4) -> np.ndarray:
        """Skin coordinates ``X`` of the skin points now at ``x`` (mm): solves ``X + d(X) = x``.

        Same algorithm as :meth:`inverse_reference`, compiled (numba): the renderer calls it for every node of
        every frame.
        """
        x = np.asarray(x, dtype=np.float64)
        flat = np.ascontiguousarray(x.reshape(-1, 2))
        out = _inverse_kernel(
            flat, self.t_a, self.t_b, self._ra, self._rb, self._rai, self.center, self.ellipse_center,
            self.semi_axes, float(self.band), float(self.mech_a), float(self.mech_center), float(self.mech_sigma),
            float(self.front_a), np.asarray(self.front_n, dtype=np.float64), float(self.front_c),
            float(self.front_c0), float(self.front_sigma), int(iterations),
        )
        return out.reshape(x.shape)

    def inverse_reference(self, x: np.ndarray, *, iterations: int = 4) -> np.ndarray:
        """Skin coordinates ``X`` of the skin points now at ``x`` (mm): solves ``X + d(X) = x``.

        Newton's method on the whole map (bulk, plastic distortion and the ridge lag), started from the exact inverse
        of the bulk motion; it converges in one step inside the sticking ellipse away from a shape, where the map is
        rigid.
        """
        x = np.asarray(x, dtype=np.float64)
        X = (x - self.t_b - self.center) @ self._rb + self.center  # R^-1 = R^T, applied to row vectors
        for _ in range(iterations):
            d, h = self.displacement(X, with_gradient=True)
            r = X + d - x
            j00, j01, j10, j11 = 1.0 + h[..., 0, 0], h[..., 0, 1], h[..., 1, 0], 1.0 + h[..., 1, 1]
            det = j00 * j11 - j01 * j10
            X = X - np.stack([(j11 * r[..., 0] - j01 * r[..., 1]) / det, (-j10 * r[..., 0] + j00 * r[..., 1]) / det], -1)
        return X


@numba.njit(cache=True, nogil=True)
def _inverse_kernel(x, ta, tb, ra, rb, rai, c, ec, axes, band, mech_a, mech_c, mech_sig, front_a, fn, front_c,
                    front_c0, front_sig, iterations):  # pragma: no cover
    n = x.shape[0]
    out = np.empty_like(x)
    a, b = axes[0], axes[1]
    rmean = 0.5 * (a + b)
    d00, d01, d10, d11 = rb[0, 0] - ra[0, 0], rb[0, 1] - ra[0, 1], rb[1, 0] - ra[1, 0], rb[1, 1] - ra[1, 1]
    sq = np.sqrt(0.5 * np.pi) * mech_sig
    fsq = np.sqrt(0.5 * np.pi) * front_sig
    for p in numba.prange(n):
        x0, x1 = x[p, 0], x[p, 1]
        q0, q1 = x0 - tb[0] - c[0], x1 - tb[1] - c[1]
        X0 = rb[0, 0] * q0 + rb[1, 0] * q1 + c[0]
        X1 = rb[0, 1] * q0 + rb[1, 1] * q1 + c[1]
        for _ in range(iterations):
            r0, r1 = X0 - c[0], X1 - c[1]
            da0 = rai[0, 0] * r0 + rai[0, 1] * r1 + ta[0]
            da1 = rai[1, 0] * r0 + rai[1, 1] * r1 + ta[1]
            df0 = d00 * r0 + d01 * r1 + (tb[0] - ta[0])
            df1 = d10 * r0 + d11 * r1 + (tb[1] - ta[1])
            du, dv = X0 - ec[0], X1 - ec[1]
            re = np.sqrt((du / a) ** 2 + (dv / b) ** 2)
            qq = (re - 1.0) * rmean / band
            if qq <= 0.0:
                beta, gb0, gb1 = 0.0, 0.0, 0.0
            elif qq >= 1.0:
                beta, gb0, gb1 = 1.0, 0.0, 0.0
            else:
                beta = 0.5 * (1.0 - np.cos(np.pi * qq))
                db = 0.5 * np.pi / band * np.sin(np.pi * qq) * rmean / re
                gb0, gb1 = db * du / (a * a), db * dv / (b * b)
            f0 = X0 + da0 + beta * df0 - x0
            f1 = X1 + da1 + beta * df1 - x1
            j00 = 1.0 + rai[0, 0] + beta * d00 + df0 * gb0
            j01 = rai[0, 1] + beta * d01 + df0 * gb1
            j10 = rai[1, 0] + beta * d10 + df1 * gb0
            j11 = 1.0 + rai[1, 1] + beta * d11 + df1 * gb1
            fs = 0.0
            if front_a != 0.0:
                # Slip front n A (F(n.X - c) - F(n.X - c0)) (see FrameDeformation._intermediate).
                z = fn[0] * X0 + fn[1] * X1
                z1, z0 = (z - front_c) / front_sig, (z - front_c0) / front_sig
                amp = front_a * fsq * (math.erf(z1 / np.sqrt(2.0)) - math.erf(z0 / np.sqrt(2.0)))
                gz = front_a * (np.exp(-0.5 * z1 * z1) - np.exp(-0.5 * z0 * z0))
                f0 += fn[0] * amp
                f1 += fn[1] * amp
                fs = fn[1] * amp
                j00 += gz * fn[0] * fn[0]
                j01 += gz * fn[0] * fn[1]
                j10 += gz * fn[1] * fn[0]
                j11 += gz * fn[1] * fn[1]
            if mech_a != 0.0:
                # Ridge lag W = -a (G(y_s) - G(X_s)) on the s row (see FrameDeformation.displacement).
                ys = X1 + da1 + beta * df1 + fs
                zy, z0 = (ys - mech_c) / mech_sig, (X1 - mech_c) / mech_sig
                gy, g0 = np.exp(-0.5 * zy * zy), np.exp(-0.5 * z0 * z0)
                f1 -= mech_a * sq * (math.erf(zy / np.sqrt(2.0)) - math.erf(z0 / np.sqrt(2.0)))
                j10 -= mech_a * gy * j10
                j11 -= mech_a * (gy * j11 - g0)
            det = j00 * j11 - j01 * j10
            X0 -= (j11 * f0 - j01 * f1) / det
            X1 -= (-j10 * f0 + j00 * f1) / det
        out[p, 0] = X0
        out[p, 1] = X1
    return out


def green_lagrange(h: np.ndarray) -> np.ndarray:
    """Green-Lagrange strain (Exx, Eyy, Exy) from displacement gradients ``h[..., 2, 2]``.

    ``E = (H + H^T + H^T H) / 2``, written so that a zero gradient gives an exactly zero strain.
    """
    h = np.asarray(h, dtype=np.float64)
    hth = np.einsum("...ki,...kj->...ij", h, h)
    exx = h[..., 0, 0] + 0.5 * hth[..., 0, 0]
    eyy = h[..., 1, 1] + 0.5 * hth[..., 1, 1]
    exy = 0.5 * (h[..., 0, 1] + h[..., 1, 0] + hth[..., 0, 1])
    return np.stack([exx, eyy, exy], axis=-1)


@dataclass(frozen=True)
class DeformationModel:
    """Bulk motion + plastic distortion + slip front + ridge/valley mechanics; ``at(t)`` gives one frame's
    deformation."""

    motion: MotionProfile
    plastic: PlasticDistortion = PlasticDistortion()
    mechanics: RidgeMechanics = RidgeMechanics()
    slip_front: SlipFront = SlipFront()
    rotation_center_mm: tuple[float, float] = (0.0, 0.0)
    ramp_s: float = 0.1

    def _envelope(self, t: float) -> float:
        return float(_smoothstep(t / self.ramp_s)) if self.ramp_s > 0 else (1.0 if t > 0 else 0.0)

    def lag_vector(self, t: float) -> np.ndarray:
        """How far (mm) the sticking ellipse trails the bulk at time t (zero at t = 0)."""
        p = self.plastic
        vu, vs = self.motion.velocity(t)
        speed = float(np.hypot(vu, vs))
        if speed == 0.0 or (p.lag_mm == 0.0 and p.stick_slip_mm == 0.0):
            return np.zeros(2)
        phase = (t / p.stick_slip_period_s) % 1.0
        # Sawtooth: the lag builds up linearly while stuck, then is released in the last slip_fraction.
        stuck = 1.0 - p.slip_fraction
        saw = phase / stuck if phase < stuck else 1.0 - float(_smoothstep((phase - stuck) / p.slip_fraction))
        amount = (p.lag_mm + p.stick_slip_mm * saw) * np.tanh(speed / p.lag_speed_mm_s)
        return self._envelope(t) * amount * np.array([vu, vs]) / speed

    def at(self, t_s: float) -> FrameDeformation:
        """The deformation at time ``t_s`` relative to ``t = 0``."""
        t = float(t_s)
        u0, s0, th0 = self.motion.pose(0.0)
        u, s, th = self.motion.pose(t)
        m = np.array([u - u0, s - s0])
        theta_b = th - th0
        p = self.plastic
        theta_a = (1.0 - p.stick) * theta_b
        t_a = (1.0 - p.stick) * m - self.lag_vector(t)
        mech = self.mechanics
        a = float(mech.peak_strain)  # the lag is zero in frame 0 by construction: no ramp needed
        return FrameDeformation(
            theta_a=theta_a,
            theta_b=theta_b,
            t_a=t_a,
            t_b=m,
            center=np.asarray(self.rotation_center_mm, dtype=np.float64),
            ellipse_center=np.asarray(p.center_mm, dtype=np.float64),
            semi_axes=np.asarray(p.semi_axes_mm, dtype=np.float64),
            band=p.band_mm,
            mech_a=a,
            mech_center=mech.center_s_mm,
            mech_sigma=mech.sigma_mm,
            front_a=float(self.slip_front.amplitude),
            front_n=self.slip_front.direction,
            front_c=self.slip_front.position(t),
            front_c0=self.slip_front.position(0.0),
            front_sigma=self.slip_front.sigma_mm,
        )

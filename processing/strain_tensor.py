"""The 2-D strain tensor as DIC tools report it (ncorr, DICe, GOM): Green-Lagrange components and principal strains.

* :func:`triangle_strain_tensors`: the tensor of each triangle of points tracked from frame a to frame b, from the
  deformation gradient ``F`` of the affine map taking its three frame-a corners to their frame-b positions.
* :func:`local_affine_fit`: the least-squares affine map of the points within a radius of a point (a "virtual
  gauge"), its ``F`` and where the point itself went.
* :func:`green_lagrange`: ``E = (F^T F - I) / 2`` of any stack of ``F``, with its principal values and direction.

Conventions: image axes (x = column, y = row, y pointing down); fractions (0.01 = 1 %); ``exy`` is the tensor
component ``E[0, 1]``, half the engineering shear; ``e1 >= e2``; ``angle_deg`` is the direction of ``e1`` from +x
towards +y (clockwise as seen on the image), in (-90, 90]. A tensor that cannot be computed (a degenerate triangle,
non-finite corners, too few or collinear gauge points) carries a status code and zeros, never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from skinstretch.processing.errors import InvalidInputError

__all__ = ["StrainTensors", "LocalAffine", "TENSOR_OK", "TENSOR_DEGENERATE", "TENSOR_NOT_FINITE",
           "TENSOR_STATUS_NAMES", "green_lagrange", "triangle_strain_tensors", "local_affine_fit"]

#: Why a tensor is (not) there; stored as int8 (``tensor_status`` of the results' triangle tables).
TENSOR_OK, TENSOR_DEGENERATE, TENSOR_NOT_FINITE = 0, 1, 2
TENSOR_STATUS_NAMES = {TENSOR_OK: "ok", TENSOR_DEGENERATE: "degenerate", TENSOR_NOT_FINITE: "not_finite"}


@dataclass(frozen=True)
class StrainTensors:
    """Green-Lagrange strain of ``n`` elements (fractions, image axes); 0 wherever ``status`` is not TENSOR_OK."""

    exx: np.ndarray
    eyy: np.ndarray
    exy: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    angle_deg: np.ndarray
    status: np.ndarray  # int8: TENSOR_OK, TENSOR_DEGENERATE, TENSOR_NOT_FINITE

    @property
    def ok(self) -> np.ndarray:
        return self.status == TENSOR_OK


def green_lagrange(F: np.ndarray, *, status: np.ndarray | None = None) -> StrainTensors:
    """``E = (F^T F - I) / 2`` of ``F`` (..., 2, 2) with its principal strains and the angle of ``e1``.

    ``status`` (optional, int8 of shape ``F.shape[:-2]``) marks elements already known bad; a non-finite ``F``
    is marked TENSOR_NOT_FINITE. Bad elements get zeros.

    >>> t = green_lagrange(np.array([[1.02, 0.0], [0.0, 1.0]]))
    >>> round(float(t.exx), 6), round(float(t.e1), 6), float(t.angle_deg)
    (0.0202, 0.0202, 0.0)
    """
    F = np.asarray(F, dtype=np.float64)
    if F.shape[-2:] != (2, 2):
        raise InvalidInputError(f"F must have shape (..., 2, 2), got {F.shape}")
    st = np.zeros(F.shape[:-2], np.int8) if status is None else np.array(status, dtype=np.int8, copy=True)
    finite = np.all(np.isfinite(F), axis=(-2, -1))
    st[(st == TENSOR_OK) & ~finite] = TENSOR_NOT_FINITE
    good = st == TENSOR_OK
    F = np.where(good[..., None, None], F, np.eye(2))
    a, b, c, d = F[..., 0, 0], F[..., 0, 1], F[..., 1, 0], F[..., 1, 1]
    exx = 0.5 * (a * a + c * c - 1.0)
    eyy = 0.5 * (b * b + d * d - 1.0)
    exy = 0.5 * (a * b + c * d)
    mean, half = 0.5 * (exx + eyy), 0.5 * (exx - eyy)
    radius = np.hypot(half, exy)
    angle = np.degrees(0.5 * np.arctan2(2.0 * exy, exx - eyy))
    angle = np.where(angle <= -90.0, angle + 180.0, angle)
    z = np.zeros_like(exx)
    return StrainTensors(*(np.where(good, v, z) for v in (exx, eyy, exy, mean + radius, mean - radius, angle)), st)


def triangle_strain_tensors(corners_a: np.ndarray, corners_b: np.ndarray, *, min_area_px2: float = 1e-6
                            ) -> StrainTensors:
    """The strain of each triangle: corners (T, 3, 2) x, y px in frame a and in frame b.

    ``F`` solves ``[p1 - p0, p2 - p0]_b = F [p1 - p0, p2 - p0]_a`` exactly (three points fix an affine map). A
    triangle whose frame-a area is below ``min_area_px2`` is TENSOR_DEGENERATE. A flipped triangle (det F < 0) has
    a tensor all the same: the results' ``flipped`` column says it is not a strain.

    >>> a = np.array([[[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]]])
    >>> t = triangle_strain_tensors(a, a * [1.01, 1.0])
    >>> round(float(t.exx[0]), 7), round(float(t.eyy[0]), 7)
    (0.01005, 0.0)
    """
    a = np.asarray(corners_a, dtype=np.float64)
    b = np.asarray(corners_b, dtype=np.float64)
    if a.shape != b.shape or a.shape[-2:] != (3, 2):
        raise InvalidInputError(f"corners_a and corners_b must both have shape (T, 3, 2), got {a.shape}, {b.shape}")
    da = np.stack([a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]], axis=-1)  # columns are the two edges
    db = np.stack([b[:, 1] - b[:, 0], b[:, 2] - b[:, 0]], axis=-1)
    det = da[:, 0, 0] * da[:, 1, 1] - da[:, 0, 1] * da[:, 1, 0]
    status = np.zeros(a.shape[0], np.int8)
    finite = np.all(np.isfinite(a), axis=(1, 2)) & np.all(np.isfinite(b), axis=(1, 2))
    status[~finite] = TENSOR_NOT_FINITE
    status[finite & ~(0.5 * np.abs(det) >= min_area_px2)] = TENSOR_DEGENERATE
    safe = np.where(status == TENSOR_OK, det, 1.0)
    inv = np.empty_like(da)
    inv[:, 0, 0], inv[:, 1, 1] = da[:, 1, 1] / safe, da[:, 0, 0] / safe
    inv[:, 0, 1], inv[:, 1, 0] = -da[:, 0, 1] / safe, -da[:, 1, 0] / safe
    F = np.einsum("tij,tjk->tik", np.nan_to_num(db), inv)
    return green_lagrange(F, status=status)


@dataclass(frozen=True)
class LocalAffine:
    """The least-squares affine map ``p_b = F (p_a - center) + position_b`` of the points near ``center``.

    ``ok`` False (with ``reason``) when too few points were in reach or they were (nearly) collinear; ``F`` is
    then the identity and ``position_b`` the centre. ``residual_rms_px``: RMS of the fit's residuals (per
    coordinate, over the 2n - 6 degrees of freedom); ``F_sigma``: the standard error of each entry of ``F`` under
    independent residuals of that size (0 for an exact fit of 3 points, which leaves no residual to judge by)."""

    F: np.ndarray  # (2, 2)
    center: np.ndarray  # (2,) x, y px in frame a
    position_b: np.ndarray  # (2,) where the centre went, px in frame b
    n_points: int
    ok: bool
    reason: str = ""
    residual_rms_px: float = 0.0
    F_sigma: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))

    @property
    def strain_sigma(self) -> tuple[float, float, float]:
        """Standard errors of ``exx``, ``eyy``, ``exy`` to first order (small strain: ``E ~ (F + F^T) / 2 - I``)."""
        s = self.F_sigma
        return float(s[0, 0]), float(s[1, 1]), float(0.5 * np.hypot(s[0, 1], s[1, 0]))

    @property
    def strain(self) -> StrainTensors:
        """The Green-Lagrange tensor of ``F`` (scalars as 0-d arrays; TENSOR_DEGENERATE when not ``ok``)."""
        return green_lagrange(self.F, status=np.int8(TENSOR_OK if self.ok else TENSOR_DEGENERATE))


def local_affine_fit(points_a: np.ndarray, points_b: np.ndarray, *, center, radius_px: float,
                     min_points: int = 3) -> LocalAffine:
    """Fit the affine map taking the frame-a ``points_a`` (n, 2) within ``radius_px`` of ``center`` to their
    frame-b ``points_b``, by least squares (DIC's strain window over a virtual gauge).

    Rows with a non-finite position are left out. The fit is refused (``ok`` False) with fewer than ``min_points``
    points, or when their spread is nearly one-dimensional (the smaller principal spread below 1 % of the larger).

    >>> pa = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0], [4.0, 4.0]])
    >>> fit = local_affine_fit(pa, pa * [1.01, 1.0] + 2.0, center=(2.0, 2.0), radius_px=5.0)
    >>> fit.ok, np.round(fit.position_b, 6).tolist(), round(float(fit.F[0, 0]), 6)
    (True, [4.02, 4.0], 1.01)
    """
    pa = np.asarray(points_a, dtype=np.float64).reshape(-1, 2)
    pb = np.asarray(points_b, dtype=np.float64).reshape(-1, 2)
    if pa.shape != pb.shape:
        raise InvalidInputError(f"points_a and points_b must have the same shape, got {pa.shape}, {pb.shape}")
    c = np.asarray(center, dtype=np.float64).reshape(2)
    if not (np.isfinite(radius_px) and radius_px > 0):
        raise InvalidInputError(f"radius_px must be a positive number, got {radius_px!r}")
    keep = np.all(np.isfinite(pa), axis=1) & np.all(np.isfinite(pb), axis=1)
    keep &= np.hypot(pa[:, 0] - c[0], pa[:, 1] - c[1]) <= radius_px
    pa, pb = pa[keep], pb[keep]
    n = int(pa.shape[0])
    if n < max(3, int(min_points)):
        return LocalAffine(np.eye(2), c, c.copy(), n, False, f"{n} points within {radius_px:.1f} px, need "
                                                              f"{max(3, int(min_points))}")
    ma, mb = pa.mean(axis=0), pb.mean(axis=0)
    xa, xb = pa - ma, pb - mb
    cov = xa.T @ xa
    spread = np.linalg.eigvalsh(cov)
    if not spread[0] > 1e-4 * spread[1]:
        return LocalAffine(np.eye(2), c, c.copy(), n, False, f"the {n} points within {radius_px:.1f} px are "
                                                              "(nearly) collinear")
    F = np.linalg.solve(cov, xa.T @ xb).T  # xb ~ xa F^T
    dof = 2 * n - 6
    rms = float(np.sqrt(np.sum((xb - xa @ F.T) ** 2) / dof)) if dof > 0 else 0.0
    # Var(F[i, j]) = rms^2 [cov^-1]_jj: each row of F is a least-squares fit of one coordinate.
    sigma = np.broadcast_to(rms * np.sqrt(np.diag(np.linalg.inv(cov))), (2, 2)).copy()
    return LocalAffine(F, c, mb + F @ (c - ma), n, True, residual_rms_px=rms, F_sigma=sigma)

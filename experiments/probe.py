"""A virtual strain gauge or extensometer on analysed results (DIC's "stage point" and "virtual extensometer").

:func:`probe` follows a skin point given in reference-frame pixels (the first frame with measured points, normally
frame 0: :attr:`~skinstretch.experiments.results_file.Results.cumulative`) through every frame. Each frame, the
skin points within ``radius_mm`` of it in the reference frame are fitted with an affine map to their positions in
that frame (:func:`~skinstretch.processing.strain_tensor.local_affine_fit`): the map gives where the point went,
its displacement since the reference and the cumulative Green-Lagrange tensor there. With ``to``, two such points
make an extensometer: the length between them in each frame and its change ``L/L_0 - 1``.
A frame where the fit is refused (too few or collinear points) keeps its row, with ``ok`` False and the reason.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from skinstretch.drivers.errors import SessionFileError
from skinstretch.experiments.results_file import Results, read_results
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.strain_tensor import local_affine_fit

__all__ = ["GaugeRow", "ExtensometerRow", "GaugeSeries", "probe", "reference_position", "DEFAULT_RADIUS_MM"]

#: The gauge's reach when none is given: about 3 feature spacings, or 3 flow grid steps at the default scale.
DEFAULT_RADIUS_MM = 1.0
#: Points a gauge fits at least: one more than an affine map needs, so its residual gives its uncertainty.
MIN_GAUGE_POINTS = 4


@dataclass(frozen=True)
class GaugeRow:
    """One frame of a gauge: where the point is (px), its displacement since the reference frame (px), the
    cumulative strain tensor there (fractions; angle of e1 in degrees) with the standard errors of its components
    and the RMS residual of the fit (px), the points fitted."""

    frame: int
    x: float
    y: float
    dx: float
    dy: float
    exx: float
    eyy: float
    exy: float
    e1: float
    e2: float
    angle_deg: float
    exx_sigma: float
    eyy_sigma: float
    exy_sigma: float
    residual_px: float
    n_points: int
    ok: bool
    reason: str = ""


@dataclass(frozen=True)
class ExtensometerRow:
    """One frame of an extensometer: both ends (px), the length between them (px), ``L / L_0 - 1`` and its standard
    error (from the two ends' position errors: each end's fit residual over the square root of its points)."""

    frame: int
    x1: float
    y1: float
    x2: float
    y2: float
    length_px: float
    length_change: float
    length_change_sigma: float
    n_points: int  # the fewer of the two ends' fitted points
    ok: bool
    reason: str = ""


@dataclass(frozen=True)
class GaugeSeries:
    """A gauge's (or an extensometer's) rows, one per analysed frame, with where and how it was placed."""

    kind: str  # "gauge" or "extensometer"
    at: tuple[float, float]
    to: tuple[float, float] | None
    radius_px: float
    px_per_mm: float
    reference_frame: int
    rows: list

    def columns(self) -> list[str]:
        row_type = GaugeRow if self.kind == "gauge" else ExtensometerRow
        return [f.name for f in fields(row_type)]

    def to_dataframe(self):
        import pandas as pd  # noqa: PLC0415 - only for users who ask for DataFrames

        return pd.DataFrame([asdict(r) for r in self.rows], columns=self.columns())

    def csv_text(self) -> str:
        """The rows as CSV: a header of column names (units in docs/viewer.md, "Virtual gauge"), a row a frame."""
        out = io.StringIO(newline="")
        w = csv.writer(out, lineterminator="\n")
        w.writerow(self.columns())
        for r in self.rows:
            w.writerow([_cell(v) for v in asdict(r).values()])
        return out.getvalue()

    def to_csv(self, path: str | os.PathLike) -> Path:
        """Write :meth:`csv_text` to ``path``."""
        path = Path(path)
        path.write_text(self.csv_text(), encoding="utf-8")
        return path

    def to_json(self) -> dict:
        """The viewer's form: placement and one list per column."""
        cols = self.columns()
        return {"kind": self.kind, "at": list(self.at), "to": list(self.to) if self.to else None,
                "radius_px": self.radius_px, "reference_frame": self.reference_frame,
                "columns": {c: [_json_value(getattr(r, c)) for r in self.rows] for c in cols}}


def _cell(v):
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, float):
        return f"{v:.8g}"
    return v


def _json_value(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _point(value, name: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in value)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a point (x, y) in pixels, got {value!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise InvalidInputError(f"{name} must be finite, got {value!r}")
    return x, y


def probe(results: Results | str | os.PathLike, *, at, to=None, radius_mm: float | None = None) -> GaugeSeries:
    """The gauge at ``at`` (x, y in reference-frame px), or with ``to`` the extensometer from ``at`` to ``to``,
    over every frame of ``results`` (a :class:`Results` or its file or directory). ``radius_mm``: the reach of the
    local fit (default :data:`DEFAULT_RADIUS_MM`)."""
    r = results if isinstance(results, Results) else read_results(results)
    c = r.cumulative
    if c is None:
        raise SessionFileError(f"{r.path}: results written before the cumulative motion was stored; analyse the "
                               "session again to probe it")
    if c.reference_frame < 0:
        raise InvalidInputError(f"{r.path}: no frame has 3 measured points: there is nothing to probe")
    radius_mm = DEFAULT_RADIUS_MM if radius_mm is None else float(radius_mm)
    if not (math.isfinite(radius_mm) and radius_mm > 0):
        raise InvalidInputError(f"radius_mm must be a positive number, got {radius_mm!r}")
    radius = radius_mm * r.px_per_mm
    p1 = _point(at, "at")
    p2 = _point(to, "to") if to is not None else None
    h, w = r.image_shape
    for p, name in ((p1, "at"), (p2, "to")):
        if p is not None and not (0 <= p[0] < w and 0 <= p[1] < h):
            raise InvalidInputError(f"{name} {p} is outside the {w} x {h} px frame")
    rows = []
    for k in range(r.n_frames):
        s = c.sample(k)
        if s is None:
            why = "before the reference frame" if k < c.reference_frame else "no motion measured to this frame"
            rows.append(_failed_row(k, p1, p2, why))
            continue
        pb = s.points + s.displacement
        fits = [local_affine_fit(s.points, pb, center=p, radius_px=radius, min_points=MIN_GAUGE_POINTS)
                for p in (p1, p2) if p is not None]
        rows.append(_gauge_row(k, p1, fits[0]) if p2 is None else _extensometer_row(k, p1, p2, *fits))
    return GaugeSeries("gauge" if p2 is None else "extensometer", p1, p2, radius, r.px_per_mm, c.reference_frame,
                       rows)


def reference_position(results: Results, xy, *, frame: int, radius_mm: float | None = None) -> tuple[float, float]:
    """Where the skin point seen at ``xy`` (px) in ``frame`` was in the reference frame (the viewer places a gauge
    on the frame shown): the inverse local affine fit of the cumulative motion around it; ``xy`` itself on the
    reference frame, or where no fit can be made."""
    p = _point(xy, "xy")
    c = results.cumulative
    s = c.sample(frame) if c is not None and frame != c.reference_frame else None
    if s is None or len(s) == 0:
        return p
    radius = (DEFAULT_RADIUS_MM if radius_mm is None else float(radius_mm)) * results.px_per_mm
    fit = local_affine_fit(s.points + s.displacement, s.points, center=p, radius_px=radius)
    return (float(fit.position_b[0]), float(fit.position_b[1])) if fit.ok else p


def _failed_row(k: int, p1, p2, reason: str):
    if p2 is None:
        return GaugeRow(k, math.nan, math.nan, math.nan, math.nan, *([0.0] * 10), 0, False, reason)
    return ExtensometerRow(k, math.nan, math.nan, math.nan, math.nan, math.nan, 0.0, 0.0, 0, False, reason)


def _gauge_row(k: int, p1, fit) -> GaugeRow:
    t = fit.strain
    x, y = (float(v) for v in fit.position_b)
    sxx, syy, sxy = fit.strain_sigma
    return GaugeRow(k, x, y, x - p1[0], y - p1[1], float(t.exx), float(t.eyy), float(t.exy), float(t.e1),
                    float(t.e2), float(t.angle_deg), sxx, syy, sxy, fit.residual_rms_px, fit.n_points, fit.ok,
                    fit.reason)


def _extensometer_row(k: int, p1, p2, f1, f2) -> ExtensometerRow:
    ok = f1.ok and f2.ok
    length0 = float(np.hypot(p2[0] - p1[0], p2[1] - p1[1]))
    a, b = f1.position_b, f2.position_b
    length = float(np.hypot(*(b - a)))
    change = length / length0 - 1.0 if ok and length0 > 0 else 0.0
    # Each end's position error: its fit's residual over sqrt(points) (the centre of a least-squares fit).
    sigma = math.hypot(f1.residual_rms_px / math.sqrt(max(f1.n_points, 1)),
                       f2.residual_rms_px / math.sqrt(max(f2.n_points, 1))) / length0 if ok and length0 > 0 else 0.0
    reason = "; ".join(f"{end}: {f.reason}" for end, f in (("at", f1), ("to", f2)) if not f.ok)
    return ExtensometerRow(k, float(a[0]), float(a[1]), float(b[0]), float(b[1]), length if ok else math.nan, change,
                           sigma, min(f1.n_points, f2.n_points), ok, reason)

"""Dots of a calibration grid in an image: sub-pixel centres, then their lattice indices (seed 3.4, 7.2.1).

The seed's grid is dots 0.5 mm apart printed on transparency film and pressed on the contact surface: dark dots on
the bright surface. :func:`detect_dots` finds them with sub-pixel centres (background-normalised darkness,
connected components, darkness-weighted centroids against a plane fitted to the illumination around each dot).
:func:`index_grid` gives them integer lattice indices (i, j), robust to missing and spurious dots: the grid is grown
from a regular seed dot using *local* lattice vectors extrapolated from the neighbours already indexed, so it
follows the strong spacing changes over a ridge or valley. The mapping fitted to the indexed dots is
:mod:`skinstretch.processing.grid_mapping_fit`'s.

Image pixels are ``(x, y)``: x the column, y the row, origin at the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from skinstretch.processing.argument_checks import positive_number
from skinstretch.processing.errors import InvalidInputError

__all__ = ["INDEX_NONE", "DotDetections", "detect_dots", "index_grid"]

#: Index given by :func:`index_grid` to dots that are not on the lattice.
INDEX_NONE = np.iinfo(np.int64).min



@dataclass
class DotDetections:
    """Dots found in one image: sub-pixel centres ``xy`` (K, 2) px, ``area`` (K,) px^2, ``darkness`` (K,) in 0..1."""

    xy: np.ndarray
    area: np.ndarray
    darkness: np.ndarray

    def __len__(self) -> int:
        return int(self.xy.shape[0])


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2 or image.shape[0] < 16 or image.shape[1] < 16:
        raise InvalidInputError(f"image must be a 2-D greyscale array of at least 16x16, got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.number) or not np.all(np.isfinite(image)):
        raise InvalidInputError("image must be numeric and finite")
    return image.astype(np.float32)


def detect_dots(
    image: np.ndarray,
    *,
    px_per_mm: float,
    dot_diameter_mm: float = 0.2,
    threshold: float = 0.4,
    min_area_factor: float = 0.15,
    max_area_factor: float = 3.0,
) -> DotDetections:
    """Find the dark dots of a calibration grid and their sub-pixel centres.

    Parameters
    ----------
    image : (H, W) array
        Greyscale image, dots dark on a bright surface.
    px_per_mm : float
        Nominal scale along the image x axis (sets the expected dot size and the background window).
    dot_diameter_mm : float
        Dot diameter on the sheet.
    threshold : float
        Relative darkness ``1 - I / background`` above which a pixel belongs to a dot.
    min_area_factor, max_area_factor : float
        Components smaller or larger than these multiples of the expected (sqrt(2)-compressed) dot area are
        rejected (noise, merged dots, large specks).

    Returns
    -------
    DotDetections
        Components touching the image border are left out (their centroid would be biased).
    """
    img = _check_image(image)
    px_per_mm = positive_number(px_per_mm, "px_per_mm")
    dot_diameter_mm = positive_number(dot_diameter_mm, "dot_diameter_mm")
    if not 0 < threshold < 1:
        raise InvalidInputError(f"threshold must be in (0, 1), got {threshold!r}")
    dot_px = dot_diameter_mm * px_per_mm
    # Bright background envelope: a grey closing wider than a dot removes the dots, keeping the illumination
    # (slopes of a ridge are darker, seed 6.3.2), so the darkness is relative to the local surface brightness.
    k = int(2 * math.ceil(1.5 * dot_px) + 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    background = cv2.morphologyEx(cv2.GaussianBlur(img, (0, 0), 0.8), cv2.MORPH_CLOSE, kernel)
    background = cv2.GaussianBlur(background, (0, 0), 0.25 * k)
    background = np.maximum(background, max(1.0, float(np.percentile(img, 99)) * 0.05))
    dark = np.clip(1.0 - img / background, 0.0, 1.0)
    mask = (dark > threshold).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    expected_area = math.pi / 4 * dot_px * dot_px * math.cos(math.radians(45.0))
    h, w = img.shape
    xs, areas, darks = [], [], []
    pad = 5
    for lab in range(1, n):
        x0, y0, bw, bh, area = stats[lab]
        if not (min_area_factor * expected_area <= area <= max_area_factor * expected_area):
            continue
        if x0 == 0 or y0 == 0 or x0 + bw >= w or y0 + bh >= h:
            continue
        xa, xb = max(x0 - pad, 0), min(x0 + bw + pad, w)
        ya, yb = max(y0 - pad, 0), min(y0 + bh + pad, h)
        lab_win = labels[ya:yb, xa:xb]
        comp = (lab_win == lab).astype(np.uint8)
        grown = cv2.dilate(comp, np.ones((5, 5), np.uint8)).astype(bool)
        others = cv2.dilate(((lab_win != lab) & (lab_win != 0)).astype(np.uint8), np.ones((5, 5), np.uint8))
        ring = cv2.dilate(comp, np.ones((9, 9), np.uint8)).astype(bool) & ~grown & ~others.astype(bool)
        gy, gx = np.mgrid[ya:yb, xa:xb]
        win = img[ya:yb, xa:xb]
        # Local background: a plane fitted to a ring around the dot. The slopes of a ridge or valley darken the
        # light (seed 6.3.2) with a gradient across a dot; relative darkness 1 - I / plane is then the dot's
        # coverage whatever the illumination, so its centroid is the dot's area centroid (blur preserves it).
        if ring.sum() >= 8:
            design = np.column_stack([np.ones(ring.sum()), gx[ring] - x0, gy[ring] - y0])
            coef, *_ = np.linalg.lstsq(design, win[ring].astype(np.float64), rcond=None)
            plane = coef[0] + coef[1] * (gx - x0) + coef[2] * (gy - y0)
        else:
            plane = background[ya:yb, xa:xb]
        rel = 1.0 - win / np.maximum(plane, 1.0)
        wgt = np.clip(rel, 0.0, None) * (grown & ~others.astype(bool))
        total = float(wgt.sum())
        if total <= 0:
            continue
        xs.append((float((wgt * gx).sum() / total), float((wgt * gy).sum() / total)))
        areas.append(float(area))
        darks.append(float(dark[ya:yb, xa:xb][comp.astype(bool)].mean()))
    xy = np.array(xs, dtype=np.float64).reshape(-1, 2)
    return DotDetections(xy=xy, area=np.array(areas), darkness=np.array(darks))


# ------------------------------------------------------------------------------------------------ grid topology


def _seed_lattice(xy: np.ndarray, tree: cKDTree, center: np.ndarray) -> tuple[int, np.ndarray, np.ndarray] | None:
    """A dot near the centre whose four lattice neighbours are where a regular lattice puts them (strictly first;
    a ridge's slopes can leave no strictly regular dot in a narrow strip, so then more loosely)."""
    for tol in (0.15, 0.3):
        found = _seed_lattice_within(xy, tree, center, tol)
        if found is not None:
            return found
    return None


def _seed_lattice_within(xy, tree, center, tol) -> tuple[int, np.ndarray, np.ndarray] | None:
    k = min(7, len(xy))
    order = np.argsort(np.linalg.norm(xy - center, axis=1))
    for idx in order[: min(len(order), 60)]:
        dist, nb = tree.query(xy[idx], k=k)
        vecs = xy[nb[1:]] - xy[idx]
        dist = dist[1:]
        if len(vecs) < 4 or not np.all(np.isfinite(dist)):
            continue
        a1 = vecs[0]
        cos = np.abs(vecs @ a1) / (np.linalg.norm(vecs, axis=1) * np.linalg.norm(a1))
        cand = np.flatnonzero(cos < 0.5)
        if cand.size == 0:
            continue
        a2 = vecs[cand[0]]
        ok = True
        for vec in (a1, -a1, a2, -a2):
            d, _ = tree.query(xy[idx] + vec)
            if d > tol * np.linalg.norm(vec):
                ok = False
                break
        if not ok or np.linalg.norm(a2) > 2.5 * np.linalg.norm(a1):
            continue
        # i runs along the vector closer to the image x axis, j along the other; both point to +x / +y.
        a, b = (a1, a2) if abs(a1[0]) / np.linalg.norm(a1) >= abs(a2[0]) / np.linalg.norm(a2) else (a2, a1)
        a = a if a[0] > 0 else -a
        b = b if b[1] > 0 else -b
        return int(idx), a, b
    return None


def index_grid(xy: np.ndarray, *, image_shape: tuple[int, int] | None = None, tolerance: float = 0.3) -> np.ndarray:
    """Lattice indices (i, j) of grid dots, robust to missing and spurious dots and to a ridge or valley.

    Rows of constant ``j`` run along the surface's rulings (image x), where the dot pitch is regular; across them
    the pitch changes by up to ~2x over a ridge's slopes, so no fixed lattice vector predicts the next row. The
    grid is therefore indexed row by row from a regular seed dot near the image centre: a row is walked along
    its local lattice vector (jumping over single missing dots), then the next row is found by *consensus*: every
    dot of the current row proposes its nearest dot ahead, and only proposals whose step agrees with the row's
    median step are kept (a missing dot would propose the row after next, a speck something in between).

    Parameters
    ----------
    xy : (K, 2) array
        Dot centres, px.
    image_shape : (H, W), optional
        Used to pick the seed near the image centre (default: the centre of the dots).
    tolerance : float
        A predicted position accepts the nearest dot within this fraction of the local lattice step.

    Returns
    -------
    (K, 2) int64
        (i, j) of each dot; unindexed dots (spurious, or off the lattice) get ``INDEX_NONE`` in both columns.
        Dot (0, 0) is the seed; i increases along +x, j along +y.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or not np.all(np.isfinite(xy)):
        raise InvalidInputError(f"xy must be a finite (K, 2) array, got shape {xy.shape}")
    if not 0 < tolerance < 0.5:
        raise InvalidInputError(f"tolerance must be in (0, 0.5), got {tolerance!r}")
    out = np.full((len(xy), 2), INDEX_NONE, dtype=np.int64)
    if len(xy) < 5:
        return out
    tree = cKDTree(xy)
    center = (
        np.array([(image_shape[1] - 1) / 2, (image_shape[0] - 1) / 2]) if image_shape is not None else xy.mean(0)
    )
    seed = _seed_lattice(xy, tree, center)
    if seed is None:
        return out
    idx0, a0, b0 = seed
    where: dict[tuple[int, int], int] = {}
    taken = np.zeros(len(xy), dtype=bool)

    def assign(key: tuple[int, int], k: int) -> None:
        where[key] = k
        taken[k] = True

    def walk_row(j: int, row_step: float) -> None:
        """Extend row j both ways along its local lattice vector from the dots it already has."""
        for direction in (1, -1):
            frontier = sorted((i for (i, jj) in where if jj == j), reverse=direction == 1)
            todo = list(frontier)
            while todo:
                i = todo.pop()
                p = xy[where[(i, j)]]
                back = where.get((i - direction, j))
                vec = p - xy[back] if back is not None else direction * a0
                for hop in (1, 2):
                    key = (i + hop * direction, j)
                    if key in where:
                        break
                    tol = tolerance * min(np.linalg.norm(vec), row_step)
                    dist, nb = tree.query(p + hop * vec)
                    if dist <= tol and not taken[nb]:
                        assign(key, int(nb))
                        todo.append(key[0])
                        break

    def next_row(j: int, direction: int, step: np.ndarray) -> tuple[int, np.ndarray] | None:
        """Index row j + direction by consensus of row j's dots; returns the count found and the mean step."""
        row = [(i, where[(i, j)]) for (i, jj) in list(where) if jj == j]
        along = np.array([0.0, 0.0])
        cols = sorted(i for i, _ in row)
        if len(cols) >= 2:
            along = (xy[where[(cols[-1], j)]] - xy[where[(cols[0], j)]]) / (cols[-1] - cols[0])
        a_hat = along / np.linalg.norm(along) if np.linalg.norm(along) > 0 else a0 / np.linalg.norm(a0)
        a_len = np.linalg.norm(along) if np.linalg.norm(along) > 0 else np.linalg.norm(a0)
        n_hat = np.array([-a_hat[1], a_hat[0]])
        if n_hat @ (direction * b0) < 0:
            n_hat = -n_hat
        proposals = []
        for i, k in row:
            p = xy[k]
            cand = tree.query_ball_point(p + 0.9 * step, r=1.6 * max(np.linalg.norm(step), 1.0))
            best = None
            for c in cand:
                if taken[c]:
                    continue
                o = xy[c] - p
                f, al = o @ n_hat, o @ a_hat
                if f <= 0.25 * np.linalg.norm(step) or abs(al - step @ a_hat) > 0.45 * a_len:
                    continue
                if best is None or f < best[0]:
                    best = (f, al, c)
            if best is not None:
                proposals.append((i, *best))
        if len(proposals) < 3:
            return None
        f_med = float(np.median([q[1] for q in proposals]))
        al_med = float(np.median([q[2] for q in proposals]))
        steps = []
        for i, f, al, c in proposals:
            if abs(f - f_med) <= tolerance * f_med and abs(al - al_med) <= tolerance * min(a_len, f_med):
                key = (i, j + direction)
                if key not in where and not taken[c]:
                    assign(key, int(c))
                    steps.append(xy[c] - xy[where[(i, j)]])
        if len(steps) < 3:
            return None
        return len(steps), np.mean(steps, axis=0)

    assign((0, 0), idx0)
    walk_row(0, float(np.linalg.norm(b0)))
    for direction in (1, -1):
        j, step = 0, direction * b0
        while True:
            found = next_row(j, direction, step)
            if found is None:
                break
            _, step = found
            j += direction
            walk_row(j, float(np.linalg.norm(step)))
    for (i, j), k in where.items():
        out[k] = (i, j)
    return out


"""Clips of a shipped real print (500 dpi) moved by a known slide and stretch, made without the scene simulator:
the print resampled to a pixel scale, smaller than the frame on a plain background, rendered supersampled and
integrated over each pixel (as a camera does: no interpolation phase bias in the truth)."""

from __future__ import annotations

import cv2
import numpy as np

from skinstretch.simulators.prints import print_path

NATIVE_PX_PER_MM = 500 / 25.4
SUPERSAMPLE = 4


def print_image(name: str = "afis_p1_2") -> np.ndarray:
    return cv2.imread(str(print_path(name)), cv2.IMREAD_GRAYSCALE).astype(np.float32)


def true_x(x, k: int, *, width: int, slide_px: float, stretch: float) -> np.ndarray:
    """Where the skin point at image x in frame 0 is in frame k (x only: the motion is along x)."""
    return width / 2 + (np.asarray(x, dtype=np.float64) - width / 2) * (1 + stretch * k) + slide_px * k


def print_frame(image: np.ndarray, k: int, *, px_per_mm: float, background: float, shape=(240, 320),
                slide_px: float = 0.5, stretch: float = 0.0005, noise: float = 2.0, seed: int = 0,
                contact: float | None = 0.8) -> np.ndarray:
    """Frame ``k``: the skin slid by ``slide_px`` and stretched by ``stretch`` per frame along x about the centre.
    ``contact``: the print shows inside an ellipse moving with the skin, this fraction of the frame's width and
    height, on ``background`` around it (None: the whole frame)."""
    h, w = shape
    u = SUPERSAMPLE
    yy, xx = np.mgrid[0 : h * u, 0 : w * u].astype(np.float64)
    xx, yy = (xx + 0.5) / u - 0.5, (yy + 0.5) / u - 0.5
    scale = px_per_mm / NATIVE_PX_PER_MM
    qx = (xx - w / 2 - slide_px * k) / (1 + stretch * k) + w / 2  # frame 0's skin point
    ph, pw = image.shape
    mx = ((qx - w / 2) / scale + pw / 2).astype(np.float32)
    my = ((yy - h / 2) / scale + ph / 2).astype(np.float32)
    big = cv2.remap(image, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=float(background))
    if contact is not None:
        inside = ((qx - w / 2) / (contact * w / 2)) ** 2 + ((yy - h / 2) / (contact * h / 2)) ** 2 <= 1.0
        big = np.where(inside, big, np.float32(background))
    img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    rng = np.random.default_rng(seed * 1000 + k)
    return np.clip(np.round(img + rng.normal(0, noise, img.shape)), 0, 255).astype(np.uint8)

"""Illumination compensation (seed 3.5): normalise the brightness of valleys across the field of view.

The diffuser does not light the prism uniformly, so the same valley is brighter in some places than in others.
The seed builds an illumination map ``IM`` as the per-pixel maximum over a sequence (valleys and background are the
brightest things a pixel ever sees), low-pass filters it, and rescales every frame by ``255 / LPF(IM)`` (eq. 3.6,
3.7). The map is computed once per sequence; applying it is one multiply per pixel.
"""

from __future__ import annotations

from typing import Iterable

import cv2
import numpy as np

from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError

__all__ = ["illumination_map", "compensate_illumination", "illumination_gain", "apply_illumination_gain"]

#: Floor of the low-passed map, in grey levels: a pixel that never got brighter than this is treated as unlit,
#: so its gain stays bounded (at most 255 / 8 ~ 32) instead of amplifying sensor noise without limit.
_MIN_MAP_LEVEL = 8.0


def _check_frame(frame: np.ndarray, name: str = "frame") -> np.ndarray:
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim != 2:
        got = f"{getattr(frame, 'dtype', type(frame).__name__)} {getattr(frame, 'shape', '')}"
        raise InvalidInputError(f"{name} must be a 2-D uint8 image, got {got}")
    return frame


def illumination_map(
    frames: Iterable[np.ndarray],
    *,
    calibration: Calibration,
    lowpass_sigma_mm: float = 0.5,
) -> np.ndarray:
    """The low-passed illumination map of a sequence (seed eq. 3.6 followed by its low-pass filter).

    Parameters
    ----------
    frames : iterable of (H, W) uint8 arrays
        The frames of one sequence (at least one).
    calibration : Calibration
        Converts ``lowpass_sigma_mm`` to pixels.
    lowpass_sigma_mm : float, optional
        Standard deviation of the Gaussian low-pass filter, in mm. It must be wider than a ridge period
        (~0.43 mm) so that ridges that stayed in contact all along do not imprint on the map.

    Returns
    -------
    (H, W) float32 array
        ``LPF(max_i I_i)`` in grey levels, floored at 8 so that the gain stays bounded.

    Examples
    --------
    >>> import numpy as np
    >>> from skinstretch.processing.pixel_scale import Calibration
    >>> frames = [np.full((40, 50), 100, np.uint8), np.full((40, 50), 200, np.uint8)]
    >>> float(illumination_map(frames, calibration=Calibration(px_per_mm=20.0)).mean())
    200.0
    """
    if not np.isfinite(lowpass_sigma_mm) or lowpass_sigma_mm <= 0:
        raise InvalidInputError(f"lowpass_sigma_mm must be positive, got {lowpass_sigma_mm!r}")
    peak = None
    for k, frame in enumerate(frames):
        _check_frame(frame, f"frames[{k}]")
        if peak is None:
            peak = frame.copy()
        elif frame.shape != peak.shape:
            raise InvalidInputError(f"frames[{k}] has shape {frame.shape}, expected {peak.shape}")
        else:
            cv2.max(peak, frame, dst=peak)
    if peak is None:
        raise InsufficientDataError("illumination_map needs at least one frame, got none")
    sigma = calibration.px(lowpass_sigma_mm)
    smooth = cv2.GaussianBlur(peak.astype(np.float32), (0, 0), sigmaX=sigma, borderType=cv2.BORDER_REFLECT)
    np.maximum(smooth, _MIN_MAP_LEVEL, out=smooth)
    return smooth


def compensate_illumination(frame: np.ndarray, *, illumination: np.ndarray) -> np.ndarray:
    """Rescale ``frame`` by ``255 / illumination`` and clip at 255 (seed eq. 3.7).

    Parameters
    ----------
    frame : (H, W) uint8 array
    illumination : (H, W) float32 array
        The output of :func:`illumination_map` for the sequence ``frame`` belongs to.

    Returns
    -------
    (H, W) uint8 array
    """
    _check_frame(frame)
    if not isinstance(illumination, np.ndarray) or illumination.shape != frame.shape:
        raise InvalidInputError(
            f"illumination must be an array of the frame's shape {frame.shape}, "
            f"got {getattr(illumination, 'shape', type(illumination).__name__)}"
        )
    if not np.all(np.isfinite(illumination)) or illumination.min() <= 0:
        raise InvalidInputError("illumination must be finite and positive everywhere")
    out = cv2.divide(frame.astype(np.float32), illumination.astype(np.float32, copy=False), scale=255.0)
    return np.clip(out, 0, 255).round().astype(np.uint8)


def illumination_gain(illumination: np.ndarray) -> np.ndarray:
    """The per-pixel gain ``255 / illumination`` of seed eq. 3.7, computed once per sequence.

    Parameters
    ----------
    illumination : (H, W) float32 array
        The output of :func:`illumination_map`.

    Returns
    -------
    (H, W) float32 array
        For :func:`apply_illumination_gain`.
    """
    if not isinstance(illumination, np.ndarray) or illumination.ndim != 2:
        raise InvalidInputError(f"illumination must be a 2-D array, got {getattr(illumination, 'shape', illumination)!r}")
    if not np.all(np.isfinite(illumination)) or illumination.min() <= 0:
        raise InvalidInputError("illumination must be finite and positive everywhere")
    return (255.0 / illumination.astype(np.float32)).astype(np.float32)


def apply_illumination_gain(frame: np.ndarray, *, gain: np.ndarray) -> np.ndarray:
    """Seed eq. 3.7 with a precomputed gain: ``frame * gain`` rounded and clipped to [0, 255], one pass, uint8.

    Same result as :func:`compensate_illumination` up to the rounding of the last float bit (a pixel exactly
    half-way between two grey levels may land on the other one), about five times faster (no float frame).
    """
    _check_frame(frame)
    if not isinstance(gain, np.ndarray) or gain.shape != frame.shape or gain.dtype != np.float32:
        raise InvalidInputError(
            f"gain must be a float32 array of the frame's shape {frame.shape}, got "
            f"{getattr(gain, 'dtype', type(gain).__name__)} {getattr(gain, 'shape', '')}"
        )
    # cv2's saturating cast rounds to nearest and clips at 0 and 255, exactly the clip of eq. 3.7.
    return cv2.multiply(frame, gain, dtype=cv2.CV_8U)

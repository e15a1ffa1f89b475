"""Contactor command limits: the one function every command passes through before it reaches a wire.

The display touches a person. A request that is not a position (NaN, inf, complex, not a number, not 10 x 10) is
refused with :class:`~skinstretch.drivers.errors.InvalidTargetError` naming the first bad contactor: guessing what
the caller meant (holding the previous position, dropping an imaginary part) would move the skin in a way nobody
asked for. A finite request leaves the driver on the 0.5 um encoding grid, within +/-``range_um`` and within
``max_step_um`` of the previous command of the same contactor; every contactor that had to be moved further than
the grid rounding is marked in :attr:`LimitedCommand.clamped`.

>>> import numpy as np
>>> previous = np.zeros((10, 10))
>>> request = np.full((10, 10), 80.0); request[0, 0] = 3.2
>>> limited = limit_command(request, previous, range_um=50.0, max_step_um=10.0)
>>> float(limited.command_um[0, 1]), float(limited.command_um[0, 0]), limited.clamped_range, limited.clamped_slew
(10.0, 3.0, True, True)
>>> int(limited.clamped.sum())  # every contactor but (0, 0), which was only rounded to the grid
99
>>> request[2, 3] = np.nan
>>> limit_command(request, previous)
Traceback (most recent call last):
...
skinstretch.drivers.errors.InvalidTargetError: requested_um: contactor (2, 3) is nan, not a position in um (1 such value)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skinstretch.drivers.errors import InvalidTargetError
from skinstretch.processing.errors import InvalidInputError

from .stress_protocol import COLS, POSITION_STEP_UM, RANGE_UM, ROWS


@dataclass(frozen=True)
class LimitedCommand:
    """A safe command and what had to be changed to make it safe."""

    command_um: np.ndarray  # (10, 10) float, on the 0.5 um grid
    clamped_range: bool  # some request was outside +/-range_um
    clamped_slew: bool  # some step was larger than max_step_um
    clamped: np.ndarray  # (10, 10) bool: contactors moved by more than the grid rounding (range or slew)

    @property
    def modified(self) -> bool:
        return self.clamped_range or self.clamped_slew


def validate_limits(*, range_um: float, max_step_um: float) -> tuple[float, float]:
    """Check the limits themselves and snap them down onto the encoding grid."""
    if not (np.isfinite(range_um) and POSITION_STEP_UM <= range_um <= RANGE_UM):
        raise InvalidInputError(f"range_um must be in {POSITION_STEP_UM}..{RANGE_UM} um, got {range_um!r}")
    if not (np.isfinite(max_step_um) and POSITION_STEP_UM <= max_step_um <= 2 * RANGE_UM):
        raise InvalidInputError(f"max_step_um must be in {POSITION_STEP_UM}..{2 * RANGE_UM} um, got {max_step_um!r}")
    grid = POSITION_STEP_UM
    return float(np.floor(range_um / grid) * grid), float(np.floor(max_step_um / grid) * grid)


def check_target(requested_um, *, name: str = "requested_um") -> np.ndarray:
    """``requested_um`` as a (10, 10) float array, or InvalidTargetError naming what is wrong and where.

    Accepted: real numbers (integer or floating dtypes, nested sequences of them), all finite. Refused: complex
    values (even with a zero imaginary part: a complex target is a bug upstream), booleans, strings, objects,
    another shape, NaN and infinities.
    """
    return _finite_real(requested_um, name=name, shape=(ROWS, COLS))


def check_movie(movie_um, *, name: str = "movie_um") -> np.ndarray:
    """A (frames, 10, 10) movie as a float array, refused like :func:`check_target` (naming frame and contactor)
    before a single frame is sent."""
    return _finite_real(movie_um, name=name, shape=(None, ROWS, COLS))


def _finite_real(value, *, name: str, shape: tuple) -> np.ndarray:
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as exc:  # ragged nesting
        raise InvalidTargetError(f"{name} must be an array of numbers: {exc}") from None
    wanted = "(frames, 10, 10) with frames >= 1" if shape[0] is None else str(shape)
    if raw.ndim != len(shape) or any(w is not None and g != w for g, w in zip(raw.shape, shape)) or raw.size == 0:
        raise InvalidTargetError(f"{name} must have shape {wanted}, got {raw.shape}")

    def where_of(mask: np.ndarray) -> tuple[int, ...]:
        return tuple(int(v) for v in np.argwhere(mask)[0])

    def place(where: tuple[int, ...]) -> str:
        return f"contactor {where}" if len(where) == 2 else f"frame {where[0]}, contactor {where[1:]}"

    if np.iscomplexobj(raw):
        imaginary = np.imag(raw) != 0
        where = where_of(imaginary) if imaginary.any() else (0,) * raw.ndim
        raise InvalidTargetError(f"{name} is complex ({raw.dtype}; {place(where)} = {raw[where]!r}): positions are "
                                 "real micrometres", contactor=where[-2:])
    if raw.dtype.kind not in "iuf":
        raise InvalidTargetError(f"{name} must hold real numbers, got dtype {raw.dtype}")
    out = raw.astype(float, copy=True)
    bad = ~np.isfinite(out)
    if bad.any():
        where = where_of(bad)
        n = int(bad.sum())
        raise InvalidTargetError(f"{name}: {place(where)} is {out[where]}, not a position in um "
                                 f"({n} such value{'s' if n > 1 else ''})", contactor=where[-2:])
    return out


def limit_command(requested_um, previous_um, *, range_um: float = RANGE_UM,
                  max_step_um: float = 10.0) -> LimitedCommand:
    """Clamp a requested (10, 10) frame to the range and the per-frame slew limit.

    Parameters
    ----------
    requested_um : array_like, shape (10, 10)
        What the caller wants, in micrometres: finite real numbers (see :func:`check_target`).
    previous_um : array_like, shape (10, 10)
        The last command sent (must itself be safe: finite, in range, on the grid).
    range_um : float, keyword-only
        Half range (<= 50 um, the STReSS travel).
    max_step_um : float, keyword-only
        Largest change of one contactor between two consecutive frames.

    Returns
    -------
    LimitedCommand
        ``command_um`` satisfies ``|c| <= range_um`` and ``|c - previous| <= max_step_um``, on the 0.5 um grid;
        ``clamped`` marks every contactor requested outside the range or beyond the slew limit, and everywhere
        else ``|c - request| <= 0.25 um`` (the grid rounding): a request is never altered silently.

    Raises
    ------
    InvalidTargetError
        The request is not a (10, 10) array of finite real numbers; the message names the first bad contactor.
    """
    range_um, max_step_um = validate_limits(range_um=range_um, max_step_um=max_step_um)
    request = check_target(requested_um)
    previous = np.asarray(previous_um, dtype=float)
    if (previous.shape != (ROWS, COLS) or not np.all(np.isfinite(previous))
            or np.any(np.abs(previous) > range_um)):
        raise InvalidInputError("previous_um must be a finite (10, 10) command within range")
    grid = POSITION_STEP_UM
    previous = np.rint(previous / grid) * grid  # already on the grid when it came from here

    out_of_range = np.abs(request) > range_um
    # range is a multiple of the grid, so rounding after the clip stays in range
    target = np.rint(np.clip(request, -range_um, range_um) / grid) * grid
    step = target - previous
    over_slew = np.abs(step) > max_step_um
    # the limited point lies between previous and target, both in range and on the grid
    command = previous + np.clip(step, -max_step_um, max_step_um)
    command = np.clip(command, -range_um, range_um)  # belt and braces against rounding
    clamped = out_of_range | over_slew
    return LimitedCommand(command, bool(out_of_range.any()), bool(over_slew.any()), clamped)


def rest_ramp(previous_um, *, max_step_um: float = 10.0) -> list[np.ndarray]:
    """The slew-limited frames that bring ``previous_um`` back to zero (last frame is all zeros)."""
    _, max_step_um = validate_limits(range_um=RANGE_UM, max_step_um=max_step_um)
    current = np.asarray(previous_um, dtype=float)
    frames = []
    while np.any(current != 0):
        current = limit_command(np.zeros((ROWS, COLS)), current, max_step_um=max_step_um).command_um
        frames.append(current)
    return frames

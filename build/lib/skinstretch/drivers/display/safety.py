"""Contactor command limits: the one function every command passes through before it reaches a wire.

The display touches a person. Whatever a caller asks (NaN, inf, huge values, wrong dtype), the command that
leaves the driver is on the 0.5 um encoding grid, within +/-``range_um`` and within ``max_step_um`` of the
previous command of the same contactor. Non-finite requests hold the previous position.

>>> import numpy as np
>>> previous = np.zeros((10, 10))
>>> request = np.full((10, 10), 80.0); request[0, 0] = np.nan
>>> limited = limit_command(request, previous, range_um=50.0, max_step_um=10.0)
>>> float(limited.command_um[0, 1]), float(limited.command_um[0, 0]), limited.clamped_range, limited.clamped_slew
(10.0, 0.0, True, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skinstretch.processing.errors import InvalidInputError

from .stress_protocol import COLS, POSITION_STEP_UM, RANGE_UM, ROWS


@dataclass(frozen=True)
class LimitedCommand:
    """A safe command and what had to be changed to make it safe."""

    command_um: np.ndarray  # (10, 10) float, on the 0.5 um grid
    clamped_range: bool  # some request was outside +/-range_um
    clamped_slew: bool  # some step was larger than max_step_um
    non_finite: int  # how many requests were NaN/inf (held at the previous command)

    @property
    def modified(self) -> bool:
        return self.clamped_range or self.clamped_slew or self.non_finite > 0


def validate_limits(*, range_um: float, max_step_um: float) -> tuple[float, float]:
    """Check the limits themselves and snap them down onto the encoding grid."""
    if not (np.isfinite(range_um) and POSITION_STEP_UM <= range_um <= RANGE_UM):
        raise InvalidInputError(f"range_um must be in {POSITION_STEP_UM}..{RANGE_UM} um, got {range_um!r}")
    if not (np.isfinite(max_step_um) and POSITION_STEP_UM <= max_step_um <= 2 * RANGE_UM):
        raise InvalidInputError(f"max_step_um must be in {POSITION_STEP_UM}..{2 * RANGE_UM} um, got {max_step_um!r}")
    grid = POSITION_STEP_UM
    return float(np.floor(range_um / grid) * grid), float(np.floor(max_step_um / grid) * grid)


def limit_command(requested_um, previous_um, *, range_um: float = RANGE_UM,
                  max_step_um: float = 10.0) -> LimitedCommand:
    """Clamp a requested (10, 10) frame to the range and the per-frame slew limit.

    Parameters
    ----------
    requested_um : array_like, shape (10, 10)
        What the caller wants, in micrometres. Anything numeric; NaN/inf hold the previous command.
    previous_um : array_like, shape (10, 10)
        The last command sent (must itself be safe: finite, in range, on the grid).
    range_um : float, keyword-only
        Half range (<= 50 um, the STReSS travel).
    max_step_um : float, keyword-only
        Largest change of one contactor between two consecutive frames.

    Returns
    -------
    LimitedCommand
        ``command_um`` satisfies ``|c| <= range_um`` and ``|c - previous| <= max_step_um``, on the 0.5 um grid.
    """
    range_um, max_step_um = validate_limits(range_um=range_um, max_step_um=max_step_um)
    try:
        request = np.array(requested_um, dtype=float, copy=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InvalidInputError(f"requested_um must be numeric, got {type(requested_um).__name__}") from exc
    if request.shape != (ROWS, COLS):
        raise InvalidInputError(f"requested_um must have shape (10, 10), got {request.shape}")
    previous = np.asarray(previous_um, dtype=float)
    if (previous.shape != (ROWS, COLS) or not np.all(np.isfinite(previous))
            or np.any(np.abs(previous) > range_um)):
        raise InvalidInputError("previous_um must be a finite (10, 10) command within range")
    grid = POSITION_STEP_UM
    previous = np.rint(previous / grid) * grid  # already on the grid when it came from here

    bad = ~np.isfinite(request)
    non_finite = int(bad.sum())
    request[bad] = previous[bad]
    clamped_range = bool(np.any(np.abs(request) > range_um))
    # range is a multiple of the grid, so rounding after the clip stays in range
    target = np.rint(np.clip(request, -range_um, range_um) / grid) * grid
    step = target - previous
    clamped_slew = bool(np.any(np.abs(step) > max_step_um))
    # the limited point lies between previous and target, both in range and on the grid
    command = previous + np.clip(step, -max_step_um, max_step_um)
    command = np.clip(command, -range_um, range_um)  # belt and braces against rounding
    return LimitedCommand(command, clamped_range, clamped_slew, non_finite)


def rest_ramp(previous_um, *, max_step_um: float = 10.0) -> list[np.ndarray]:
    """The slew-limited frames that bring ``previous_um`` back to zero (last frame is all zeros)."""
    _, max_step_um = validate_limits(range_um=RANGE_UM, max_step_um=max_step_um)
    current = np.asarray(previous_um, dtype=float)
    frames = []
    while np.any(current != 0):
        current = limit_command(np.zeros((ROWS, COLS)), current, max_step_um=max_step_um).command_um
        frames.append(current)
    return frames

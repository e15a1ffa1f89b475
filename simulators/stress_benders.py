"""The STReSS firmware twin's 10x10 piezo benders: first-order lag, play-operator hysteresis, seeded gain and sensor
offsets, and a deflection that drops under the finger's lateral load (bender and skin as two springs in series).
Integrated exactly between events (piecewise-constant targets). Used by :class:`~skinstretch.simulators.stress_firmware.StressFirmware`.
"""

from __future__ import annotations

import math

import numpy as np

from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import NonNegativeFloat, PositiveFloat, validated_dataclass

__all__ = ["BenderParameters", "BenderArray"]


@validated_dataclass
class BenderParameters:
    """Piezo bender model. Values are plausible for STReSS-class benders; no datasheet is public."""

    tau_s: PositiveFloat = 0.0004  # first-order lag
    hysteresis_um: NonNegativeFloat = 0.6  # play-operator half width
    gain_spread: NonNegativeFloat = 0.03  # seeded per-contactor gain 1 +/- spread (1 sigma)
    offset_spread_um: NonNegativeFloat = 1.0  # seeded position-sensor offsets (removed by ZERO)
    noise_um: NonNegativeFloat = 0.05  # position-sensor noise (1 sigma)
    bender_stiffness_n_per_mm: PositiveFloat = 0.5  # lateral stiffness of one bender tip
    rest_tau_s: PositiveFloat = 0.005  # soft return to rest


class BenderArray:
    """10x10 benders, integrated exactly between events (piecewise-constant targets)."""

    def __init__(self, *, params: BenderParameters = BenderParameters(), seed: int = 0, t0: float = 0.0) -> None:
        self.params = params
        rng = np.random.default_rng(seed)
        shape = (sp.ROWS, sp.COLS)
        self.gain = 1.0 + params.gain_spread * rng.standard_normal(shape)
        self.offset_um = params.offset_spread_um * rng.standard_normal(shape)
        self._noise = np.random.default_rng(seed + 1)
        self.load_n_per_mm = np.zeros(shape)
        self.target_um = np.zeros(shape)  # command in force (decays during rest)
        self.lag_um = np.zeros(shape)
        self.play_um = np.zeros(shape)
        self.resting = True
        self.t = float(t0)

    def set_load(self, stiffness_n_per_mm) -> None:
        """Finger load per contactor as a lateral skin stiffness (N/mm); a scalar applies to all."""
        k = np.broadcast_to(np.asarray(stiffness_n_per_mm, dtype=float), (sp.ROWS, sp.COLS)).copy()
        if not np.all(np.isfinite(k)) or np.any(k < 0):
            raise InvalidInputError("stiffness_n_per_mm must be finite and >= 0")
        self.load_n_per_mm = k

    def advance(self, t: float) -> None:
        dt = t - self.t
        if dt <= 0:
            return
        p = self.params
        e = math.exp(-dt / p.tau_s)
        if self.resting:
            # cascade of the rest ramp r(t) = r0 exp(-t/tr) and the bender lag: exact solution
            tr = p.rest_tau_s
            er = math.exp(-dt / tr)
            if abs(tr - p.tau_s) > 1e-12:
                self.lag_um = self.lag_um * e + self.target_um * tr / (tr - p.tau_s) * (er - e)
            else:
                self.lag_um = (self.lag_um + self.target_um * dt / tr) * e
            self.target_um = self.target_um * er
        else:
            self.lag_um = self.target_um + (self.lag_um - self.target_um) * e
        # the lag response between events is monotone, so the play operator at the end point is exact
        h = p.hysteresis_um
        self.play_um = np.clip(self.play_um, self.lag_um - h, self.lag_um + h)
        self.t = t

    def deflection_um(self) -> np.ndarray:
        """True tip deflection: bender and skin are springs in series."""
        kb = self.params.bender_stiffness_n_per_mm
        return self.gain * self.play_um * kb / (kb + self.load_n_per_mm)

    def sensor_um(self) -> np.ndarray:
        """What the position sensors read (offset included, noise seeded)."""
        noise = self.params.noise_um * self._noise.standard_normal((sp.ROWS, sp.COLS))
        return self.deflection_um() + self.offset_um + noise

    def command(self, target_um: np.ndarray) -> None:
        self.target_um = np.asarray(target_um, float).copy()
        self.resting = False

    def rest(self) -> None:
        self.resting = True


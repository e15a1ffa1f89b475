"""``stresssim://`` for :func:`serial.serial_for_url`: the STReSS firmware simulator (see simulators.stresssim)."""

from simulators.stresssim import StressSimSerial as Serial

__all__ = ["Serial"]

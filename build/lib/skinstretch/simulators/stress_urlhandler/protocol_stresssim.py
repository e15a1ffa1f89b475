"""``stresssim://`` for :func:`serial.serial_for_url`: the STReSS firmware simulator (see skinstretch.simulators.stress_links)."""

from skinstretch.simulators.stress_links import StressSimSerial as Serial

__all__ = ["Serial"]

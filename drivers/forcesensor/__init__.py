"""Force/torque sensors: the :class:`~drivers.forcesensor.base.ForceSensor` interface and the ATI Net F/T driver.

The simulated Net F/T box lives in :mod:`simulators.netft` (drivers never import simulators).
"""

from drivers.forcesensor.base import FORCE_SAMPLE_DTYPE, ForceSample, ForceSensor, ForceStats
from drivers.forcesensor.netft import NetFTSensor

__all__ = ["FORCE_SAMPLE_DTYPE", "ForceSample", "ForceSensor", "ForceStats", "NetFTSensor"]

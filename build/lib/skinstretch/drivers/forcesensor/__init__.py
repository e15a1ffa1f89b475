"""Force/torque sensors: the :class:`~skinstretch.drivers.forcesensor.base.ForceSensor` interface and the ATI Net F/T driver.

The simulated Net F/T box lives in :mod:`skinstretch.simulators.netft_box` (drivers never import simulators).
"""

from skinstretch.drivers.forcesensor.base import FORCE_SAMPLE_DTYPE, ForceSample, ForceSensor, ForceStats
from skinstretch.drivers.forcesensor.netft import NetFTSensor

__all__ = ["FORCE_SAMPLE_DTYPE", "ForceSample", "ForceSensor", "ForceStats", "NetFTSensor"]

"""skinstretch: fingertip skin-stretch measurement from FTIR fingerprint video, and playback on a STReSS display.

One installed namespace with four layers (``docs/python-api.md`` is the user's guide to the public API):

- :mod:`skinstretch.processing`: pure computation (extraction, tracking, strain, flow, display mapping);
- :mod:`skinstretch.drivers`: devices (camera, STReSS display, force sensor) and the session file;
- :mod:`skinstretch.simulators`: the fingertip scene simulator and a twin of every device;
- :mod:`skinstretch.experiments`: protocols, recording, analysis, playback, reports, the command line.

The names of the public API are imported lazily, so ``import skinstretch`` stays fast and importing a layer
(``skinstretch.processing``) never pulls in the layers above it.
"""

from __future__ import annotations

__version__ = "0.2.0"

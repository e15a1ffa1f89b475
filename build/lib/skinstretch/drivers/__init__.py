"""Device drivers (camera, STReSS tactile display, force/torque sensor) and the session file format.

Every device kind has one small abstract interface; each concrete device owns a transport and a pure protocol
codec. This package never imports :mod:`simulators`.
"""

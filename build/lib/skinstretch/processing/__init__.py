"""Pure computation for skinstretch: image processing, feature extraction, tracking and skin stretch.

Nothing in this package does file I/O, plotting, or imports ``drivers``, ``simulators`` or ``experiments``.
Parameters are given in physical units (mm, degrees, frames) and converted to pixels once, through a
:class:`skinstretch.processing.pixel_scale.Calibration`.
"""

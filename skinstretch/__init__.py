"""skinstretch: fingertip skin-stretch measurement from FTIR fingerprint video, and playback on a STReSS display.

One installed namespace with four layers (``docs/python-api.md`` is the user's guide to the public API):

- :mod:`skinstretch.processing`: pure computation (extraction, tracking, strain, flow, display mapping);
- :mod:`skinstretch.drivers`: devices (camera, STReSS display, force sensor) and the session file;
- :mod:`skinstretch.simulators`: the fingertip scene simulator and a twin of every device;
- :mod:`skinstretch.experiments`: protocols, recording, analysis, playback, reports, the command line.

The public API below is imported lazily (PEP 562), so ``import skinstretch`` stays fast and importing a layer
(``skinstretch.processing``) never pulls in the layers above it::

    import skinstretch as ss
    results = ss.analyze("session.h5", "out", method="features", params={"strain": {"spans": [1, 11]}})
    results.to_dataframe("trajectories"); results.profile; ss.save_figures(results, "out/figures")
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.2.0"

#: Public name -> (module, attribute).
_PUBLIC = {
    # sessions
    "open_session": ("skinstretch.drivers.session_file", "open_session"),
    "simulate_session": ("skinstretch.simulators.scene", "simulate_to_file"),
    # analysis
    "analyze": ("skinstretch.experiments.analysis", "analyze_session"),
    "analyze_frames": ("skinstretch.experiments.analysis", "analyze_frames"),
    "analyze_many": ("skinstretch.experiments.batch", "analyze_many"),
    "make_executor": ("skinstretch.experiments.analysis", "make_executor"),
    "AnalysisParams": ("skinstretch.experiments.analysis", "AnalysisParams"),
    "analysis_params": ("skinstretch.experiments.analysis", "analysis_params"),
    "ExtractionParams": ("skinstretch.processing.extraction", "ExtractionParams"),
    "TrackingParams": ("skinstretch.processing.tracking", "TrackingParams"),
    "SubpixelParams": ("skinstretch.processing.displacement_refinement", "SubpixelParams"),
    "FlowParams": ("skinstretch.processing.flow", "FlowParams"),
    "DisplayMappingParams": ("skinstretch.processing.display_mapping", "DisplayMappingParams"),
    "StrainParams": ("skinstretch.experiments.analysis", "StrainParams"),
    "GlassShadingParams": ("skinstretch.experiments.analysis", "GlassShadingParams"),
    "ExecutionParams": ("skinstretch.experiments.analysis", "ExecutionParams"),
    "Calibration": ("skinstretch.processing.pixel_scale", "Calibration"),
    # results
    "read_results": ("skinstretch.experiments.results_file", "read_results"),
    "Results": ("skinstretch.experiments.results_file", "Results"),
    "save_figures": ("skinstretch.experiments.analysis.result_figures", "save_figures"),
    "probe": ("skinstretch.experiments.probe", "probe"),
    # errors
    "SkinstretchError": ("skinstretch.processing.errors", "SkinstretchError"),
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        module, attr = _PUBLIC[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'skinstretch' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)

"""Compile every compiled kernel (numba) once, at set-up: ``python -m skinstretch.experiments.compile_kernels``.

numba compiles a kernel at its first call and keeps it in its disk cache (``__pycache__`` beside the source, see
:mod:`skinstretch.processing.jit`); without this step a fresh install's first analysis spends minutes compiling.
``./run`` calls it after installing and whenever the sources changed since (its stamp in ``.venv``). It renders short
scenes (flat and a ridge, whose glass-shading step has kernels of its own) and analyses them by both methods, one
process, serially: the kernels are compiled for the same argument types a real analysis passes them. The live view
compiles its own (:func:`skinstretch.experiments.viewer.live_analysis.warm_up`).
"""

from __future__ import annotations

import logging
import sys
import time

__all__ = ["compile_kernels"]

log = logging.getLogger(__name__)

#: Scenes and lengths that reach every stage: key frames and 11-frame spans on glass, the shading step over a ridge.
_CLIPS = (("flatL", 24), ("ridgeL", 40))


def compile_kernels() -> float:
    """Run the simulator, both analysis methods and the live view on short clips; returns the seconds it took."""
    from skinstretch.experiments.analysis.pipeline import analyze_frames, surface_kind  # noqa: PLC0415
    from skinstretch.experiments.viewer.live_analysis import warm_up  # noqa: PLC0415
    from skinstretch.simulators.scene import render_session  # noqa: PLC0415

    t0 = time.perf_counter()
    for scene, n in _CLIPS:
        session = render_session(scene, n_frames=n, seed=0)
        surface = surface_kind(session.metadata)
        for method in ("features", "flow"):
            analyze_frames(session.frames, calibration=session.calibration, method=method, surface=surface,
                           params={"execution": {"kind": "serial"}, "tracking": {"min_length_frames": 5}})
    warm_up()
    return time.perf_counter() - t0


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    log.info("compiling the analysis' kernels once (numba; a few minutes on 2 cores)")
    log.info("compiled in %.0f s", compile_kernels())
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Bench section ``simulator``: rendering speed per scene, and how true the truth is.

Columns
-------
init s        building the renderer (print, master image, constant maps)
frames/s      render_frame throughput (640x484 for the full-mode scenes), single process
truth s       computing the whole SessionTruth
map err px    max / RMS distance between the skin point the renderer samples at each pixel (node grid every 4 px,
              bilinear) and the exact inverse of the deformation, in camera pixels, at the middle frame
inverse px    max |forward(inverse(x)) - x| over the node grid, in pixels
warp RMS      noise-free frame k vs frame 0 warped by the truth displacement (grey levels, contact interior,
              uniform illumination; flat scenes only, where the light does not depend on the position)
"""

from __future__ import annotations

import time

import numpy as np
from scipy import ndimage as ndi

from experiments.bench import BenchOptions, BenchTable

SECTION = "simulator"
DESCRIPTION = "scene simulator: frames/s per scene and truth self-consistency"


def _warp_residual(scene, k: int) -> float:
    from simulators.scene import SceneRenderer

    camera = scene.camera.model_copy(update={"vignetting": 0.0, "illumination_tilt": 0.0})
    r = SceneRenderer(scene.model_copy(update={"n_frames": k + 1, "camera": camera}), seed=0, noise=0)
    t = r.truth()
    f0, fk = r.render_frame(0).astype(float), r.render_frame(k).astype(float)
    h, w = f0.shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    step = t.grid_x[1] - t.grid_x[0]
    X, Y = x.copy(), y.copy()
    for _ in range(8):
        X = x - ndi.map_coordinates(t.displacement[k, ..., 0].astype(float), [Y / step, X / step], order=3, mode="nearest")
        Y = y - ndi.map_coordinates(t.displacement[k, ..., 1].astype(float), [Y / step, X / step], order=3, mode="nearest")
    pred = ndi.map_coordinates(f0, [Y, X], order=3, mode="nearest")
    valid = ndi.map_coordinates(t.displacement_valid[k].astype(float), [Y / step, X / step], order=1) > 0.999
    inner = np.zeros_like(valid)
    inner[12:-12, 12:-12] = True
    core = ndi.binary_erosion(valid & inner, iterations=20)
    return float(np.sqrt(np.mean((pred - fk)[core] ** 2))) if core.any() else float("nan")


def _map_error(r, k: int) -> tuple[float, float]:
    maps = r._maps(k)
    h, w = maps.shape[:2]
    fx, fy = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    exact = r._deform(k).inverse(r.optics.image_to_surface(np.stack([fx, fy], -1)))
    mu = (exact[..., 0] - r._master_u0) / r._master_step
    ms = (exact[..., 1] - r._master_s0) / r._master_step
    err = np.hypot(maps[..., 0] - mu, maps[..., 1] - ms) / r.scene.camera.oversample  # master px -> camera px
    return float(err.max()), float(np.sqrt(np.mean(err**2)))


def _inverse_error(r, k: int) -> float:
    d = r._deform(k)
    x = r._nodes_surface.reshape(-1, 2)
    back = d.forward(d.inverse(x))
    return float(np.max(np.hypot(*(back - x).T)) * r.calibration.px_per_mm)


def run(options: BenchOptions) -> list[BenchTable]:
    from simulators.scene import SCENE_NAMES, SceneRenderer, load_scene

    names = list(options.scenes or (["flatL", "ridgeS"] if options.quick else SCENE_NAMES))
    n_frames = 30 if options.quick else 180
    rows = []
    for name in names:
        scene = load_scene(name).model_copy(update={"n_frames": n_frames})
        t0 = time.perf_counter()
        r = SceneRenderer(scene, seed=0)
        t_init = time.perf_counter() - t0
        t0 = time.perf_counter()
        for k in range(n_frames):
            r.render_frame(k)
        fps = n_frames / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        truth = r.truth()
        t_truth = time.perf_counter() - t0
        k_mid = n_frames // 2
        map_max, map_rms = _map_error(r, k_mid)
        inv = _inverse_error(r, k_mid)
        warp = _warp_residual(scene, min(n_frames - 1, 15 if options.quick else 60)) if scene.surface.kind == "flat" else float("nan")
        n_vis = int(truth.feature_visible[k_mid].sum())
        rows.append([name, f"{r.camera_mode.width}x{r.camera_mode.height}", n_frames, t_init, fps,
                     t_init + n_frames / fps + t_truth, t_truth, map_max, map_rms, inv, warp, n_vis])
    notes = [
        "goal: >= 100 frames/s at 640x484 (a 180-frame scene in < 2 s); the machine's 2 cores are shared, so "
        "throughput depends on load",
        "map err: geometric error of the rendered image against the exact field (the truth uses the exact field)",
        "warp RMS: at the quantisation + interpolation level (~1 grey level) when the truth is true",
    ]
    return [BenchTable(
        title=f"scene simulator ({n_frames} frames per scene, seed 0)",
        columns=["scene", "size", "frames", "init s", "frames/s", "total s", "truth s", "map err max px",
                 "map err rms px", "inverse px", "warp RMS grey", "visible features"],
        rows=rows,
        notes=notes,
    )]

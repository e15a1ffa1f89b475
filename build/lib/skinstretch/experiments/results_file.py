"""The results of ``skinstretch analyze``: ``OUTDIR/results.h5`` (everything) and ``OUTDIR/summary.json``.

The layout is documented in ``docs/results-format.md``; this module is the only code that reads or writes it.
Variable-length per-pair data (motion samples, triangulation edges and triangles) are stored as flat tables
with a ``pair`` column, indexing a per-span ``pairs`` table that carries each pair's status.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from skinstretch.drivers.errors import SessionFileError

FORMAT_NAME = "skinstretch-results"
FORMAT_VERSION = 1

PAIR_DTYPE = np.dtype(
    [("frame_a", np.int32), ("frame_b", np.int32), ("n_points", np.int32), ("status", "S96")]
)
MOTION_DTYPE = np.dtype(
    [("pair", np.int32), ("id", np.int64), ("x", np.float64), ("y", np.float64), ("dx", np.float64), ("dy", np.float64)]
)
EDGE_DTYPE = np.dtype(
    [
        ("pair", np.int32),
        ("id_a", np.int64),
        ("id_b", np.int64),
        ("xa", np.float64),
        ("ya", np.float64),
        ("xb", np.float64),
        ("yb", np.float64),
        ("length", np.float64),
        ("change", np.float64),
    ]
)
TRIANGLE_DTYPE = np.dtype(
    [
        ("pair", np.int32),
        ("id_a", np.int64),
        ("id_b", np.int64),
        ("id_c", np.int64),
        ("x0", np.float64),
        ("y0", np.float64),
        ("x1", np.float64),
        ("y1", np.float64),
        ("x2", np.float64),
        ("y2", np.float64),
        ("area", np.float64),
        ("change", np.float64),
        ("flipped", np.bool_),
    ]
)


@dataclass
class SpanStrain:
    """Triangulation strain of every frame pair at one span (seed 5.3.1)."""

    span: int
    pairs: np.ndarray  # PAIR_DTYPE
    edges: np.ndarray  # EDGE_DTYPE
    triangles: np.ndarray  # TRIANGLE_DTYPE


@dataclass
class Results:
    """Everything ``analyze`` produces for one session. Arrays absent for a method are ``None``."""

    method: str
    session_path: str
    n_frames: int
    image_shape: tuple[int, int]
    px_per_mm: float
    coordinates: str  # "image" or "rectified" (positions are mapping(mm) * px_per_mm)
    frame_flags: list[str]  # per frame: "" or why it gave nothing (extraction flags, flow status)
    motion_pairs: np.ndarray  # PAIR_DTYPE, consecutive pairs
    motion: np.ndarray  # MOTION_DTYPE
    fingertip_displacement: np.ndarray  # (N-1, 2)
    fingertip_valid: np.ndarray  # (N-1,)
    fingertip_position: np.ndarray  # (N, 2)
    window: dict[str, Any]  # x0, y0, x1, y1 or {"status": why none}
    window_centers: np.ndarray | None  # (N, 2)
    strain: dict[int, SpanStrain]
    profile_axis: int
    profile_position: np.ndarray
    profile_change: np.ndarray
    profile_valid: np.ndarray
    tactile_positions_um: np.ndarray | None
    tactile_reset: np.ndarray | None
    tactile_clipped: np.ndarray | None
    tactile_stretch_change: np.ndarray | None
    timing: dict[str, float]
    params: dict[str, Any]
    versions: dict[str, str]
    features: np.ndarray | None = None
    trajectories: dict[str, np.ndarray] | None = None
    flow_grid_x: np.ndarray | None = None
    flow_grid_y: np.ndarray | None = None
    flow_displacement: np.ndarray | None = None
    flow_valid: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def write_results(path: str | os.PathLike, r: Results) -> Path:
    """Write ``r`` to ``path`` (atomically: a temporary file renamed when complete)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".partial")
    with h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT_NAME
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["created_unix"] = time.time()
        f.attrs["method"] = r.method
        f.attrs["session_path"] = r.session_path
        f.attrs["n_frames"] = r.n_frames
        f.attrs["image_shape"] = np.asarray(r.image_shape, dtype=np.int64)
        f.attrs["px_per_mm"] = r.px_per_mm
        f.attrs["coordinates"] = r.coordinates
        f.attrs["timing_json"] = json.dumps(r.timing)
        f.attrs["params_json"] = json.dumps(r.params, default=str)
        f.attrs["versions_json"] = json.dumps(r.versions)
        f.attrs["window_json"] = json.dumps(r.window)
        f.attrs["extra_json"] = json.dumps(r.extra, default=str)
        f.create_dataset("frame_flags", data=np.array([s.encode() for s in r.frame_flags], dtype="S128"))
        f.create_dataset("motion_pairs", data=r.motion_pairs)
        f.create_dataset("motion", data=r.motion, compression="gzip", compression_opts=1)
        g = f.create_group("fingertip")
        g["displacement"] = r.fingertip_displacement
        g["valid"] = r.fingertip_valid
        g["position"] = r.fingertip_position
        if r.window_centers is not None:
            f["window_centers"] = r.window_centers
        sg = f.create_group("strain")
        for span, s in sorted(r.strain.items()):
            h = sg.create_group(f"span_{span}")
            h.attrs["span"] = span
            h.create_dataset("pairs", data=s.pairs)
            h.create_dataset("edges", data=s.edges, compression="gzip", compression_opts=1)
            h.create_dataset("triangles", data=s.triangles, compression="gzip", compression_opts=1)
        p = f.create_group("profile")
        p.attrs["axis"] = r.profile_axis
        p["position"] = r.profile_position
        p["change"] = r.profile_change
        p["valid"] = r.profile_valid
        if r.tactile_positions_um is not None:
            t = f.create_group("tactile_movie")
            t["positions_um"] = r.tactile_positions_um
            t["reset"] = r.tactile_reset
            t["clipped"] = r.tactile_clipped
            t["stretch_change"] = r.tactile_stretch_change
            t.attrs["motion_axis"] = r.profile_axis
        if r.features is not None:
            f.create_dataset("features", data=r.features, compression="gzip", compression_opts=1)
        if r.trajectories is not None:
            tg = f.create_group("trajectories")
            for name, arr in r.trajectories.items():
                tg.create_dataset(name, data=arr, compression="gzip", compression_opts=1)
        if r.flow_displacement is not None:
            fg = f.create_group("flow")
            fg["grid_x"] = r.flow_grid_x
            fg["grid_y"] = r.flow_grid_y
            fg.create_dataset("displacement", data=r.flow_displacement, compression="gzip", compression_opts=1)
            fg.create_dataset("valid", data=r.flow_valid, compression="gzip", compression_opts=1)
    os.replace(tmp, path)
    return path


def read_results(path: str | os.PathLike) -> Results:
    """Read a results file, or raise SessionFileError saying why it cannot be read."""
    path = Path(path)
    if path.is_dir():
        path = path / "results.h5"
    if not path.exists():
        raise SessionFileError(f"{path}: no such results file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise SessionFileError(f"{path}: HDF5 file cannot be opened, truncated or corrupt ({exc})") from None
    with f:
        fmt = f.attrs.get("format")
        fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
        if fmt != FORMAT_NAME:
            raise SessionFileError(f"{path}: not a skinstretch results file (format attribute {fmt!r})")
        if int(f.attrs.get("format_version", -1)) != FORMAT_VERSION:
            raise SessionFileError(f"{path}: results format version {f.attrs.get('format_version')} is not supported")
        try:
            strain = {}
            for name in f["strain"]:
                h = f["strain"][name]
                span = int(h.attrs["span"])
                strain[span] = SpanStrain(span, h["pairs"][()], h["edges"][()], h["triangles"][()])
            tm = f.get("tactile_movie")
            fg = f.get("flow")
            tg = f.get("trajectories")
            return Results(
                method=str(f.attrs["method"]),
                session_path=str(f.attrs["session_path"]),
                n_frames=int(f.attrs["n_frames"]),
                image_shape=tuple(int(v) for v in f.attrs["image_shape"]),
                px_per_mm=float(f.attrs["px_per_mm"]),
                coordinates=str(f.attrs["coordinates"]),
                frame_flags=[s.decode() for s in f["frame_flags"][()]],
                motion_pairs=f["motion_pairs"][()],
                motion=f["motion"][()],
                fingertip_displacement=f["fingertip/displacement"][()],
                fingertip_valid=f["fingertip/valid"][()],
                fingertip_position=f["fingertip/position"][()],
                window=json.loads(str(f.attrs["window_json"])),
                window_centers=f["window_centers"][()] if "window_centers" in f else None,
                strain=strain,
                profile_axis=int(f["profile"].attrs["axis"]),
                profile_position=f["profile/position"][()],
                profile_change=f["profile/change"][()],
                profile_valid=f["profile/valid"][()],
                tactile_positions_um=tm["positions_um"][()] if tm is not None else None,
                tactile_reset=tm["reset"][()] if tm is not None else None,
                tactile_clipped=tm["clipped"][()] if tm is not None else None,
                tactile_stretch_change=tm["stretch_change"][()] if tm is not None else None,
                timing=json.loads(str(f.attrs["timing_json"])),
                params=json.loads(str(f.attrs["params_json"])),
                versions=json.loads(str(f.attrs["versions_json"])),
                features=f["features"][()] if "features" in f else None,
                trajectories={k: tg[k][()] for k in tg} if tg is not None else None,
                flow_grid_x=fg["grid_x"][()] if fg is not None else None,
                flow_grid_y=fg["grid_y"][()] if fg is not None else None,
                flow_displacement=fg["displacement"][()] if fg is not None else None,
                flow_valid=fg["valid"][()] if fg is not None else None,
                extra=json.loads(str(f.attrs.get("extra_json", "{}"))),
            )
        except (KeyError, ValueError, TypeError, OSError) as exc:
            raise SessionFileError(f"{path}: results file is missing or has a damaged part ({exc})") from None

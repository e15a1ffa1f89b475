"""``skinstretch play MOVIE [--display URL] [--closed-loop]``: play a tactile movie on a STReSS display.

MOVIE is an analysed results directory (its tactile movie, seed 5.4), a ``.npy`` (T, 10, 10) array in micrometres
or an ``.h5`` with a ``movie`` dataset. Without ``--display`` the movie plays on the simulated display;
``--display 'stresssim://NAME?faults=stall_after:300'`` plays it on the simulated display with fault switches
(faults: drop, corrupt, stall_after, vanish_after; also baud, seed, load in N/mm). The output file is checked
before the display is opened, so a recording is never played and then lost.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Callable


def _finite(text: str) -> float:
    """An argparse type: a finite number (NaN and infinities are refused with the value named)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def _positive(text: str) -> float:
    """An argparse type: a finite number above 0."""
    value = _finite(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be greater than 0, got {text}")
    return value


def _movie_setting(field: str) -> Callable[[str], float]:
    """An argparse type: a number a protocol's movie accepts as ``field``: the same limits as
    :class:`~skinstretch.experiments.protocol.MovieSpec` (the display's rate range, a positive gain, a force
    ceiling up to its maximum)."""

    def parse(text: str) -> float:
        from pydantic import ValidationError  # noqa: PLC0415

        from skinstretch.experiments.protocol import MovieSpec  # noqa: PLC0415 - keeps `skinstretch --help` fast

        value = _finite(text)
        try:
            MovieSpec.model_validate({field: value})
        except ValidationError as exc:
            limit = exc.errors()[0]["msg"].removeprefix("Input should be ")
            raise argparse.ArgumentTypeError(f"must be {limit}, got {text}") from None
        return value

    return parse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("play", help="play a tactile movie on the STReSS display (closed loop with --closed-loop)",
                       description=__doc__.split("\n\n", 1)[1])
    p.add_argument("movie", type=Path, help="results directory, .npy or .h5 movie")
    p.add_argument("--display", default=None,
                   help="serial port or pyserial URL of the display, e.g. /dev/ttyUSB0 or "
                   "'stresssim://lab?faults=stall_after:300' (default: a simulated display)")
    p.add_argument("--closed-loop", action="store_true", help="correct each contactor from its measured position")
    p.add_argument("--compare", action="store_true", help="play open loop then closed loop and compare")
    p.add_argument("--rate", type=_movie_setting("rate_hz"), default=700.0,
                   help="display frame rate, 1..700 Hz (default 700)")
    p.add_argument("--movie-rate", type=_positive, default=None,
                   help="frame rate of the movie, Hz (default: the camera rate of its session, else the --rate)")
    p.add_argument("--gain", type=_movie_setting("gain"), default=1.0,
                   help="scale of the contactor positions, in (0, 100] (default 1)")
    p.add_argument("--peak-um", type=_positive, default=30.0,
                   help="scale the movie down to this peak excursion, um (default 30)")
    p.add_argument("--force-ceiling", type=_movie_setting("force_ceiling_n"), default=5.0,
                   help="stop above this normal force, in (0, 50] N (default 5)")
    p.add_argument("--no-force", action="store_true", help="play without the force sensor")
    p.add_argument("-o", "--output", type=Path, default=None, help="session file recording the playback (.h5)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing -o file (refused without it)")
    p.set_defaults(func=run)


def _outputs(args: argparse.Namespace, loops: list[bool]) -> list[Path | None]:
    """The playback recording of each loop (None without -o), each checked writable and new."""
    from skinstretch.experiments.output_paths import REPLACE_IT, check_output_file  # noqa: PLC0415

    if args.output is None:
        return [None] * len(loops)
    if len(loops) == 1:
        paths = [args.output]
    else:
        paths = [args.output.with_name(f"{args.output.stem}-{'closed' if closed else 'open'}"
                                       f"{args.output.suffix or '.h5'}") for closed in loops]
    return [check_output_file(p, overwrite=args.overwrite, remedy=REPLACE_IT) for p in paths]


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.playback import fit_movie, load_movie, play_movie, resample_movie  # noqa: PLC0415
    from skinstretch.experiments.protocol import DeviceSpec, Rig  # noqa: PLC0415
    from skinstretch.experiments.rig import RigDevices  # noqa: PLC0415

    loops = [False, True] if args.compare else [args.closed_loop]
    outputs = _outputs(args, loops)  # before the display moves: a recording that cannot be written is refused
    movie, rate = load_movie(args.movie)
    movie, scale = fit_movie(movie * args.gain, peak_um=args.peak_um)
    source_rate = args.movie_rate if args.movie_rate is not None else rate or args.rate
    movie = resample_movie(movie, from_hz=source_rate, to_hz=args.rate)
    display = DeviceSpec(kind="sim") if args.display is None else DeviceSpec(kind="stress", url=args.display)
    rig = Rig(name="play", display=display, force=DeviceSpec(kind="none" if args.no_force else "sim"))
    devices = RigDevices(rig)
    print(f"movie {args.movie}: {movie.shape[0]} frames at {args.rate:g} Hz (from {source_rate:g} Hz, scale "
          f"{scale * args.gain:.3g}), display {devices.describe()['display']}")
    results = []
    try:
        for closed, path in zip(loops, outputs):
            results.append(play_movie(devices.display_device(), movie, rate_hz=args.rate, closed_loop=closed,
                                      force=devices.force, force_ceiling_n=args.force_ceiling, path=path,
                                      overwrite=args.overwrite,
                                      settle_frames=min(150, movie.shape[0] // 4), progress=print,
                                      metadata={"movie": str(args.movie)}))
    finally:
        devices.close()
    if len(results) == 2 and results[1].rms_error_um > 0 and math.isfinite(results[0].rms_error_um):
        print(f"closed loop cuts the RMS error {results[0].rms_error_um / results[1].rms_error_um:.1f} times")
    return 0 if all(r.complete for r in results) else 3

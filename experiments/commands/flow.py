"""``skinstretch flow IMAGE_A IMAGE_B -o FIELD.npz``: the dense displacement field between two images, for users who
just want one (no session file, no analysis).

The field is our dense flow (:class:`skinstretch.processing.flow.DenseFlow`) interpolated to every pixel:
``FIELD.npz`` holds float32 arrays ``u`` and ``v`` (pixels, the images' shape; ``u`` along x, the columns, ``v``
along y), NaN where nothing was measured (outside the grid of windows that fit in the image, and next to a node
that is out of contact or was rejected), and the settings used (``window_px``, ``grid_step_px``, ``px_per_mm``).
The resolution knob is the window: ``--window-px`` (or ``--window-mm`` with ``--px-per-mm``); smaller resolves
shorter features with more noise (``skinstretch bench --only star`` prints the curve).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from skinstretch.processing.errors import InsufficientDataError, InvalidInputError

#: The rig's full field: 640 px over 10.3 mm (FACTS).
DEFAULT_PX_PER_MM = 640 / 10.3


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "flow",
        help="dense displacement field between two images, written as u, v arrays (.npz)",
        description="Measure the displacement from IMAGE_A to IMAGE_B with skinstretch's dense flow and write it to "
        "an .npz file: float32 arrays u (x, columns) and v (y, rows) in pixels, the images' shape, NaN where "
        "nothing was measured.",
    )
    p.add_argument("image_a", type=Path, help="first image (PNG, TIFF, ...; grey or colour, 8 or 16 bit)")
    p.add_argument("image_b", type=Path, help="second image, same size")
    p.add_argument("-o", "--output", type=Path, required=True, help="field file to write (.npz)")
    p.add_argument("--window-px", type=int, default=None,
                   help="registration window in pixels (an even number is rounded up to odd; overrides --window-mm): "
                        "the resolution knob, smaller resolves shorter features with more noise")
    p.add_argument("--window-mm", type=float, default=None, help="registration window in mm (default 0.8)")
    p.add_argument("--px-per-mm", type=float, default=DEFAULT_PX_PER_MM,
                   help=f"image scale, for the settings given in mm (default {DEFAULT_PX_PER_MM:.2f}, the rig's full "
                        "field of 640 px over 10.3 mm)")
    p.add_argument("--fingerprint-gate", action="store_true",
                   help="refuse images without fingerprint texture in contact, as the analysis does (default: any "
                        "texture, e.g. a DIC speckle, is registered)")
    p.add_argument("--no-adaptive", action="store_true",
                   help="uniform regularization (default: weakened where the images ask for more detail)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=run)


def read_grey(path: Path) -> np.ndarray:
    """An image file as a grey image, 8 or 16 bit as stored (colour to luminance)."""
    import cv2  # noqa: PLC0415

    if not path.is_file():
        raise InvalidInputError(f"{path}: no such image file")
    img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InvalidInputError(f"{path}: not an image OpenCV can read")
    if img.dtype not in (np.uint8, np.uint16):
        raise InvalidInputError(f"{path}: {img.dtype} images are not supported (8 or 16 bit integers)")
    return img


def to_8bit_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two grey images as 8 bit for the flow. Two 8-bit images pass as they are; otherwise (16 bit, often 10 or 12
    bit of data; an 8-bit image beside a 16-bit one counts as its top byte) both are mapped by the same linear
    scale from their common grey-level range to 0-255, so a 12-bit camera's images keep their contrast (a fixed
    1/257 would leave 16 grey levels) and brightness constancy holds between them."""
    if a.dtype == np.uint8 and b.dtype == np.uint8:
        return a, b
    a, b = (img.astype(np.float64) * (257.0 if img.dtype == np.uint8 else 1.0) for img in (a, b))
    lo = min(float(a.min()), float(b.min()))
    hi = max(float(a.max()), float(b.max()))
    scale = 255.0 / max(hi - lo, 1.0)
    return tuple(np.round((img - lo) * scale).astype(np.uint8) for img in (a, b))


def run(args: argparse.Namespace) -> int:
    from skinstretch.experiments.output_paths import REPLACE_IT, check_output_file  # noqa: PLC0415
    from skinstretch.processing.flow import DenseFlow, FlowParams  # noqa: PLC0415
    from skinstretch.processing.pixel_scale import Calibration  # noqa: PLC0415

    if not (np.isfinite(args.px_per_mm) and args.px_per_mm > 0):
        raise InvalidInputError(f"--px-per-mm must be positive, got {args.px_per_mm}")
    a, b = read_grey(args.image_a), read_grey(args.image_b)
    check_output_file(args.output, overwrite=args.overwrite, remedy=REPLACE_IT)
    if a.shape != b.shape:
        raise InvalidInputError(f"the images differ in size: {a.shape[1]} x {a.shape[0]} and {b.shape[1]} x {b.shape[0]}")
    a, b = to_8bit_pair(a, b)
    options: dict = {"adaptive": not args.no_adaptive, "texture_gate": args.fingerprint_gate}
    if args.window_mm is not None:
        options["window_mm"] = args.window_mm
    if args.window_px is not None:
        options["window_px"] = args.window_px + (1 - args.window_px % 2)  # windows are centred: odd
    try:
        params = FlowParams(**options)
    except InvalidInputError as exc:  # a bad value is named by the flag that gave it
        text = str(exc)
        for field, flag in (("window_px", "--window-px"), ("window_mm", "--window-mm")):
            text = text.replace(f"FlowParams.{field}:", f"{flag}:")
        raise InvalidInputError(text) from None
    flow = DenseFlow(calibration=Calibration(px_per_mm=float(args.px_per_mm)), params=params)
    t0 = time.perf_counter()
    field = flow.compute(a, b)
    seconds = time.perf_counter() - t0
    if not field.valid.any():
        raise InsufficientDataError(f"no displacement measured between {args.image_a} and {args.image_b}: "
                                    f"{field.status} (no texture in any {flow.window_px} px window?)")
    u, v = field.dense(a.shape)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with open(args.output, "wb") as fh:  # np.savez would add .npz to a name without it
        np.savez_compressed(fh, u=u, v=v, window_px=np.int64(flow.window_px), grid_step_px=np.int64(flow.grid_step_px),
                            px_per_mm=np.float64(args.px_per_mm))
    ok = np.isfinite(u)
    print(f"wrote {args.output}: u, v over {100 * ok.mean():.0f} % of the pixels, median displacement "
          f"({np.median(u[ok]):.3f}, {np.median(v[ok]):.3f}) px, window {flow.window_px} px, grid "
          f"{flow.grid_step_px} px, {seconds:.2f} s", file=sys.stderr)
    return 0

"""``skinstretch evaluate OUTDIR [--session SESSION.h5] [--json]``: score results against simulated truth."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from skinstretch.drivers.errors import SessionFileError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="compare analysis results with the ground truth of a simulated session",
        description="Score OUTDIR/results.h5 against the truth stored in the simulated session it was computed "
        "from (or --session): features, tracking, trajectories, strain, profile, timing. A session rendered with a "
        "real print as its texture (simulate --texture) has no feature truth: its features are not scored, the "
        "rest is.",
    )
    p.add_argument("outdir", type=Path, help="directory written by skinstretch analyze (or its results.h5)")
    p.add_argument("--session", type=Path, default=None, help="simulated session (default: the one analysed)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=run)


def _clean(v: Any) -> Any:
    """JSON has no NaN: undefined numbers become null."""
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if hasattr(v, "item"):
        return _clean(v.item())
    return v


def evaluate(outdir: Path, session: Path | None = None) -> dict[str, Any]:
    """The evaluation dictionary (see ``skinstretch evaluate --help``)."""
    from skinstretch.drivers.session_file import open_session  # noqa: PLC0415
    from skinstretch.experiments.evaluation.tracking import evaluate_tracking  # noqa: PLC0415
    from skinstretch.experiments.evaluation.trajectories import (  # noqa: PLC0415
        evaluate_trajectories,
        feature_truth_known,
    )
    from skinstretch.experiments.results_file import read_results  # noqa: PLC0415

    r = read_results(outdir)
    spath = Path(session) if session is not None else Path(r.session_path)
    with open_session(spath) as s:
        if not s.has_truth:
            raise SessionFileError(f"{spath}: session has no ground truth (only simulated sessions can be evaluated)")
        truth = s.truth
    out: dict[str, Any] = {"session": str(spath), "method": r.method}
    out["features"] = None
    known, why = feature_truth_known(truth)
    if not known:
        out["features_not_scored"] = why
    elif r.features is not None:
        try:
            from skinstretch.experiments.evaluation.features import evaluate_features  # noqa: PLC0415
        except ImportError:
            pass
        else:
            fe = evaluate_features(r.features, truth, px_per_mm=r.px_per_mm, image_shape=r.image_shape)
            out["features"] = {
                k: {m: v.get(m) for m in ("recall", "precision", "loc_rmse_px")}
                for k, v in fe.items()
                if isinstance(v, dict) and k in ("valley_ending", "valley_bifurcation", "pore")
            }
    if r.coordinates == "image":
        out.update(evaluate_tracking(r, truth))
        out["trajectories"] = evaluate_trajectories(r, truth)
    else:
        # Motion measured through a calibration mapping is in skin coordinates, while the simulator's truth is in
        # the image pixels of the optics it rendered with: comparing them would print meaningless errors.
        out.update({part: None for part in ("tracking", "trajectories", "strain", "profile")})
        out["timing"] = {"frames_per_s": float(r.timing.get("frames_per_s", math.nan))}
        out["not_evaluated"] = (
            f"motion, strain and profile are in {r.coordinates!r} coordinates (the session carries a calibration "
            "mapping) and the truth is in image pixels; analyse the session without its mapping to score them "
            "(the mapping itself is scored by `skinstretch bench --only calibration`)"
        )
    return _clean(out)


def run(args: argparse.Namespace) -> int:
    result = evaluate(args.outdir, args.session)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"{result['method']} results vs truth of {result['session']}")
    if result.get("not_evaluated"):
        print(f"  note: {result['not_evaluated']}")
    for part in ("features", "tracking", "trajectories", "strain", "profile", "timing"):
        value = result.get(part)
        if part == "features" and result.get("features_not_scored"):
            print(f"  features: NOT SCORED: {result['features_not_scored']}")
            continue
        if value is None:
            print(f"  {part}: n/a")
            continue
        for k, v in value.items():
            print(f"  {part}.{k}: {v}")
    return 0

"""``skinstretch import`` without ``--surface`` reads the prism surface from the frames (flat, ridge or valley;
:mod:`skinstretch.processing.surface_detection`), records it with its evidence, and ``--surface`` still wins."""

from __future__ import annotations

import numpy as np
import pytest

from skinstretch.cli import main
from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.bench.import_video import write_video
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.surface_detection import ContrastAccumulator, detect_surface


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """6-frame clips of flatL, ridgeL and valleyL (two seeds each) as lossless AVIs, with their pixel scale."""
    from skinstretch.simulators.scene import simulate_to_file

    d = tmp_path_factory.mktemp("surface_clips")
    out = {}
    for scene in ("flatL", "ridgeL", "valleyL"):
        for seed in (21, 22):
            with open_session(simulate_to_file(scene, d / f"{scene}-{seed}.h5", n_frames=6, seed=seed)) as s:
                frames, ppm = s.read_frames(), s.calibration.px_per_mm
            out[scene, seed] = write_video(d / f"{scene}-{seed}.avi", frames, rate=60), ppm
    return out


@pytest.mark.parametrize("seed", [21, 22])
@pytest.mark.parametrize("scene,kind", [("flatL", "flat"), ("ridgeL", "ridge"), ("valleyL", "valley")])
def test_a_clip_imported_without_surface_is_read_as_its_surface(clips, tmp_path, capsys, scene, kind, seed):
    video, ppm = clips[scene, seed]
    assert main(["import", str(video), "-o", str(tmp_path / "s.h5"), "--px-per-mm", str(ppm)]) == 0
    with open_session(tmp_path / "s.h5") as s:
        surface = s.metadata["surface"]
    assert surface["kind"] == kind and surface["decided_by"] == "detected from the frames"
    found = surface["detection"]
    assert found["kind"] == kind and found["frames"] == 6
    if kind == "flat":
        assert found["band_depth"] < 0.1 and found["crest_level"] is None
    else:  # a deep band straight across the field (the scenes' run along x); a ridge's middle keeps its contrast
        assert found["axis"] == "y" and found["band_depth"] > 0.35 and found["strip_depth"] > 0.8 * found["band_depth"]
        assert (found["crest_level"] > 0.8) if kind == "ridge" else (found["crest_level"] < 0.72)
    said = [line for line in capsys.readouterr().err.splitlines() if "surface" in line]  # the CLI's log lines
    assert len(said) == 1 and f"surface detected in {video}: {kind}: " in said[0], said


def test_the_surface_given_wins_and_the_analysis_uses_it(clips, tmp_path):
    video, ppm = clips["ridgeL", 21]
    assert main(["import", str(video), "-o", str(tmp_path / "s.h5"), "--px-per-mm", str(ppm), "--surface", "flat",
                 "-q"]) == 0
    with open_session(tmp_path / "s.h5") as s:
        assert s.metadata["surface"] == {"kind": "flat", "decided_by": "given"}


def test_a_transposed_clip_is_read_across_the_other_axis(clips):
    from skinstretch.drivers.frame_readers import open_frame_reader

    video, ppm = clips["valleyL", 22]
    with open_frame_reader(video) as reader:
        frames = np.stack([f.image for f in reader.frames()])
    found = detect_surface(np.transpose(frames, (0, 2, 1)), px_per_mm=ppm)
    assert (found.kind, found.axis) == ("valley", "x")


def test_what_cannot_be_read_says_why():
    flat_image = np.full((200, 200), 90, np.uint8)
    with pytest.raises(InsufficientDataError, match="at least 2 frames, got 1"):
        detect_surface([flat_image], px_per_mm=40)
    with pytest.raises(InsufficientDataError, match="no texture"):
        detect_surface([flat_image, flat_image], px_per_mm=40)
    with pytest.raises(InsufficientDataError, match=r"at least 2 mm \(84 px\) each way, got 50x200 px"):
        detect_surface(np.zeros((3, 200, 50)), px_per_mm=40)
    with pytest.raises(InvalidInputError, match="px_per_mm must be a positive number, got nan"):
        ContrastAccumulator(px_per_mm=float("nan"))
    acc = ContrastAccumulator(px_per_mm=40)
    acc.add(flat_image)
    with pytest.raises(InvalidInputError, match="frame is"):
        acc.add(np.zeros((100, 100)))

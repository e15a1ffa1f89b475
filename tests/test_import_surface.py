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


def _moved_print(**conditions):
    from skinstretch.simulators.moved_print import ClipConditions, PrintMotion, render_print_clip

    c = ClipConditions(**{"shape": (512, 512), "n_frames": 6, **conditions})
    return render_print_clip(c, PrintMotion(slide_px=(0.5, 0.0), stretch=(0.0005, 0.0))).frames


@pytest.mark.parametrize("px_per_mm,background,bright", [
    (15.0, "white", False), (19.685, "white", False), (30.0, "black", False), (20.0, "grey", False),
    (40.0, "black", True), (100.0, "white", False),
])
def test_a_flat_print_smaller_than_the_frame_reads_flat_on_any_background(px_per_mm, background, bright):
    """Issue 38: the plain background around a print (and the step at its edge) is no glass-fixed band."""
    found = detect_surface(_moved_print(px_per_mm=px_per_mm, background=background, bright_ridges=bright),
                           px_per_mm=px_per_mm)
    assert found.kind == "flat" and found.band_depth < 0.15, found.describe()
    if px_per_mm < 62:  # the 20 x 25 mm print leaves background in a 512-px frame
        assert found.textured_fraction < 0.9
    assert "% of the frame that holds print or skin, 6 frames" in found.describe()


def test_a_band_across_a_print_smaller_than_the_frame_is_still_read():
    """The texture mask keeps a glass-fixed band that takes 0.6 of the contrast: a valley on a grey background."""
    frames = _moved_print(px_per_mm=25.0, background="grey", noise_grey=0.0).astype(np.float64)
    band = 1 - 0.6 * np.exp(-0.5 * ((np.arange(512) - 280) / 12.0) ** 2)[:, None]  # along x, across y
    found = detect_surface(128 + (frames - 128) * band, px_per_mm=25.0)
    assert (found.kind, found.axis) == ("valley", "y") and abs(found.band_at_px - 280) < 5, found.describe()


def test_the_import_says_what_it_read_and_from_what(tmp_path, capsys):
    import cv2

    folder = tmp_path / "frames"
    folder.mkdir()
    for k, f in enumerate(_moved_print(px_per_mm=19.685, background="white")):
        cv2.imwrite(str(folder / f"f{k}.png"), f)
    assert main(["import", str(folder), "-o", str(tmp_path / "s.h5"), "--px-per-mm", "19.685", "--fps", "60"]) == 0
    with open_session(tmp_path / "s.h5") as s:
        assert s.metadata["surface"]["kind"] == "flat"
        assert 0.1 < s.metadata["surface"]["detection"]["textured_fraction"] < 0.5
    said = [line for line in capsys.readouterr().err.splitlines() if "surface" in line]
    assert len(said) == 1 and "flat: no glass-fixed band" in said[0] and "of the frame that holds print" in said[0]

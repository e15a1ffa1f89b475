"""The frame readers shared by the replay camera and ``skinstretch import``: videos (PyAV), TIFF stacks (tifffile)
and folders of images (natural order), their metadata, the grey rule, and one clear error per bad file."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st

from skinstretch.drivers.errors import FrameFileError
from skinstretch.drivers.frame_readers import ImageFolder, TiffStack, VideoFile, open_frame_reader, to_grey
from skinstretch.experiments.bench.import_video import write_video


def _frames(n=6, h=24, w=32, dtype=np.uint8, seed=3):
    return np.random.default_rng(seed).integers(0, np.iinfo(dtype).max, (n, h, w), dtype=dtype)


def test_lossless_avi_reads_back_exactly_with_its_times(tmp_path):
    frames = _frames()
    path = write_video(tmp_path / "v.avi", frames, rate=50)
    with VideoFile(path) as v:
        assert (v.n_frames, v.shape, v.dtype, v.fps) == (6, (24, 32), np.uint8, 50.0)
        got = list(v.frames())
        assert v.describe()["codec"] == "ffv1" and v.describe()["container"] == "avi"
        assert v.read(3).index == 3 and v.read(1).index == 1  # going back restarts
    np.testing.assert_array_equal(np.stack([f.image for f in got]), frames)
    np.testing.assert_allclose([f.time_s for f in got], np.arange(6) / 50.0)


def test_matroska_without_a_frame_count_and_a_16_bit_video(tmp_path):
    deep = _frames(4, dtype=np.uint16)
    path = write_video(tmp_path / "v.mkv", deep, pix_fmt="gray16le", in_format="gray16le")
    with open_frame_reader(path) as v:
        assert isinstance(v, VideoFile) and v.n_frames is None and v.dtype == np.uint16
        np.testing.assert_array_equal(np.stack([f.image for f in v.frames()]), deep)
        with pytest.raises(IndexError):
            v.read(4)


def test_colour_video_becomes_bt601_luma(tmp_path):
    rgb = np.random.default_rng(5).integers(0, 256, (3, 16, 16, 3), dtype=np.uint8)
    path = write_video(tmp_path / "c.mkv", rgb, pix_fmt="bgr0", in_format="rgb24")
    with VideoFile(path) as v:
        got = np.stack([f.image for f in v.frames()])
        assert v.colour and v.describe()["colour"] is True
    want = np.stack([cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in rgb])
    assert np.abs(got.astype(int) - want).max() <= 1


def test_damaged_videos_are_named(tmp_path):
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 4)
    with pytest.raises(FrameFileError, match="junk.mp4"):
        VideoFile(junk)
    good = write_video(tmp_path / "cut.avi", _frames(40, 48, 64))
    data = good.read_bytes()
    good.write_bytes(data[: len(data) // 2])  # the header still declares 40 frames
    with VideoFile(good) as v, pytest.raises(FrameFileError, match="cut.avi.*truncated"):
        list(v.frames())
    with pytest.raises(FrameFileError, match="no such video"):
        VideoFile(tmp_path / "missing.avi")


def test_imagej_stack_declares_rate_and_pixel_size(tmp_path):
    deep = _frames(5, dtype=np.uint16)
    path = tmp_path / "ij.tif"
    tifffile.imwrite(path, deep, imagej=True, resolution=(0.062, 0.062),
                     metadata={"unit": "um", "finterval": 1 / 120, "axes": "TYX"})
    with open_frame_reader(path) as t:
        assert isinstance(t, TiffStack) and t.n_frames == 5 and t.dtype == np.uint16
        assert t.fps == pytest.approx(120.0) and t.px_per_mm == pytest.approx(62.0)
        got = list(t.frames())
    np.testing.assert_array_equal(np.stack([f.image for f in got]), deep)
    assert got[2].time_s == pytest.approx(2 / 120)


def test_ome_tiff_declares_rate_pixel_size_and_plane_times(tmp_path):
    frames = _frames(4)
    path = tmp_path / "s.ome.tif"
    tifffile.imwrite(path, frames, ome=True, metadata={
        "axes": "TYX", "PhysicalSizeX": 20.0, "PhysicalSizeXUnit": "µm", "TimeIncrement": 25.0,
        "TimeIncrementUnit": "ms", "Plane": {"DeltaT": [10.0, 10.03, 10.05, 10.075], "DeltaTUnit": ["s"] * 4}})
    with TiffStack(path) as t:
        assert t.px_per_mm == pytest.approx(50.0) and t.fps == pytest.approx(40.0)
        assert [round(f.time_s, 6) for f in t.frames()] == [0.0, 0.03, 0.05, 0.075]
        assert t.describe()["metadata"] == "OME"


def test_plain_and_colour_stacks_and_the_axes_refused(tmp_path):
    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, _frames(4), photometric="minisblack")
    with TiffStack(plain) as t:
        assert t.fps is None and t.px_per_mm is None and math.isnan(t.read(1).time_s) and not t.colour
    rgb = np.random.default_rng(2).integers(0, 256, (4, 8, 10, 3), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "rgb.tif", rgb, photometric="rgb")
    with TiffStack(tmp_path / "rgb.tif") as t:
        np.testing.assert_array_equal(t.read(2).image, cv2.cvtColor(rgb[2], cv2.COLOR_RGB2GRAY))
        assert t.colour
    tifffile.imwrite(tmp_path / "tc.ome.tif", np.zeros((3, 2, 8, 10), np.uint8), ome=True, metadata={"axes": "TCYX"})
    with pytest.raises(FrameFileError, match="tc.ome.tif.*TCYX.*more than one stack axis"):
        TiffStack(tmp_path / "tc.ome.tif")
    (tmp_path / "bad.tif").write_bytes(b"II*\x00" + b"\xff" * 64)
    with pytest.raises(FrameFileError, match="bad.tif"):
        open_frame_reader(tmp_path / "bad.tif")


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(0, 2000), min_size=1, max_size=12, unique=True))
def test_folder_is_read_in_natural_order(tmp_path_factory, numbers):
    folder = tmp_path_factory.mktemp("frames")
    for n in numbers:  # each image holds its own number, so the order read is visible
        cv2.imwrite(str(folder / f"frame{n}.png"), np.full((4, 6), n % 256, np.uint8))
    with ImageFolder(folder) as f:
        assert [p.name for p in f.paths] == [f"frame{n}.png" for n in sorted(numbers)]
        assert [int(fr.image[0, 0]) for fr in f.frames()] == [n % 256 for n in sorted(numbers)]
        assert f.fps is None and f.px_per_mm is None and not f.colour


def test_folder_errors_name_the_file(tmp_path):
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"f{k}.png"), np.zeros((4, 6), np.uint8))
    cv2.imwrite(str(tmp_path / "f3.png"), np.zeros((5, 6), np.uint8))
    (tmp_path / "f4.png").write_bytes(b"\x89PNG broken")
    with ImageFolder(tmp_path) as f:
        with pytest.raises(FrameFileError, match="f3.png: 6x5 uint8 differs from the first image f0.png"):
            f.read(3)
        with pytest.raises(FrameFileError, match="f4.png: cannot be read"):
            f.read(4)
    with pytest.raises(FrameFileError, match="no images found"):
        ImageFolder(tmp_path / "f0.png").paths and ImageFolder(tmp_path / "nothing*.png")


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, 255), min_size=3, max_size=3), st.sampled_from([np.uint8, np.uint16, np.int32]))
def test_grey_rule_is_bt601_luma_in_either_channel_order(rgb, dtype):
    scale = 257 if dtype != np.uint8 else 1
    pixel = np.array(rgb, np.int64) * scale
    image = np.broadcast_to(pixel, (2, 3, 3)).astype(dtype)
    want = 0.299 * pixel[0] + 0.587 * pixel[1] + 0.114 * pixel[2]
    got_rgb = to_grey(image, channel_order="rgb", where="t")
    got_bgr = to_grey(np.ascontiguousarray(image[:, :, ::-1]), channel_order="bgr", where="t")
    np.testing.assert_array_equal(got_rgb, got_bgr)
    assert got_rgb.dtype == dtype and abs(float(got_rgb[0, 0]) - want) <= 0.5 + 1e-6 * want

"""The lossy codec's displacement error measured at import (:mod:`skinstretch.experiments.codec_error`): it reads the
file's own quality setting, grows as the quality falls, is nothing for lossless storage, and declines to guess."""

from __future__ import annotations

import numpy as np
import pytest

from skinstretch.experiments.bench.import_video import write_video
from skinstretch.experiments.codec_error import encoder_settings, measure_codec_error
from skinstretch.simulators.moved_print import ClipConditions, PrintMotion, render_print_clip

_PPM = 30.0


@pytest.fixture(scope="module")
def frames():
    clip = render_print_clip(ClipConditions(px_per_mm=_PPM, shape=(240, 320), n_frames=6),
                             PrintMotion(slide_px=(0.4, 0.1)))
    return clip.frames


def _x264(path, frames, crf):
    return write_video(path, frames, codec="libx264", pix_fmt="yuv420p", rate=60, options={"crf": str(crf)})


def _mpeg4(path, frames, quantiser):
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=60)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = "yuv420p"
        stream.codec_context.gop_size = 4
        stream.codec_context.qmin = stream.codec_context.qmax = quantiser
        for f in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="gray")))
        container.mux(stream.encode())
    return path


def test_the_quality_is_read_from_the_file(tmp_path, frames):
    x264 = encoder_settings(_x264(tmp_path / "a.mp4", frames, 23))
    assert (x264.encoder, x264.options, x264.quantizer, x264.bit_rate) == ("libx264", {"crf": "23.0"}, None, None)
    x265 = encoder_settings(write_video(tmp_path / "h.mp4", frames, codec="libx265", pix_fmt="yuv420p",
                                        options={"crf": "26", "x265-params": "log-level=error"}))
    assert (x265.encoder, x265.options) == ("libx265", {"crf": "26.0"})
    for q in (3, 8):  # no header: the quantiser that gives a key frame of the file its size
        mpeg4 = encoder_settings(_mpeg4(tmp_path / f"q{q}.avi", frames, q))
        assert mpeg4.encoder == "mpeg4" and mpeg4.quantizer == q and mpeg4.bit_rate is None, mpeg4
    assert "quantiser 8" in mpeg4.describe()


def test_the_error_grows_as_the_quality_falls_and_is_nothing_without_loss(tmp_path, frames):
    found = {crf: measure_codec_error(_x264(tmp_path / f"c{crf}.mp4", frames, crf), frames[3], px_per_mm=_PPM,
                                      workdir=tmp_path) for crf in (0, 18, 30)}
    assert found[0].sigma_px < 0.005  # x264's lossless mode
    assert 0.01 < found[18].sigma_px < found[30].sigma_px < 0.5
    for f in found.values():
        assert 0.0 <= f.independent_px <= f.sigma_px and f.shared_px**2 + f.independent_px**2 == pytest.approx(
            f.sigma_px**2)
    assert "libx264 at crf 18.0" in found[18].how and found[18].to_dict()["sigma_px"] == found[18].sigma_px
    assert not list(tmp_path.glob("codec-probe-*"))  # scratch files removed


def test_it_declines_rather_than_guesses(tmp_path, frames):
    video = _x264(tmp_path / "a.mp4", frames, 18)
    assert measure_codec_error(video, np.full((240, 320), 128, np.uint8), px_per_mm=_PPM, workdir=tmp_path) is None
    assert measure_codec_error(video, frames[0].astype(np.uint16), px_per_mm=_PPM, workdir=tmp_path) is None

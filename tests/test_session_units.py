"""Session files explain themselves: units on every dataset, named axes and columns, keyed codes; and sessions
written before those attributes existed (tests/data, written by the code of main 13774b0) still open and are
described the same way."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.session_file import (
    SESSION_DATASETS,
    SessionWriter,
    StreamSpec,
    open_session,
    write_session,
)
from skinstretch.processing.pixel_scale import Calibration
from tests.test_session_file import _frames, _truth

MODE = CAMERA_MODES["strip"]
CAL = Calibration(px_per_mm=62.0)
DATA = Path(__file__).parent / "data"


def _all_datasets(f: h5py.File) -> dict[str, h5py.Dataset]:
    out = {}
    f.visititems(lambda name, obj: out.__setitem__(name, obj) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_every_dataset_of_a_recorded_and_a_simulated_session_has_units(tmp_path):
    rec = tmp_path / "rec.h5"
    with SessionWriter(rec, camera_mode=MODE, calibration=CAL,
                       streams={"force": ((6,), "f8"), "display_state": ((10, 10), "f4"),
                                "grip": StreamSpec((2,), "f4", "N, N", ("finger",), ("thumb", "index"))}) as w:
        w.append_frame(_frames(1)[0], timestamp=1.0, frame_id=0)
        w.append_samples("force", 1.0, np.arange(6.0))
    sim = write_session(tmp_path / "sim.h5", _frames(4), timestamps=np.arange(4) / MODE.fps, camera_mode=MODE,
                        calibration=CAL, truth=_truth(4))
    for path in (rec, sim):
        with h5py.File(path, "r") as f:
            assert "x = column, y = row" in f.attrs["conventions"]
            datasets = _all_datasets(f)
            missing = [name for name, ds in datasets.items() if "units" not in ds.attrs]
            assert missing == [], f"{path.name}: datasets without units: {missing}"
            for name, ds in datasets.items():
                labels = [d.label for d in ds.dims]
                assert all(labels), f"{name} has unnamed axes {labels}"
                if "columns" in ds.attrs:
                    assert len(ds.attrs["columns"]) == ds.shape[-1], name
    with h5py.File(rec, "r") as f:
        force = f["streams/force/data"]
        assert list(force.attrs["columns"]) == ["fx", "fy", "fz", "tx", "ty", "tz"]
        assert force.attrs["units"] == "N, N, N, N m, N m, N m"
        assert [d.label for d in force.dims] == ["sample", "component"]
        assert [d.label for d in f["streams/display_state/data"].dims] == ["sample", "contactor_row",
                                                                           "contactor_column"]
        assert f["streams/display_state/data"].attrs["units"] == "um"
        assert list(f["status"].attrs["enum_names"]) == ["recording", "complete", "failed"]
        assert list(f["status"].attrs["enum_values"]) == [0, 1, 2]
        assert [d.label for d in f["frames"].dims] == ["frame", "y", "x"]
    with h5py.File(sim, "r") as f:
        kind = f["truth/feature_kind"]
        assert dict(zip(kind.attrs["enum_values"], kind.attrs["enum_names"])) == {
            0: "valley_ending", 1: "valley_bifurcation", 2: "pore"}
        assert list(f["truth/strain"].attrs["columns"]) == ["exx", "eyy", "exy"]
        assert f["truth/rigid"].attrs["units"] == "px, px, deg"
        assert [d.label for d in f["truth/displacement"].dims] == ["frame", "grid_y", "grid_x", "component"]
    with open_session(rec) as s:
        assert s.stream_info("grip").columns == ("thumb", "index")
        assert s.stream_info("force").units == "N, N, N, N m, N m, N m"
        assert s.dataset_info("status").enum == {0: "recording", 1: "complete", 2: "failed"}


def test_a_stream_of_unknown_meaning_says_so(tmp_path):
    with SessionWriter(tmp_path / "s.h5", camera_mode=MODE, calibration=CAL, streams={"custom": ((3,), "f4")}):
        pass
    with open_session(tmp_path / "s.h5") as s:
        assert s.stream_info("custom").units == "unspecified"


@pytest.mark.parametrize("name", ["session-v1-before-units.h5", "session-v1-simulated-before-units.h5"])
def test_sessions_written_before_units_still_open_and_are_described(name):
    with open_session(DATA / name) as s:
        assert s.complete and s.n_frames == 3 and s.shape == (3, 12, 16)
        assert s.read_frames().dtype == np.uint8
        # open_session reads without HDF5's file lock, and one process opens a file with one locking flag
        with h5py.File(DATA / name, "r", locking=False) as f:
            assert "units" not in f["frames"].attrs  # really the old layout
        assert s.dataset_info("frames") == SESSION_DATASETS["frames"]
        assert s.dataset_info("timestamps").units == "s"
        assert s.dataset_info("status").enum[1] == "complete"
        if s.stream_names():
            t, data = s.read_stream("force")
            assert data.shape == (2, 6) and data[0, 2] == pytest.approx(1.5)
            assert s.stream_info("force").columns == ("fx", "fy", "fz", "tx", "ty", "tz")
        if s.has_truth:
            assert list(s.truth.feature_kind) == [0, 2]
            assert s.dataset_info("truth/feature_kind").enum[2] == "pore"
            assert s.dataset_info("truth/rigid").columns == ("tx", "ty", "theta")

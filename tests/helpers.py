"""Helpers shared by several test modules (not tests themselves)."""

import time

import numpy as np

from skinstretch.processing.feature_table import make_features


def wait_until(predicate, timeout_s: float = 5.0, poll_s: float = 0.005) -> None:
    """Poll ``predicate`` until it holds: a bounded wait on another thread; AssertionError after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not reached within {timeout_s} s")
        time.sleep(poll_s)


def y_shaped_skeleton() -> np.ndarray:
    """A one-pixel skeleton (60x60 uint8) shaped like a Y lying on its side: a stem along +x from (5, 30) to
    (29, 30) and two diagonal arms to the upper and lower right, i.e. one bifurcation near (29, 30) and three
    endings."""
    sk = np.zeros((60, 60), np.uint8)
    sk[30, 5:30] = 1
    for i in range(1, 22):
        sk[30 - i, 29 + i] = 1
        sk[30 + i, 29 + i] = 1
    return sk


def sliding_feature_grid(k: int, rng_seed: int = 0) -> np.ndarray:
    """A grid of features sliding 1.5 px per frame; a few vanish for 2 frames (re-linked) or for good."""
    rng = np.random.default_rng(rng_seed)
    gx, gy = np.meshgrid(np.arange(20.0, 300.0, 23.0), np.arange(20.0, 200.0, 21.0))
    x, y = gx.ravel() + 1.5 * k, gy.ravel() + 0.4 * k
    kind = rng.integers(0, 3, x.size)
    keep = np.ones(x.size, bool)
    keep[(np.arange(x.size) % 7 == k % 7)] = False  # each feature missing one frame in 7
    keep[5:9] = k < 25  # some end for good
    return make_features(x[keep], y[keep], kind[keep], frame=k)


def assert_file_explains_itself(path) -> dict:
    """Every dataset of the HDF5 file ``path`` (a session, a results file, a playback log) carries a description,
    units in the shared vocabulary (one per column or field where they differ), named axes from the shared list,
    columns matching its last axis and the keys of its codes. Returns {dataset name: DatasetInfo}."""
    import json

    import h5py

    from skinstretch.drivers.file_vocabulary import AXES, CONVENTIONS, UNITS, read_dataset_info, unit_words

    infos = {}
    with h5py.File(path, "r") as f:
        assert f.attrs["conventions"] == CONVENTIONS, path
        datasets = []
        f.visititems(lambda name, obj: datasets.append(name) if isinstance(obj, h5py.Dataset) else None)
        assert datasets, path
        for name in datasets:
            ds = f[name]
            info = read_dataset_info(ds)
            assert info is not None, f"{path}: {name} has no units or description"
            assert info.description, f"{path}: {name} has no description"
            words = unit_words(info.units)
            assert set(words) <= UNITS, f"{path}: {name} units {info.units!r} outside the vocabulary"
            assert len(info.axes) == ds.ndim and set(info.axes) <= set(AXES), f"{path}: {name} axes {info.axes}"
            if ds.dtype.names:  # a table: a unit for every field, codes for every coded field
                assert info.units.startswith("{") and list(json.loads(info.units)) == list(ds.dtype.names), name
                for coded in {"status", "kind"} & set(ds.dtype.names):
                    assert info.column_codes[coded][0] in ("ok", "valley_ending"), (name, info.column_codes)
            elif info.columns:
                assert len(info.columns) == ds.shape[-1] and info.axes[-1] == "component", name
                assert len(words) in (1, len(info.columns)), (name, info.units)
            else:
                assert len(words) == 1 and "component" not in info.axes, (name, info.units, info.axes)
            if name.split("/")[-1] in ("status", "feature_kind"):
                assert info.enum and info.enum[0] in ("recording", "valley_ending"), (name, info.enum)
            infos[name] = info
    return infos

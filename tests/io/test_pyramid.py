"""build_pyramid: exact sums level by level, resumability, NGFF metadata, refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zarr

import chunkdic.io.levels as levels
import chunkdic.io.store as store
from chunkdic.errors import InputError
from chunkdic.io.pyramid import build_pyramid
from chunkdic.io.scan import open_scan
from chunkdic.io.scanwrite import write_scan


def block_sums(x: np.ndarray, s: int) -> np.ndarray:
    """Oracle: level ``s`` by NumPy reshape-sums in int64 (odd trailing voxels dropped)."""
    x = x.astype(np.int64)
    for _ in range(s):
        n = [k // 2 for k in x.shape]
        x = x[: 2 * n[0], : 2 * n[1], : 2 * n[2]].reshape(n[0], 2, n[1], 2, n[2], 2).sum(axis=(1, 3, 5))
    return x


@pytest.fixture()
def scan_path(tmp_path):
    x = np.random.default_rng(5).integers(0, 256, (45, 38, 27), dtype=np.uint8)
    p = tmp_path / "s.zarr"
    write_scan(p, x, chunks=8, voxel_size=(3.0, 2.0, 2.0), unit="mm")
    return p, x


def test_levels_equal_numpy_block_sums(scan_path):
    p, x = scan_path
    scan = build_pyramid(p, 4)
    assert scan.stored_levels() == [0, 1, 2, 3, 4]
    for s in range(5):
        got = scan.level(s).compute()
        assert got.shape == tuple(n // 2**s for n in x.shape)
        np.testing.assert_array_equal(got, block_sums(x, s))
    # 8-bit data: the 4^3 level fits uint16 (the paper's 14 bits), level 3 needs uint32
    assert scan.dtype(2) == np.uint16 and scan.dtype(3) == np.uint32
    assert int(scan.level(2).max().compute()) <= 255 * 64


def test_rerun_skips_complete_levels_and_rebuilds_incomplete(scan_path, monkeypatch):
    p, x = scan_path
    build_pyramid(p, 2)
    stamp = {s: (p / str(s) / "zarr.json").stat().st_mtime_ns for s in (1, 2)}
    calls = []
    original = levels.write_level
    monkeypatch.setattr("chunkdic.io.pyramid.write_level", lambda *a, **k: calls.append(a[1]) or original(*a, **k))
    build_pyramid(p, 2)
    assert calls == []
    assert all((p / str(s) / "zarr.json").stat().st_mtime_ns == stamp[s] for s in (1, 2))
    # level 1 interrupted (not complete): it and every level above are rebuilt
    meta = p / "1" / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"]["chunkdic"]["complete"] = False
    meta.write_text(json.dumps(doc))
    scan = build_pyramid(p, 3)
    assert calls == [1, 2, 3]
    for s in range(4):
        np.testing.assert_array_equal(scan.level(s).compute(), block_sums(x, s))
    calls.clear()
    build_pyramid(p, 3, overwrite=True)
    assert calls == [1, 2, 3]


def test_invalid_level_is_rebuilt(scan_path):
    p, x = scan_path
    build_pyramid(p, 1)
    g = zarr.open_group(str(p), mode="r+")
    del g["1"]
    g.create_array("1", shape=(3, 3, 3), dtype="uint8", attributes={"chunkdic": {"level": 1, "complete": True}})
    assert open_scan(str(p)).stored_levels() == [0]  # wrong shape/dtype: not trusted
    scan = build_pyramid(p, 1)
    np.testing.assert_array_equal(scan.level(1).compute(), block_sums(x, 1))


def test_interrupted_build_leaves_no_complete_level(scan_path, monkeypatch):
    p, x = scan_path
    calls = []

    def flaky(block, path, key, z0=0, block_info=None):
        calls.append(key)
        if key == "2" and len(calls) > 3:
            raise KeyboardInterrupt("killed")
        return write(block, path, key, z0, block_info=block_info)

    write = store._write_block
    monkeypatch.setattr(store, "_write_block", flaky)
    with pytest.raises(KeyboardInterrupt):
        build_pyramid(p, 3)
    g = zarr.open_group(str(p), mode="r")
    assert g["2"].attrs["chunkdic"]["complete"] is False
    assert "3" not in g
    assert open_scan(str(p)).stored_levels() == [0, 1]
    ms = g.attrs["ome"]["multiscales"][0]
    assert [d["path"] for d in ms["datasets"]] == ["0", "1"]
    monkeypatch.setattr(store, "_write_block", write)
    scan = build_pyramid(p, 3)
    assert scan.stored_levels() == [0, 1, 2, 3]
    np.testing.assert_array_equal(scan.level(3).compute(), block_sums(x, 3))


def test_ngff_after_pyramid(scan_path):
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    p, _ = scan_path
    build_pyramid(p, 3)
    node = list(Reader(parse_url(str(p)))())[0]
    assert len(node.data) == 4
    vs = np.array([3.0, 2.0, 2.0])
    for s, tr in enumerate(node.metadata["coordinateTransformations"]):
        t = {d["type"]: d for d in tr}
        np.testing.assert_allclose(t["scale"]["scale"], vs * 2**s)
        np.testing.assert_allclose(t["translation"]["translation"], vs * (2**s - 1) / 2)
    assert node.metadata["axes"][0]["unit"] == "millimeter"


def test_refusals(tmp_path, scan_path):
    p, _ = scan_path
    with pytest.raises(InputError, match="at most 4"):
        build_pyramid(p, 5)
    with pytest.raises(InputError, match="does not exist"):
        build_pyramid(tmp_path / "nope.zarr", 1)
    with pytest.raises(InputError, match=">= 1"):
        build_pyramid(p, 0)
    np.save(tmp_path / "v.npy", np.zeros((4, 4, 4)))
    with pytest.raises(InputError, match="ingest"):
        build_pyramid(tmp_path / "v.npy", 1)
    zarr.create_array(str(tmp_path / "arr.zarr"), shape=(4, 4, 4), dtype="uint8")
    with pytest.raises(InputError, match="ingest"):
        build_pyramid(tmp_path / "arr.zarr", 1)
    assert open_scan(str(p)).stored_levels() == [0]


def test_level0_window_and_mean_display_pyramid(scan_path, capsys):
    """Sum levels grow 8x per level: the scan's omero window is level 0's (from the coarsest
    level / 8^k) and SCAN/display holds sums / 8^s, one window fitting every level."""
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    from chunkdic.cli.app import main

    p, x = scan_path
    assert main(["pyramid", str(p), "--levels", "2", "--display"]) == 0
    capsys.readouterr()
    means = block_sums(x, 2) / 64.0  # level-0 means over 4^3 cubes
    lo, hi = np.percentile(means, [1, 99])
    attrs = json.loads((p / "zarr.json").read_text())["attributes"]
    window = attrs["ome"]["omero"]["channels"][0]["window"]
    assert (window["start"], window["end"]) == pytest.approx((lo, hi))
    assert (window["min"], window["max"]) == pytest.approx((means.min(), means.max()))
    assert x.min() <= window["start"] < window["end"] <= x.max()  # a level-0 window, not a sum's
    g = zarr.open_group(str(p / "display"), mode="r")
    assert sorted(g.array_keys()) == ["1", "2"]
    for s in (1, 2):
        assert g[str(s)].dtype == np.float32
        assert np.array_equal(g[str(s)][...], block_sums(x, s) / 8.0**s)  # exact
    node = list(Reader(parse_url(str(p / "display")))())[0]
    scan = list(Reader(parse_url(str(p)))())[0]
    assert node.metadata["coordinateTransformations"] == scan.metadata["coordinateTransformations"][1:]
    assert node.metadata["contrast_limits"] == [[window["start"], window["end"]]]
    assert open_scan(p).stored_levels() == [0, 1, 2]  # the subgroup is not a level
    build_pyramid(p, 2, overwrite=True)  # rebuilt sums: the stale display goes
    assert not (p / "display").exists()


def test_window_from_a_bounded_sample_read_by_tasks(tmp_path):
    """The one window helper: extremes exact, percentiles from the array's ``[::step]^3``
    grid of at most ``samples`` voxels (gathered chunk by chunk from tasks), channels apart,
    an all-NaN channel None."""
    from chunkdic.io.display import sample_step, windows

    rng = np.random.default_rng(3)
    x = rng.normal(size=(2, 30, 29, 31)).astype(np.float32)
    x[1] = np.nan
    zarr.create_array(str(tmp_path / "a.zarr"), data=x, chunks=(1, 8, 8, 8))
    step = sample_step(x.shape[1:], 1000)
    grid = x[0, ::step, ::step, ::step]
    assert grid.size <= 1000 < x[0, ::step - 1, ::step - 1, ::step - 1].size  # the smallest stride that fits
    got = windows(str(tmp_path / "a.zarr"), "", channels=(0, 1), scale=0.5, samples=1000)
    lo, hi = np.percentile(grid.astype(np.float64) * 0.5, [1, 99])
    assert got[0] == pytest.approx([lo, hi, 0.5 * x[0].min(), 0.5 * x[0].max()], rel=1e-12)
    assert got[1] is None
    full = windows(str(tmp_path / "a.zarr"), "", channels=(0,))[0]  # under the default bound: every voxel
    assert full[:2] == pytest.approx(np.percentile(x[0].astype(np.float64), [1, 99]), rel=1e-12)

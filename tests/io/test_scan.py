"""write_scan / open_scan / Scan: round trips, exact pyramid sums, refs, NGFF, refusals."""

from __future__ import annotations

import inspect
import json
from pathlib import Path

import dask.array as da
import numpy as np
import pytest
import zarr

from chunkdic.errors import InputError
from chunkdic.io.coarsen import coarsen_sum, pyramid_dtype
from chunkdic.io.handles import ArrayRef
from chunkdic.io.scan import open_scan
from chunkdic.io.scanwrite import write_scan
from chunkdic.io.store import check_write_alignment, store_array


def block_sums(x: np.ndarray, s: int) -> np.ndarray:
    """Oracle: level ``s`` by NumPy reshape-sums in int64 (odd trailing voxels dropped)."""
    x = x.astype(np.float64) if x.dtype.kind == "f" else x.astype(np.int64)
    for _ in range(s):
        n = [k // 2 for k in x.shape]
        x = x[: 2 * n[0], : 2 * n[1], : 2 * n[2]].reshape(n[0], 2, n[1], 2, n[2], 2).sum(axis=(1, 3, 5))
    return x


@pytest.fixture(scope="module")
def vol8():
    return np.random.default_rng(0).integers(0, 256, (37, 29, 23), dtype=np.uint8)


def test_pyramid_dtype_table():
    assert [pyramid_dtype("uint8", s).name for s in range(5)] == ["uint8", "uint16", "uint16", "uint32", "uint32"]
    assert pyramid_dtype("uint16", 1).name == "uint32"
    assert pyramid_dtype("int16", 1).name == "int32"
    assert pyramid_dtype("int8", 1).name == "int16"
    assert pyramid_dtype("float32", 3).name == "float32"
    assert pyramid_dtype("float64", 1).name == "float64"
    assert pyramid_dtype(">u2", 0) == np.dtype("uint16")
    # the paper's case: a 4^3 sum of 8-bit data fills 14 bits
    assert 255 * 64 < 2**14 <= np.iinfo(pyramid_dtype("uint8", 2)).max


@pytest.mark.parametrize("shape", [(37, 29, 23), (8, 9, 7), (5, 4, 3)])
def test_coarsen_sum_equals_numpy(shape):
    x = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    for chunks in [(4, 6, 2), (3, 5, 7), shape]:
        got = coarsen_sum(da.from_array(x, chunks=chunks)).compute()
        assert got.dtype == np.uint16
        np.testing.assert_array_equal(got, block_sums(x, 1))
    np.testing.assert_array_equal(coarsen_sum(x), block_sums(x, 1))


@pytest.mark.parametrize("src, out", [("uint8", "uint16"), ("uint16", "uint32"), ("int16", "int32"),
                                      ("uint32", "uint32"), ("float32", "float32")])
def test_numba_kernel_equals_numpy_twin(src, out):
    from chunkdic.io.coarsen import coarsen_block, coarsen_block_numpy

    rng = np.random.default_rng(3)
    if np.dtype(src).kind == "f":
        x = rng.random((11, 8, 9)).astype(src)
    else:
        info = np.iinfo(src)
        hi = min(int(info.max), 2**20)  # level-2 uint32 sums of 8-bit data stay far below 2**32
        x = rng.integers(max(int(info.min), -hi), hi, (11, 8, 9), endpoint=True).astype(src)
    for block in (x, x[1:, 2:, :7]):  # odd sizes, non-contiguous
        got = coarsen_block(block, out)
        assert got.dtype == np.dtype(out)
        np.testing.assert_array_equal(got, coarsen_block_numpy(block, out))
        np.testing.assert_allclose(got, block_sums(block, 1))


def test_write_scan_roundtrip_levels(tmp_path, vol8):
    seen = []
    scan = write_scan(tmp_path / "a.zarr", da.from_array(vol8, chunks=(7, 11, 5)), chunks=8, levels=3,
                      voxel_size=4.91, unit="um", progress=seen.append)
    assert scan.stored_levels() == [0, 1, 2, 3]
    assert scan.voxel_size == (4.91, 4.91, 4.91) and scan.unit == "micrometer"
    assert seen and seen[-1] == 1.0 and all(b >= a for a, b in zip(seen, seen[1:]))
    for s in range(4):
        assert scan.dtype(s) == pyramid_dtype("uint8", s)
        np.testing.assert_array_equal(scan.level(s).compute(), block_sums(vol8, s))
    g = zarr.open_group(str(tmp_path / "a.zarr"), mode="r")
    assert g["0"].chunks == (8, 8, 8)
    assert all(g[str(s)].attrs["chunkdic"] == {"level": s, "complete": True} for s in range(4))
    # reopened from disk: same voxel size; lazy level 4 from stored level 3
    again = open_scan(str(tmp_path / "a.zarr"))
    assert again.voxel_size == (4.91, 4.91, 4.91)
    np.testing.assert_array_equal(again.level(4).compute(), block_sums(vol8, 4))
    assert open_scan(str(tmp_path / "a.zarr"), voxel_size=(2, 1, 1)).voxel_size == (2.0, 1.0, 1.0)


def test_write_scan_float_levels(tmp_path):
    x = np.random.default_rng(2).random((9, 10, 11)).astype(np.float32)
    scan = write_scan(tmp_path / "f.zarr", x, chunks=4, levels=2)
    assert scan.dtype(2) == np.float32
    np.testing.assert_allclose(scan.level(2).compute(), block_sums(x, 2), rtol=1e-6)


def test_ngff_metadata_read_by_ome_zarr(tmp_path):
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    path = tmp_path / "m.zarr"
    write_scan(path, np.zeros((17, 16, 15), np.uint8), chunks=8, levels=2, voxel_size=(2.0, 1.0, 0.5),
               unit="micrometer")
    node = list(Reader(parse_url(str(path)))())[0]
    assert [a["name"] for a in node.metadata["axes"]] == ["z", "y", "x"]
    assert {a["unit"] for a in node.metadata["axes"]} == {"micrometer"}
    assert [tuple(a.shape) for a in node.data] == [(17, 16, 15), (8, 8, 7), (4, 4, 3)]
    vs = np.array([2.0, 1.0, 0.5])
    for s, transforms in enumerate(node.metadata["coordinateTransformations"]):
        by_type = {t["type"]: t for t in transforms}
        np.testing.assert_allclose(by_type["scale"]["scale"], vs * 2**s)
        np.testing.assert_allclose(by_type["translation"]["translation"], vs * (2**s - 1) / 2)


def test_write_scan_refuses_existing_and_overwrites(tmp_path, vol8):
    p = tmp_path / "a.zarr"
    write_scan(p, vol8, chunks=16)
    with pytest.raises(InputError, match="pass --overwrite"):
        write_scan(p, vol8)
    scan = write_scan(p, vol8[:10], chunks=16, overwrite=True)
    assert scan.shape(0) == (10, 29, 23)
    np.testing.assert_array_equal(scan.level(0).compute(), vol8[:10])
    (tmp_path / "notzarr").mkdir()
    (tmp_path / "notzarr" / "precious.txt").write_text("keep")
    with pytest.raises(InputError, match="chunkdic did not write"):
        write_scan(tmp_path / "notzarr", vol8, overwrite=True)
    assert (tmp_path / "notzarr" / "precious.txt").exists()


def test_failed_write_leaves_nothing(tmp_path, vol8):
    def boom(b, block_info=None):
        if block_info[0]["chunk-location"][0] == 2:
            raise RuntimeError("disk on fire")
        return b

    data = da.from_array(vol8, chunks=8).map_blocks(boom, dtype=vol8.dtype)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_scan(tmp_path / "a.zarr", data, chunks=8)
    assert not (tmp_path / "a.zarr").exists()


def test_chunk_alignment_violation_is_caught(tmp_path):
    with pytest.raises(InputError, match="multiples of 8"):
        check_write_alignment(((5, 11), (16,), (16,)), (16, 16, 16), (8, 8, 8))
    check_write_alignment(((8, 8), (16,), (10,)), (16, 16, 10), (8, 8, 8))
    arr = zarr.create_array(str(tmp_path / "x.zarr"), shape=(16, 16, 16), chunks=(8, 8, 8), dtype="uint8")
    with pytest.raises(InputError, match="own whole chunks"):
        store_array(da.ones((16, 16, 16), dtype="uint8", chunks=(5, 16, 16)), str(tmp_path / "x.zarr"), "")
    assert int(np.asarray(arr[:]).sum()) == 0  # nothing written
    # sharded arrays: the write unit is the shard
    sharded = zarr.create_array(str(tmp_path / "s.zarr"), shape=(16, 16, 16), chunks=(4, 4, 4),
                                shards=(8, 8, 8), dtype="uint8")
    with pytest.raises(InputError, match="multiples of 8"):
        store_array(da.ones((16, 16, 16), dtype="uint8", chunks=4), str(tmp_path / "s.zarr"), "")
    store_array(da.ones((16, 16, 16), dtype="uint8", chunks=8), str(tmp_path / "s.zarr"), "")
    assert int(np.asarray(sharded[:]).sum()) == 16**3


def test_open_scan_sources(tmp_path, vol8):
    np.save(tmp_path / "v.npy", vol8)
    write_scan(tmp_path / "g.zarr", vol8, chunks=16, levels=1)
    zarr.create_array(str(tmp_path / "root.zarr"), data=vol8, chunks=(16, 16, 16))
    sources = [
        vol8,
        da.from_array(vol8, chunks=10),
        str(tmp_path / "v.npy"),
        str(tmp_path / "g.zarr"),
        str(tmp_path / "g.zarr/0"),
        str(tmp_path / "root.zarr"),
        zarr.open_group(str(tmp_path / "g.zarr"), mode="r"),
        zarr.open_array(str(tmp_path / "g.zarr"), path="0", mode="r"),
    ]
    for src in sources:
        scan = open_scan(src)
        assert scan.shape(0) == vol8.shape and scan.dtype(0) == np.uint8
        np.testing.assert_array_equal(scan.level(0).compute(), vol8)
        np.testing.assert_array_equal(scan.level(2).compute(), block_sums(vol8, 2))
    npy = open_scan(str(tmp_path / "v.npy"))
    assert npy.refs([0])[0].kind == "npy"  # used in place, memory-mapped
    assert open_scan(str(tmp_path / "g.zarr")).stored_levels() == [0, 1]


def test_refs_materialize_missing_levels(tmp_path, vol8):
    scan = open_scan(vol8)
    refs = scan.refs([0, 2, 3], tmp_path / "scratch" / "ref")
    assert set(refs) == {0, 2, 3}
    for s, ref in refs.items():
        assert isinstance(ref, ArrayRef) and ref.kind == "zarr"
        np.testing.assert_array_equal(ref.read((slice(None),) * 3), block_sums(vol8, s))
        assert ref.dtype == pyramid_dtype("uint8", s).name
    stored = write_scan(tmp_path / "g.zarr", vol8, chunks=16)
    refs = stored.refs([0, 1, 2], tmp_path / "scratch2")
    assert refs[0].path == str(tmp_path / "g.zarr")  # stored level used directly
    assert refs[2].path.startswith(str(tmp_path / "scratch2"))
    np.testing.assert_array_equal(refs[2].read((slice(None),) * 3), block_sums(vol8, 2))


def test_incomplete_level_is_ignored(tmp_path, vol8):
    p = tmp_path / "a.zarr"
    write_scan(p, vol8, chunks=16, levels=1)
    meta = p / "1" / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"]["chunkdic"]["complete"] = False
    meta.write_text(json.dumps(doc))
    scan = open_scan(str(p))
    assert scan.stored_levels() == [0]
    np.testing.assert_array_equal(scan.level(1).compute(), block_sums(vol8, 1))


@pytest.mark.parametrize(
    "src, match",
    [
        ("missing.zarr", "does not exist"),
        (np.zeros((4, 4)), "3-D"),
        (da.zeros((2, 3, 4, 5)), "3-D"),
        (12, "cannot open a scan"),
        ("notes.txt", "not a Zarr store"),
        ("bad.zarr", "cannot read"),
        ("flat.npy", "3-D"),
        ("slices.tif", "chunkdic ingest"),
    ],
)
def test_open_scan_refuses(tmp_path, monkeypatch, src, match):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / "bad.zarr").mkdir()
    (tmp_path / "bad.zarr" / "zarr.json").write_text("{not json")
    np.save(tmp_path / "flat.npy", np.zeros((3, 3)))
    (tmp_path / "slices.tif").write_bytes(b"II*\x00")
    with pytest.raises(InputError, match=match) as err:
        open_scan(src)
    assert "\n" not in str(err.value)


def test_write_scan_refuses_bad_input(tmp_path):
    with pytest.raises(InputError, match="3-D"):
        write_scan(tmp_path / "a.zarr", np.zeros((4, 4)))
    with pytest.raises(InputError, match="at most"):
        write_scan(tmp_path / "a.zarr", np.zeros((4, 4, 4)), levels=3)
    with pytest.raises(InputError, match="unit"):
        write_scan(tmp_path / "a.zarr", np.zeros((4, 4, 4)), voxel_size=1, unit="furlongs")
    with pytest.raises(InputError, match="voxel size"):
        write_scan(tmp_path / "a.zarr", np.zeros((4, 4, 4)), voxel_size=(1, 2))
    assert not (tmp_path / "a.zarr").exists()


def test_public_names_are_the_functions_whatever_was_imported_first():
    """A submodule named like a public function would shadow it once imported."""
    import importlib

    import chunkdic

    for name in chunkdic.__all__:
        try:
            importlib.import_module(f"chunkdic.{name}")
        except ModuleNotFoundError:
            pass
        assert not inspect.ismodule(getattr(chunkdic, name)), name


@pytest.mark.parametrize("kind", ["numpy", "in-memory zarr"])
def test_in_memory_inputs_never_travel_inside_a_graph(tmp_path, monkeypatch, kind):
    """A NumPy (or in-memory Zarr) level 0 on a distributed client: written to scratch from
    the client chunk by chunk (no graph), the coarser levels then built by the client's
    tasks whose arguments hold only handles (pickled under 1 kB, against 512 kB of
    voxels), exact sums."""
    import pickle

    from distributed import Client

    import chunkdic.io.levels as levels
    from chunkdic.scheduler import DistributedRunner

    x = np.random.default_rng(3).integers(0, 60000, size=(64, 64, 64), dtype=np.uint16)
    if kind == "numpy":
        src = x
    else:
        src = zarr.create_array(zarr.storage.MemoryStore(), shape=x.shape, chunks=(32, 32, 32), dtype=x.dtype)
        src[...] = x
    monkeypatch.setattr(levels, "store_array", lambda *a, **k: pytest.fail("a Dask graph was built"))
    sizes = []
    original = DistributedRunner.map_unordered

    def recording(self, fn, args):
        args = list(args)
        sizes.extend(len(pickle.dumps(a)) for a in args)
        return original(self, fn, args)

    monkeypatch.setattr(DistributedRunner, "map_unordered", recording)
    with Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=":0"):
        refs = open_scan(src).refs([0, 1, 2], tmp_path / "scratch")
    assert sizes and max(sizes) < 1_000, sizes  # the tasks ran on the client; measured ~0.5 kB each
    np.testing.assert_array_equal(refs[0].read((slice(None),) * 3), x)
    np.testing.assert_array_equal(refs[2].read((slice(None),) * 3), block_sums(x, 2))


def float32_sums(x: np.ndarray, s: int) -> np.ndarray:
    """Oracle of a float32 pyramid: each step a NumPy reshape-sum in float64 rounded to
    float32 (exact sums for the data below: float32 values of a narrow range)."""
    for _ in range(s):
        n = [k // 2 for k in x.shape]
        x = (x[: 2 * n[0], : 2 * n[1], : 2 * n[2]].astype(np.float64).reshape(n[0], 2, n[1], 2, n[2], 2)
             .sum(axis=(1, 3, 5)).astype(np.float32))
    return x


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "float32"])
def test_scratch_levels_by_tasks_equal_the_lazy_levels(tmp_path, dtype):
    """The scratch levels of ``refs`` (tasks, chunkdic.io.scratch_levels) equal bit for bit the
    lazy Dask levels and an independent NumPy reshape-sum, on an odd shape cut into 8³
    chunks (many tasks, trailing partial chunks, trimmed odd voxels); also levels asked
    alone (built from level 0 in one task per chunk, intermediate levels never stored)."""
    import dask.config

    rng = np.random.default_rng(11)
    shape = (37, 22, 51)
    if dtype == "float32":
        x = (rng.integers(0, 65536, shape) / 16).astype(np.float32)
    else:
        x = rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)
    with dask.config.set({"chunkdic.chunk-size": 8}):
        write_scan(tmp_path / "s.zarr", x, chunks=8)
        refs = open_scan(str(tmp_path / "s.zarr")).refs([1, 2, 3, 4], tmp_path / "a")
        alone = open_scan(str(tmp_path / "s.zarr")).refs([3, 4], tmp_path / "b")
        lazy = {s: open_scan(str(tmp_path / "s.zarr")).level(s).compute() for s in range(1, 5)}
    assert refs[1].open().chunks == (8, 8, 8) and not any(r.path.startswith(str(tmp_path / "s.zarr"))
                                                          for r in refs.values())
    for s in range(1, 5):
        got = refs[s].read((slice(None),) * 3)
        oracle = float32_sums(x, s) if dtype == "float32" else block_sums(x, s)
        assert got.dtype == pyramid_dtype(dtype, s) == lazy[s].dtype
        np.testing.assert_array_equal(got, lazy[s])
        np.testing.assert_array_equal(got, oracle)
        if s in alone:
            np.testing.assert_array_equal(alone[s].read((slice(None),) * 3), got)


def test_refs_of_an_empty_level(tmp_path):
    """A level with an empty axis is still created (and complete): shape (0, 2, 3)."""
    x = np.ones((3, 9, 13), np.uint8)
    ref = open_scan(str(write_scan(tmp_path / "s.zarr", x).path)).refs([2], tmp_path / "scratch")[2]
    assert ref.shape == (0, 2, 3) and ref.read((slice(None),) * 3).shape == (0, 2, 3)


def test_correlation_of_zarr_scans_never_imports_dask_array(tmp_path):
    """``import dask.array`` costs ~1 s (it imports xarray and pandas when installed): a
    correlation of two Zarr scans without stored levels builds its scratch levels by
    tasks and never imports it (a fresh interpreter, as a user's script)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    import chunkdic

    x = (np.random.default_rng(2).random((64, 64, 64)) * 4000).astype(np.uint16)
    write_scan(tmp_path / "f.zarr", x)  # level 0 only: levels 1 and 2 go to scratch
    f = str(tmp_path / "f.zarr")
    code = ("import sys, chunkdic\n"
            f"r = chunkdic.correlate({f!r}, {f!r}, element_size=8, coarsest=2)\n"
            "assert r.info['levels'] == [2, 1, 0], r.info['levels']\n"
            "print(sorted(m for m in ('dask.array', 'pandas', 'xarray') if m in sys.modules))\n")
    here = str(Path(chunkdic.__file__).parent.parent)  # this chunkdic, whether installed or not
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout


def test_write_scan_of_a_numpy_array_writes_it_from_the_client(tmp_path, monkeypatch):
    """No Dask graph at all for a NumPy level 0 (it would carry the array)."""
    import chunkdic.io.levels as levels

    monkeypatch.setattr(levels, "store_array", lambda *a, **k: pytest.fail("a graph was built"))
    x = np.arange(20 * 18 * 16, dtype=np.uint16).reshape(20, 18, 16)
    scan = write_scan(tmp_path / "s.zarr", x, chunks=8)
    np.testing.assert_array_equal(scan.level(0).compute(), x)


def test_scratch_levels_of_an_interrupted_run_are_adopted_only_complete(tmp_path):
    """``refs(..., adopt=True)`` on the scratch an interrupted run wrote for the same scan
    (issue 21, item 5): complete levels are reused as they are (not written again), a level
    with a chunk cut short is built again (to the right sums), and a level coarser than any
    wanted one (done before the kill) is removed."""
    import dask.config

    rng = np.random.default_rng(12)
    x = rng.integers(0, 4000, (40, 36, 44)).astype(np.uint16)
    scratch = tmp_path / "ref"
    with dask.config.set({"chunkdic.chunk-size": 8}):
        first = open_scan(x).refs([0, 1, 2, 3], scratch)  # level 0 from memory, then the sums
        group = Path(first[0].path)
        chunk0, chunk1 = group / "0" / "c" / "1" / "1" / "1", group / "1" / "c" / "0" / "1" / "0"
        stamp0 = chunk0.stat().st_mtime_ns
        chunk1.write_bytes(chunk1.read_bytes()[:-3])  # level 1: a chunk cut short by the kill
        again = open_scan(x).refs([0, 1, 2], scratch, adopt=True)
    assert [r.path for r in again.values()] == [str(group)] * 3  # the same group, no new one
    assert chunk0.stat().st_mtime_ns == stamp0  # level 0 reused, not written again
    assert not (group / "3").exists()  # coarser than any wanted level: removed
    for s in (0, 1, 2):
        np.testing.assert_array_equal(again[s].read((slice(None),) * 3), block_sums(x, s))
    assert chunk1.stat().st_size > 0 and again[1].read((slice(None),) * 3).shape == block_sums(x, 1).shape


def test_a_large_array_is_written_slab_by_slab_each_graph_bounded(tmp_path, monkeypatch):
    """A write of more blocks than ``MAX_GRAPH_BLOCKS`` computes one graph per slab of block planes,
    none of more blocks (dask's map_blocks records every block up front: a Zarr input declaring
    10 000³ voxels grew one graph past 1 GiB); the array written is the same."""
    import dask.array as da

    from chunkdic.io import store

    monkeypatch.setattr(store, "MAX_GRAPH_BLOCKS", 20)
    sizes = []
    real = store._compute
    monkeypatch.setattr(store, "_compute", lambda x, *a, **k: (sizes.append(int(np.prod(x.numblocks))),
                                                              real(x, *a, **k))[1])
    data = da.arange(24 * 16 * 16, dtype=np.uint16, chunks=4).reshape(24, 16, 16).rechunk(4)
    scan = write_scan(tmp_path / "s.zarr", data, chunks=4)
    assert sizes == [16, 16, 16, 16, 16, 16] and sum(sizes) == 6 * 4 * 4  # 96 blocks, 16 per plane of blocks
    assert np.array_equal(np.asarray(scan.level(0)), np.arange(24 * 16 * 16, dtype=np.uint16).reshape(24, 16, 16))

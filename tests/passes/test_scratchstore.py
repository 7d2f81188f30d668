"""The compact scratch layout (issue 21 item 1): chunks read from their files equal zarr's
read, a compact run's field does not depend on the blocks and stays close to the fast
layout's and to the exact translation, and the pyramid levels a run wrote are deleted
once their level is done."""

from __future__ import annotations

import os
from pathlib import Path

import dask.config
import numpy as np
import pytest
import zarr
from textures import smooth_noise

import chunkdic
from chunkdic.passes import scratchstore
from chunkdic.passes.haloed import HaloedBlocks, quantization
from chunkdic.passes.prefilter import prepared_grid


@pytest.mark.parametrize("layout", ["fast", "compact"])
def test_chunk_files_read_as_zarr_reads_them(tmp_path, layout):
    rng = np.random.default_rng(1)
    data = rng.integers(0, 4096, (70, 50, 40)).astype(np.uint16)
    data[:32, :32, :32] = 0  # a chunk equal to the fill value: zarr writes no file for it
    with dask.config.set({"chunkdic.scratch-layout": layout}):
        z = zarr.create_array(str(tmp_path / "a.zarr"), shape=data.shape, chunks=(32,) * 3, dtype="uint16",
                              compressors=scratchstore.compressors("g", 2), zarr_format=3, fill_value=0)
    z[...] = data
    assert not (tmp_path / "a.zarr" / "c" / "0" / "0" / "0").exists()
    for window in [(slice(0, 70), slice(0, 50), slice(0, 40)), (slice(5, 66), slice(31, 33), slice(0, 1)),
                   (slice(33, 64), slice(10, 45), slice(17, 39))]:
        got = scratchstore.read_window(str(tmp_path / "a.zarr"), window, 32, "uint16", layout == "compact")
        np.testing.assert_array_equal(got, data[window])


def test_haloed_store_round_trip_in_both_layouts(tmp_path):
    rng = np.random.default_rng(2)
    region = (rng.random((20, 18, 17)) * 60000).astype(np.float32)
    for layout in ("fast", "compact"):
        with dask.config.set({"chunkdic.scratch-layout": layout}):
            store = HaloedBlocks.create(tmp_path / f"{layout}.zarr", (2, 1, 1), (20, 20, 20), "float32",
                                        quantize_from="uint16")
        back = store.write((1, 0, 0), region)
        np.testing.assert_array_equal(store.read((1, 0, 0), region.shape), back)
        step = 16.0 if layout == "compact" else 1.0
        assert store.step == step and store.compressed == (layout == "compact")
        assert np.abs(back - region).max() <= step / 2 + 1e-3  # the grid's rounding, nothing else


def test_compact_grids_are_16_times_coarser():
    with dask.config.set({"chunkdic.scratch-layout": "compact"}):
        assert quantization("uint16") == (0.0, 16.0) and quantization("uint8") == (0.0, 2.0**-4)
        compact = prepared_grid("uint16", 1.0, "cubic")
        assert scratchstore.compressors("f", 2) is not None
    fast = prepared_grid("uint16", 1.0, "cubic")
    assert compact[0] == fast[0] and compact[1] == pytest.approx(16 * fast[1])
    assert scratchstore.compressors("f", 2) is None  # auto, outside a run that chose compact
    with dask.config.set({"chunkdic.scratch-layout": "small"}), pytest.raises(chunkdic.InputError):
        scratchstore.layout()


def test_compact_run_is_block_independent_and_close_to_the_fast_one():
    """The compact grid is the level's, so blocks do not matter; its rounding (σ 4.6 grey levels
    here, on a 60000-level texture) moves the field far less than the measurement error."""
    f = smooth_noise((48, 48, 48), sigma=1.2, seed=5)
    f = ((f - f.min()) / (f.max() - f.min()) * 60000 + 2000).astype(np.uint16)
    g = np.roll(f, (1, 2, -1), axis=(0, 1, 2))  # f(X) = g(X + (1, 2, -1))
    runs = {}
    # a fixed length: on this noise-free pair the misfit the automatic choice weighs is the
    # compact grid's own rounding, and the discrepancy sat on a tie between 45 and 64 voxels
    # that the blocks' summation order (1e-7) decided; the choice is not what is tested here
    for layout, m in (("compact", 1), ("compact", 4), ("fast", 4)):
        with dask.config.set({"chunkdic.scratch-layout": layout}):
            runs[layout, m] = chunkdic.correlate(f, g, element_size=8, block_elements=m, coarsest=0,
                                                 regularization_length=64.0, grey_cell=0.0).displacement  # per element: blocks 1 and 4 differ
    np.testing.assert_allclose(runs["compact", 1], runs["compact", 4], rtol=0, atol=1e-6)
    truth = np.array([1.0, 2.0, -1.0])[:, None, None, None]
    inner = (slice(None), slice(1, -1), slice(1, -1), slice(1, -1))
    fast_error = np.abs(runs["fast", 4] - truth)[inner].max()
    compact_error = np.abs(runs["compact", 4] - truth)[inner].max()
    assert np.abs(runs["compact", 4] - runs["fast", 4]).max() < 2e-3
    assert compact_error < fast_error + 2e-3 and compact_error < 0.02, (fast_error, compact_error)


def _pyramid_levels(scratch: Path) -> set:
    """Pyramid level arrays (``<scan group>/<level>/zarr.json``) under a scratch directory."""
    found = set()
    for dirpath, _, files in os.walk(scratch):
        p = Path(dirpath)
        if "zarr.json" in files and p.name.isdigit() and len(p.name) == 1:
            found.add(int(p.name))
    return found


def test_pyramid_levels_are_deleted_once_their_level_is_done(tmp_path):
    f = smooth_noise((96, 96, 96), sigma=1.5, seed=3)
    f = ((f - f.min()) / (f.max() - f.min()) * 50000 + 5000).astype(np.uint16)
    np.save(tmp_path / "ref.npy", f)
    np.save(tmp_path / "def.npy", np.roll(f, (1, -1, 0), axis=(0, 1, 2)))
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    seen = {}

    def progress(event):
        if event["stage"] == "matrix":
            seen[event["level"]] = _pyramid_levels(scratch)

    with dask.config.set({"chunkdic.scratch-directory": str(scratch)}):
        res = chunkdic.correlate(tmp_path / "ref.npy", tmp_path / "def.npy", element_size=8, coarsest=2,
                                 progress=progress)
    assert res.info["status"] == "converged"
    assert seen[2] >= {1, 2}  # both built at the start
    assert 2 not in seen[1] and 1 in seen[1]
    assert not seen[0] & {1, 2}


# --------------------------------------------------------------------------- adopted by a resumed run (issue 21, item 5)


@pytest.mark.parametrize("layout", ["fast", "compact"])
def test_haloed_store_is_adopted_only_complete_and_whole(tmp_path, layout):
    """A haloed f store is reused by a resumed run only when marked complete, laid out as
    this run lays it out and with every chunk file at its whole length."""
    rng = np.random.default_rng(3)
    grid, chunk = (2, 1, 2), (10, 12, 9)
    with dask.config.set({"chunkdic.scratch-layout": layout}):
        store = HaloedBlocks.create(tmp_path / "f.zarr", grid, chunk, "float32", quantize_from="uint16")
        blocks = {idx: rng.uniform(0, 60000, chunk).astype(np.float32) for idx in np.ndindex(*grid)}
        for idx, block in blocks.items():
            store.write(idx, block)

        def adopted(**kw):
            args = dict(grid=grid, chunk=chunk, dtype="float32", quantize_from="uint16") | kw
            return HaloedBlocks.adopt(tmp_path / "f.zarr", **args)

        assert adopted() is None  # every chunk written, but not marked complete
        store.mark_complete()
        got = adopted()
        assert got == store
        for idx, block in blocks.items():
            np.testing.assert_array_equal(got.read(idx, chunk), store.read(idx, chunk))
        assert adopted(grid=(2, 2, 2)) is None  # other blocks
        assert adopted(quantize_from="float32") is None  # another grid (scratch precision)
        chunk_file = tmp_path / "f.zarr" / "c" / "1" / "0" / "1" / "0" / "0" / "0"
        whole = chunk_file.read_bytes()
        chunk_file.write_bytes(whole[:-1])  # a chunk cut short (a kill while it was written)
        assert adopted() is None
        chunk_file.write_bytes(whole)
        assert adopted() == store
        store.unmark()  # a pass rewriting it
        assert adopted() is None
    with dask.config.set({"chunkdic.scratch-layout": "compact" if layout == "fast" else "fast"}):
        store.mark_complete()
        assert HaloedBlocks.adopt(tmp_path / "f.zarr", grid, chunk, "float32", quantize_from="uint16") is None


@pytest.mark.parametrize("local", [True, False])
def test_prepared_g_is_adopted_only_complete_whole_and_on_this_runs_grid(tmp_path, local):
    from chunkdic.passes.prefilter import adopt_prepared, build_prepared, record_path
    from chunkdic.io.handles import ArrayRef

    rng = np.random.default_rng(4)
    g = rng.integers(0, 65535, (40, 36, 30)).astype(np.uint16)
    zarr.create_array(str(tmp_path / "g.zarr"), data=g, chunks=(16, 16, 16), zarr_format=3)
    g_ref = ArrayRef("zarr", str(tmp_path / "g.zarr"), "", g.shape, "uint16")
    box = ((2, 38), (0, 36), (3, 29))
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    for k in (1, 2):  # a second build supersedes the first
        built = build_prepared(g_ref, box, scratch / f"g-level0-{k}.zarr",
                               lambda fn, args: (fn(*a) for a in args), halo=16, local=local, sigma=1.0)
    grid = prepared_grid("uint16", 1.0, "cubic")
    got, k = adopt_prepared(scratch, 0, grid, local=local)
    assert k == 2 and got == built
    window = (slice(5, 30), slice(1, 20), slice(3, 29))
    np.testing.assert_array_equal(got.read(window), built.read(window))
    assert adopt_prepared(scratch, 1, grid, local=local) is None  # another level's
    assert adopt_prepared(scratch, 0, (grid[0], grid[1] * 16), local=local) is None  # the compact grid
    if local:
        assert adopt_prepared(scratch, 0, grid, local=False) is None  # a memory-mapped file: local tasks only
        data = Path(built.ref.path)
    else:
        data = Path(built.ref.path, "c", "0", "0", "0")  # one 64³ chunk
    whole = data.read_bytes()
    data.write_bytes(whole[:-2])  # cut short
    assert adopt_prepared(scratch, 0, grid, local=local) is None
    data.write_bytes(whole)
    record_path(built.ref.path).unlink()  # a build killed before its end: never trusted
    assert adopt_prepared(scratch, 0, grid, local=local)[1] == 1  # the earlier build, complete
    record_path(Path(scratch, Path(built.ref.path).name.replace("-2", "-1"))).unlink()
    assert adopt_prepared(scratch, 0, grid, local=local) is None

"""ingest: every format round-trips values and voxel size; bad input refused, nothing left."""

from __future__ import annotations

import argparse

import h5py
import numpy as np
import pytest
import tifffile

from chunkdic.cli import scan_commands as _cli_scan
from chunkdic.errors import InputError
from chunkdic.io.formats.base import natural_key
from chunkdic.io.formats.ingest import ingest, slab_chunks

SHAPE = (13, 17, 19)


@pytest.fixture(scope="module")
def vol16():
    return np.random.default_rng(0).integers(0, 60000, SHAPE, dtype=np.uint16)


def _roundtrip(scan, expected, voxel_size=None, unit=None):
    got = scan.level(0).compute()
    assert got.dtype == expected.dtype.newbyteorder("=")
    np.testing.assert_array_equal(got, expected)
    assert scan.voxel_size == voxel_size
    assert scan.unit == unit


def test_natural_sort():
    names = ["slice_10.tif", "slice_2.tif", "slice_1.tif", "Slice_100.tif", "slice_11.tif"]
    assert sorted(names, key=natural_key) == ["slice_1.tif", "slice_2.tif", "slice_10.tif", "slice_11.tif",
                                              "Slice_100.tif"]


def test_tiff_folder(tmp_path, vol16):
    d = tmp_path / "slices"
    d.mkdir()
    for z in range(SHAPE[0]):  # unpadded numbers: lexical order would put 10 before 2
        tifffile.imwrite(d / f"slice_{z}.tif", vol16[z])
    (d / "notes.txt").write_text("ignored")
    scan = ingest(d, tmp_path / "o.zarr", chunks=8, voxel_size=4.91, unit="um", levels=1)
    _roundtrip(scan, vol16, (4.91,) * 3, "micrometer")
    assert scan.stored_levels() == [0, 1]


def test_tiff_folder_compressed_and_banded(tmp_path, vol16, monkeypatch):
    d = tmp_path / "slices"
    d.mkdir()
    for z in range(SHAPE[0]):
        tifffile.imwrite(d / f"s{z:03d}.tiff", vol16[z], compression="zlib")
    monkeypatch.setenv("DASK_CHUNKDIC__INGEST_SLAB_BYTES", "2000")  # force y bands
    import dask.config

    dask.config.refresh()
    try:
        scan = ingest(d, tmp_path / "o.zarr", chunks=4)
    finally:
        monkeypatch.delenv("DASK_CHUNKDIC__INGEST_SLAB_BYTES")
        dask.config.refresh()
    _roundtrip(scan, vol16)


def test_3d_tiff_with_imagej_voxel_size(tmp_path, vol16):
    tifffile.imwrite(tmp_path / "v.tif", vol16, imagej=True, resolution=(1 / 2.5, 1 / 2.5),
                     metadata={"spacing": 5.0, "unit": "um"})
    scan = ingest(tmp_path / "v.tif", tmp_path / "o.zarr", chunks=8)
    assert scan.voxel_size == pytest.approx((5.0, 2.5, 2.5)) and scan.unit == "micrometer"
    np.testing.assert_array_equal(scan.level(0).compute(), vol16)
    # the user's voxel size wins over the metadata
    scan = ingest(tmp_path / "v.tif", tmp_path / "o2.zarr", chunks=8, voxel_size=1.5, unit="mm")
    _roundtrip(scan, vol16, (1.5,) * 3, "millimeter")


def test_3d_tiff_compressed_pages(tmp_path, vol16):
    tifffile.imwrite(tmp_path / "v.tif", vol16, compression="zlib")
    _roundtrip(ingest(tmp_path / "v.tif", tmp_path / "o.zarr", chunks=8, voxel_size=2), vol16, (2.0,) * 3)


def test_tiled_volumetric_tiff_reads_only_the_tiles_a_slab_needs(tmp_path, vol16, monkeypatch):
    """One compressed volumetric page of 3-D tiles: read through tifffile's chunked store;
    a slab decodes the tiles it overlaps (counted), never the whole series."""
    from chunkdic.io.formats.tiff import open_tiff_file

    tifffile.imwrite(tmp_path / "v.tif", vol16, tile=(4, 16, 16), volumetric=True, compression="zlib")
    monkeypatch.setattr(tifffile.TiffPageSeries, "asarray", lambda *a, **k: pytest.fail("whole series read"))
    reader = open_tiff_file(tmp_path / "v.tif")[0]
    np.testing.assert_array_equal(reader[(slice(2, 9), slice(0, 17), slice(3, 19))], vol16[2:9, :, 3:])
    _roundtrip(ingest(tmp_path / "v.tif", tmp_path / "o.zarr", chunks=8), vol16)


def test_compressed_tiff_stored_as_one_block_is_refused_when_large(tmp_path, vol16, monkeypatch):
    import chunkdic.io.formats.tiff as openers

    # one zlib tile holding every slice of a (13, 17, 19) volume: fine while small...
    tifffile.imwrite(tmp_path / "v.tif", vol16, tile=(16, 32, 32), volumetric=True, compression="zlib")
    _roundtrip(ingest(tmp_path / "v.tif", tmp_path / "o.zarr", chunks=8), vol16)
    # ...refused, with a hint, above the limit
    monkeypatch.setattr(openers, "WHOLE_VOLUME_TIFF_LIMIT", 1000)
    with pytest.raises(InputError, match="one block .* every slab would decode the whole file"):
        ingest(tmp_path / "v.tif", tmp_path / "o2.zarr", chunks=8)
    assert not (tmp_path / "o2.zarr").exists()


def test_raw_big_endian_with_offset(tmp_path, vol16):
    with open(tmp_path / "v.vol", "wb") as f:
        f.write(b"HEADER" * 10)
        f.write(vol16.astype(">u2").tobytes())
    scan = ingest(tmp_path / "v.vol", tmp_path / "o.zarr", shape="13,17,19", dtype="uint16", byte_order="big",
                  offset=60, chunks=8, voxel_size=(3, 2, 2), unit="micrometer")
    _roundtrip(scan, vol16, (3.0, 2.0, 2.0), "micrometer")


@pytest.mark.parametrize("dtype", ["uint8", "float32"])
def test_raw_little_endian(tmp_path, dtype):
    x = (np.random.default_rng(1).random(SHAPE) * 200).astype(dtype)
    x.tofile(tmp_path / "v.raw")
    scan = ingest(tmp_path / "v.raw", tmp_path / "o.zarr", shape=SHAPE, dtype=dtype, chunks=8)
    _roundtrip(scan, x)


def test_hdf5(tmp_path, vol16):
    with h5py.File(tmp_path / "v.h5", "w") as f:
        ds = f.create_dataset("entry/data/data", data=vol16, chunks=(4, 5, 6), compression="gzip")
        ds.attrs["element_size_um"] = [3.0, 2.0, 2.0]
        f.create_dataset("entry/other", data=np.zeros((2, 2, 2)))
    scan = ingest(f"{tmp_path}/v.h5:/entry/data/data", tmp_path / "o.zarr", chunks=8)
    _roundtrip(scan, vol16, (3.0, 2.0, 2.0), "micrometer")
    scan = ingest(tmp_path / "v.h5", tmp_path / "o2.zarr", dataset="/entry/data/data", chunks=8, voxel_size=1)
    _roundtrip(scan, vol16, (1.0,) * 3)


def test_npy_and_zarr(tmp_path, vol16):
    np.save(tmp_path / "v.npy", vol16.astype(">u2"))
    scan = ingest(tmp_path / "v.npy", tmp_path / "o.zarr", chunks=8, voxel_size=0.7, unit="um")
    _roundtrip(scan, vol16, (0.7,) * 3, "micrometer")
    again = ingest(tmp_path / "o.zarr", tmp_path / "o2.zarr", chunks=4)  # recompress / rechunk a scan
    _roundtrip(again, vol16, (0.7,) * 3, "micrometer")


def test_slab_chunks_bounded():
    # whole Zarr chunks, whole planes when they fit the budget (32 MiB), else bands
    assert slab_chunks((1000, 512, 512), np.uint8, (128, 128, 128)) == (128, 512, 512)
    for shape, dtype in [((1000, 1024, 1024), np.uint8), ((900, 2048, 2048), np.uint16),
                         ((500, 4096, 4096), np.uint16)]:
        cz, cy, cx = slab_chunks(shape, dtype, (128, 128, 128))
        assert cz == 128 and cy % 128 == 0 and (cx % 128 == 0 or cx == shape[2])
        assert cz * cy * cx * np.dtype(dtype).itemsize <= 32 * 2**20


def _bad_inputs(tmp_path):
    x = np.zeros(SHAPE, np.uint8)
    x.tofile(tmp_path / "v.raw")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    tifffile.imwrite(mixed / "a1.tif", np.zeros((5, 6), np.uint8))
    tifffile.imwrite(mixed / "a2.tif", np.zeros((5, 7), np.uint8))
    mixed_t = tmp_path / "mixed_dtype"
    mixed_t.mkdir()
    tifffile.imwrite(mixed_t / "a1.tif", np.zeros((5, 6), np.uint8))
    tifffile.imwrite(mixed_t / "a2.tif", np.zeros((5, 6), np.uint16))
    with h5py.File(tmp_path / "v.h5", "w") as f:
        f["data"] = x
    np.save(tmp_path / "flat.npy", np.zeros((4, 5)))
    tifffile.imwrite(tmp_path / "flat.tif", np.zeros((4, 5), np.uint8))
    bad = np.random.default_rng(0).random(SHAPE).astype(np.float32)
    bad[11, 3, 4] = np.inf
    bad.tofile(tmp_path / "inf.raw")
    np.save(tmp_path / "nan.npy", np.where(np.arange(SHAPE[0])[:, None, None] == 7, np.nan, 1.0) * np.ones(SHAPE))
    (tmp_path / "empty").mkdir()
    good = tmp_path / "good"
    good.mkdir()
    for z in range(3):
        tifffile.imwrite(good / f"s{z}.tif", np.zeros((5, 6), np.uint8))
    return {
        "raw size": (dict(src=tmp_path / "v.raw", shape=(13, 17, 20), dtype="uint8"), "bytes"),
        "raw dtype": (dict(src=tmp_path / "v.raw", shape=SHAPE, dtype="uint16"), "bytes"),
        "raw no shape": (dict(src=tmp_path / "v.raw"), "--shape"),
        "raw bad dtype": (dict(src=tmp_path / "v.raw", shape=SHAPE, dtype="complex64"), "not supported"),
        "mixed shapes": (dict(src=mixed), "mixed shapes"),
        "mixed dtypes": (dict(src=mixed_t), "mixed shapes or dtypes"),
        "no slices": (dict(src=tmp_path / "empty"), "no .tif"),
        "missing dataset": (dict(src=f"{tmp_path}/v.h5:/nope"), "no dataset '/nope'"),
        "missing file": (dict(src=tmp_path / "missing.raw"), "does not exist"),
        "2-D npy": (dict(src=tmp_path / "flat.npy"), "3-D"),
        "2-D tiff": (dict(src=tmp_path / "flat.tif"), "3-D"),
        "inf raw": (dict(src=tmp_path / "inf.raw", shape=SHAPE, dtype="float32"), r"inf value at voxel \(z, y, x\) = \(11, 3, 4\)"),
        "nan npy": (dict(src=tmp_path / "nan.npy"), "slice z=7"),
        "unit alone": (dict(src=tmp_path / "v.raw", shape=SHAPE, dtype="uint8", unit="um"), "without a voxel size"),
        "output inside input": (dict(src=good, out=good / "o.zarr"), "inside the input"),
    }


def test_bad_inputs_refused_nothing_left(tmp_path):
    cases = _bad_inputs(tmp_path)
    for name, (kw, match) in cases.items():
        out = kw.pop("out", tmp_path / "out.zarr")
        src = kw.pop("src")
        with pytest.raises(InputError, match=match) as err:
            ingest(src, out, chunks=8, **kw)
        assert "\n" not in str(err.value), name
        assert not (tmp_path / "out.zarr").exists(), name


def test_existing_output_refused(tmp_path, vol16):
    np.save(tmp_path / "v.npy", vol16)
    ingest(tmp_path / "v.npy", tmp_path / "o.zarr", chunks=8)
    with pytest.raises(InputError, match="pass --overwrite"):
        ingest(tmp_path / "v.npy", tmp_path / "o.zarr")
    ingest(tmp_path / "v.npy", tmp_path / "o.zarr", overwrite=True, chunks=16)


def _cli(argv):
    parser = argparse.ArgumentParser(prog="chunkdic")
    _cli_scan.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args([str(a) for a in argv])
    return args.func(args)


def test_cli_ingest_and_pyramid(tmp_path, vol16, capsys):
    vol16.astype(">u2").tofile(tmp_path / "v.raw")
    out = tmp_path / "o.zarr"
    assert _cli(["ingest", tmp_path / "v.raw", out, "--shape", "13,17,19", "--dtype", "uint16",
                 "--byte-order", "big", "--voxel-size", "4.91", "--unit", "micrometer", "--chunks", "8",
                 "--levels", "1"]) == 0
    err = capsys.readouterr().err
    assert "MB/s" in err and "uint16" in err
    assert _cli(["pyramid", out, "--levels", "2"]) == 0
    from chunkdic.io.scan import open_scan

    scan = open_scan(str(out))
    assert scan.stored_levels() == [0, 1, 2] and scan.voxel_size == (4.91,) * 3
    np.testing.assert_array_equal(scan.level(0).compute(), vol16)
    with pytest.raises(InputError, match="pass --overwrite"):
        _cli(["ingest", tmp_path / "v.raw", out, "--shape", "13,17,19", "--dtype", "uint16"])
    with pytest.raises(InputError, match="bytes"):
        _cli(["ingest", tmp_path / "v.raw", tmp_path / "p.zarr", "--shape", "13,17,19", "--dtype", "uint8"])
    assert not (tmp_path / "p.zarr").exists()

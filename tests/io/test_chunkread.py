"""Reading regions of Zarr scans from their chunk files (chunkdic.io.chunkread): the voxels
written, whatever the codec, the region or the cache; each chunk decoded once when the
cache holds the neighbourhood; never an old chunk after a rewrite."""

from __future__ import annotations

import dask
import numpy as np
import pytest
import zarr

from chunkdic.errors import InputError
from chunkdic.io import chunkread
from chunkdic.io.handles import ArrayRef, forget_open_arrays


def _store(path, data, compressors, chunks=(16, 12, 20), fill_value=0):
    arr = zarr.create_array(str(path), shape=data.shape, chunks=chunks, dtype=data.dtype, compressors=compressors,
                            zarr_format=3, fill_value=fill_value)
    arr[...] = data
    return ArrayRef("zarr", str(path), "", data.shape, str(data.dtype))


def _codecs():
    from zarr.codecs import BloscCodec, ZstdCodec

    return {"blosc": (BloscCodec(cname="lz4", shuffle="bitshuffle", typesize=2),), "zstd": (ZstdCodec(level=1),),
            "none": None}


@pytest.mark.parametrize("codec", ["blosc", "zstd", "none"])
@pytest.mark.parametrize("cache", [0, 1 << 20])
def test_regions_read_from_the_chunk_files_are_the_voxels_written(tmp_path, codec, cache):
    rng = np.random.default_rng(3)
    data = rng.integers(0, 65535, (40, 30, 50), dtype=np.uint16)
    data[:16, :12, :20] = 7  # a chunk of the fill value... written (zarr skips it: no file)
    ref = _store(tmp_path / "a.zarr", data, _codecs()[codec], fill_value=7)
    assert chunkread.layout_of(ref.path, ref.key).compressor == ("" if codec == "none" else codec)
    regions = [(slice(0, 40), slice(0, 30), slice(0, 50)), (slice(3, 37), slice(5, 29), slice(11, 49)),
               (slice(15, 17), slice(11, 13), slice(19, 21)), (slice(5, 5), slice(0, 3), slice(0, 3)),
               (slice(39, 40), slice(0, 30), slice(49, 50))]
    with dask.config.set({"chunkdic.chunk-cache": cache}):
        forget_open_arrays()
        for _ in range(2):  # the second time from the cache, when there is one
            for region in regions:
                got = ref.read(region)
                assert got.dtype == np.uint16 and got.flags.writeable and np.array_equal(got, data[region])
                got[...] = 0  # a copy: the cache's chunks are untouched
    forget_open_arrays()


def test_a_big_endian_float_scan_and_a_nan_fill_value(tmp_path):
    data = np.random.default_rng(4).normal(size=(20, 24, 28)).astype(">f4")
    data[:10] = np.nan
    ref = _store(tmp_path / "f.zarr", data, None, chunks=(10, 12, 14), fill_value="NaN")
    # zarr writes a big-endian array's bytes codec as endian "big"
    region = (slice(2, 19), slice(3, 24), slice(0, 27))
    got = ref.read(region)
    assert got.dtype == np.float32 and got.dtype.isnative
    np.testing.assert_array_equal(got, data[region].astype(np.float32))


def test_each_chunk_is_decoded_once_when_neighbouring_blocks_run_in_z_order(tmp_path):
    """The M pass's reads: 4³ blocks of 24³ voxels with a 5-voxel halo, 2 voxels off the
    grid of 32³ chunks (3³ chunks): the block regions cross chunks 216 times. Run in
    Z-order with a cache of 20 chunks (of the 27), each chunk is decoded once and the
    other 189 crossings are hits; without a cache, every crossing decodes."""
    data = np.random.default_rng(5).integers(0, 65535, (96, 96, 96), dtype=np.uint16)
    ref = _store(tmp_path / "s.zarr", data, _codecs()["blosc"], chunks=(32, 32, 32))
    blocks = [(i, j, k) for i in range(4) for j in range(4) for k in range(4)]
    blocks.sort(key=chunkread.z_order_key)

    def region(index):
        return tuple(slice(max(24 * i - 5 + 2, 0), min(24 * (i + 1) + 5 + 2, 96)) for i in index)

    crossings = sum(np.prod([(r.stop - 1) // 32 - r.start // 32 + 1 for r in region(b)]) for b in blocks)
    with dask.config.set({"chunkdic.chunk-cache": 20 * 32**3 * 2}):
        forget_open_arrays()
        cache = chunkread.chunk_cache()
        for b in blocks:
            assert np.array_equal(ref.read(region(b)), data[region(b)])
        assert cache.decoded == 27 and cache.hits == crossings - 27 and cache.held <= cache.capacity
    with dask.config.set({"chunkdic.chunk-cache": 0}):
        assert chunkread.chunk_cache() is None
    forget_open_arrays()
    assert crossings == 216


def test_a_rewritten_chunk_is_never_read_from_the_cache(tmp_path):
    data = np.arange(32 * 32 * 32, dtype=np.uint16).reshape(32, 32, 32)
    ref = _store(tmp_path / "r.zarr", data, _codecs()["blosc"], chunks=(16, 16, 16))
    region = (slice(4, 28),) * 3
    assert np.array_equal(ref.read(region), data[region])
    arr = zarr.open_array(str(tmp_path / "r.zarr"), mode="r+")
    arr[0:16, 0:16, 0:16] = 9  # the same store, one chunk file rewritten
    data[0:16, 0:16, 0:16] = 9
    assert np.array_equal(ref.read(region), data[region])
    forget_open_arrays()


def test_a_cut_short_chunk_is_named_in_one_line(tmp_path):
    data = np.random.default_rng(6).integers(0, 65535, (32, 32, 32), dtype=np.uint16)
    ref = _store(tmp_path / "c.zarr", data, _codecs()["blosc"], chunks=(16, 16, 16))
    file = tmp_path / "c.zarr" / "c" / "1" / "0" / "1"
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    with pytest.raises(InputError, match=r"chunk \(1, 0, 1\) \(file .*c/1/0/1\) cannot be read: .*damaged"):
        ref.read((slice(10, 20),) * 3)
    assert np.array_equal(ref.read((slice(0, 16),) * 3), data[:16, :16, :16])  # the others read
    forget_open_arrays()


def test_sharded_arrays_are_read_by_zarr_gzip_and_v2_from_their_chunk_files(tmp_path):
    from zarr.codecs import GzipCodec

    data = np.random.default_rng(7).integers(0, 255, (20, 20, 20), dtype=np.uint8)
    sharded = zarr.create_array(str(tmp_path / "sh.zarr"), shape=data.shape, chunks=(5, 5, 5), shards=(10, 10, 10),
                                dtype=data.dtype, zarr_format=3)
    sharded[...] = data
    gz = _store(tmp_path / "gz.zarr", data, (GzipCodec(),), chunks=(8, 8, 8))
    v2 = zarr.create_array(str(tmp_path / "v2.zarr"), shape=data.shape, chunks=(8, 8, 8), dtype=data.dtype,
                           zarr_format=2)
    v2[...] = data
    region = (slice(3, 17), slice(0, 20), slice(6, 7))
    for name in ("sh.zarr", "gz.zarr", "v2.zarr"):
        assert (chunkread.layout_of(str(tmp_path / name), "") is None) == (name == "sh.zarr")
        ref = ArrayRef("zarr", str(tmp_path / name), "", data.shape, "uint8")
        assert np.array_equal(ref.read(region), data[region])
    assert gz is not None
    forget_open_arrays()


def test_z_order_visits_each_octant_before_the_next():
    cells = sorted(((i, j, k) for i in range(4) for j in range(4) for k in range(4)), key=chunkread.z_order_key)
    assert cells[:8] == [(0, 0, 0), (0, 0, 1), (0, 1, 0), (0, 1, 1), (1, 0, 0), (1, 0, 1), (1, 1, 0), (1, 1, 1)]
    # each run of 8 is one 2x2x2 octant; each run of 64, one 4x4x4
    assert all(len({tuple(v // 2 for v in c) for c in cells[n:n + 8]}) == 1 for n in range(0, 64, 8))

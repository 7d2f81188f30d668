"""chunk_is_complete / store_array(resume=True): a chunk file cut short is written again,
even when its decoder would accept it (docs/safety.md, "Resuming a synthetic pair")."""

from __future__ import annotations

from pathlib import Path

import dask.array as da
import numpy as np
import pytest
import zarr

from chunkdic.io.scanwrite import write_scan
from chunkdic.io.store import blosc_frame_is_whole, chunk_is_complete, store_array
from cutchunks import cut_in_half, stale_tail_reads

SHAPE, CHUNK = (64, 32, 32), 32


def ramp(z, y, x):
    """The scan's voxels: an analytic pattern (compresses, so each chunk is a real Blosc frame)."""
    return ((97 * z + 31 * y + 7 * x) % 4099).astype(np.uint16)


def lazy_ramp():
    return da.fromfunction(ramp, shape=SHAPE, chunks=CHUNK, dtype=np.uint16)


@pytest.fixture
def scan(tmp_path) -> Path:
    """A uint16 scan (Blosc lz4 + bit shuffle, chunkdic's default for 16 bits), 2 chunks."""
    path = tmp_path / "s.zarr"
    write_scan(str(path), lazy_ramp(), chunks=CHUNK)
    return path


def chunk_file(scan: Path, coords) -> Path:
    return scan / "0" / "c" / "/".join(str(c) for c in coords)


def test_a_cut_chunk_that_its_decoder_accepts_is_still_incomplete(scan, monkeypatch):
    cut = chunk_file(scan, (1, 0, 0))
    whole = {cut: cut_in_half(cut)}
    stale_tail_reads(monkeypatch, whole)
    arr = zarr.open_array(store=str(scan), path="0", mode="r")
    # the hazard is there: the cut chunk decodes, to the voxels it held before the cut
    z, y, x = np.mgrid[32:64, 0:32, 0:32]
    assert np.array_equal(arr[32:64], ramp(z, y, x)), "the decoder now checks the length: drop this control"
    assert not chunk_is_complete(arr, (1, 0, 0))
    assert chunk_is_complete(arr, (0, 0, 0))


def test_the_resume_writes_the_cut_chunk_again_bit_for_bit(scan, monkeypatch):
    cut, kept = chunk_file(scan, (1, 0, 0)), chunk_file(scan, (0, 0, 0))
    kept_mtime = kept.stat().st_mtime_ns
    whole = {cut: cut_in_half(cut)}
    stale_tail_reads(monkeypatch, whole)
    assert store_array(lazy_ramp(), str(scan), "0", resume=True) == 1  # the cut block only
    assert cut.read_bytes() == whole[cut]
    assert kept.stat().st_mtime_ns == kept_mtime


def test_blosc_frame_is_whole_compares_the_header_with_the_file(scan, tmp_path):
    f = chunk_file(scan, (0, 0, 0))
    nbytes = CHUNK ** 3 * 2
    assert blosc_frame_is_whole(str(f), nbytes)
    assert not blosc_frame_is_whole(str(f), nbytes // 2)  # a frame of another chunk shape
    longer = tmp_path / "longer"
    longer.write_bytes(f.read_bytes() + b"\0")
    assert not blosc_frame_is_whole(str(longer), nbytes)
    for n in (15, len(f.read_bytes()) - 1):
        short = tmp_path / f"short{n}"
        short.write_bytes(f.read_bytes()[:n])
        assert not blosc_frame_is_whole(str(short), nbytes)


# --------------------------------------------------------------------------- inputs: open_scan checks the frames


def test_a_cut_chunk_of_an_input_is_refused_by_name_though_it_decodes(scan, tmp_path, monkeypatch, capsys):
    """A copy of the scan with chunk (1, 0, 0) cut to half, read the way its decoder accepts it
    (to its former voxels, without an error): the CLI refuses the scan in one line naming the
    file and the two lengths, exit 2, nothing written; the intact copy passes."""
    import shutil

    from chunkdic.cli.app import main

    intact = tmp_path / "intact.zarr"
    shutil.copytree(scan, intact)
    assert main(["pyramid", str(intact), "--levels", "1"]) == 0
    capsys.readouterr()
    cut = chunk_file(scan, (1, 0, 0))
    whole = {cut: cut_in_half(cut)}
    stale_tail_reads(monkeypatch, whole)
    z, y, x = np.mgrid[32:64, 0:32, 0:32]
    arr = zarr.open_array(store=str(scan), path="0", mode="r")
    assert np.array_equal(arr[32:64], ramp(z, y, x)), "the decoder now checks the length: drop this control"
    before = sorted(p.relative_to(scan) for p in scan.rglob("*"))
    assert main(["pyramid", str(scan), "--levels", "1"]) == 2
    err = capsys.readouterr().err
    n = len(whole[cut])
    assert err.count("\n") == 1 and err.startswith("chunkdic: error: "), err
    assert (f"{scan / '0'}: chunk file c/1/0/0 holds {n // 2} bytes where its Blosc frame header "
            f"announces {n}; the store is damaged or truncated") in err
    assert sorted(p.relative_to(scan) for p in scan.rglob("*")) == before  # no level 1 built from it


def _array(path, chunks=(CHUNK,) * 3, **kw):
    """A 64 x 32 x 32 uint16 ramp, chunks 32³ unless told, with the codecs ``kw`` give."""
    a = zarr.create_array(str(path), shape=SHAPE, chunks=chunks, dtype="uint16", **kw)
    a[...] = ramp(*np.mgrid[:64, :32, :32])
    return a


def test_a_cut_chunk_of_a_zarr_v2_blosc_array_is_refused(tmp_path):
    import numcodecs

    from chunkdic.errors import InputError
    from chunkdic.io.scan import open_scan

    _array(tmp_path / "v2.zarr", zarr_format=2, compressors=numcodecs.Blosc(cname="lz4"))
    assert open_scan(str(tmp_path / "v2.zarr")).shape(0) == SHAPE
    whole = cut_in_half(tmp_path / "v2.zarr" / "1.0.0")
    with pytest.raises(InputError, match=f"chunk file 1.0.0 holds {len(whole) // 2} bytes where its Blosc frame "
                                         f"header announces {len(whole)}"):
        open_scan(str(tmp_path / "v2.zarr"))


def test_sharded_and_zstd_arrays_are_not_header_checked(tmp_path):
    """A shard file is an index and inner chunks, not one Blosc frame: an intact sharded Blosc
    array opens (a header check would refuse it: its first frame is one inner chunk). Its
    default index carries a CRC32C: a cut shard fails to read, with the one line that names it.
    zstd takes the buffer's length: a cut zstd chunk fails to decode, and is named."""
    from zarr.codecs import BloscCodec

    from chunkdic.errors import InputError
    from chunkdic.io.scan import open_scan
    from chunkdic.io.store import blosc_frame_bytes

    sharded = _array(tmp_path / "sharded.zarr", chunks=(16,) * 3, shards=(CHUNK,) * 3,
                     compressors=BloscCodec(cname="lz4", shuffle="bitshuffle"))
    assert blosc_frame_bytes(sharded) is None
    ref = open_scan(str(tmp_path / "sharded.zarr")).stored_refs()[0]
    assert np.array_equal(ref.read((slice(32, 64), slice(0, 32), slice(0, 32))), ramp(*np.mgrid[32:64, :32, :32]))
    cut_in_half(tmp_path / "sharded.zarr" / "c" / "1" / "0" / "0")
    ref = open_scan(str(tmp_path / "sharded.zarr")).stored_refs()[0]  # opens: not checked
    with pytest.raises(InputError, match=r"chunk \(1, 0, 0\) \(file .*sharded.zarr/c/1/0/0\) cannot be read"):
        ref.read((slice(32, 64), slice(0, 32), slice(0, 32)))

    zstd = _array(tmp_path / "zstd.zarr")  # zarr's default codec
    assert blosc_frame_bytes(zstd) is None
    cut_in_half(tmp_path / "zstd.zarr" / "c" / "1" / "0" / "0")
    ref = open_scan(str(tmp_path / "zstd.zarr")).stored_refs()[0]
    with pytest.raises(InputError, match=r"chunk \(1, 0, 0\) \(file .*zstd.zarr/c/1/0/0\) cannot be read"):
        ref.read((slice(32, 64), slice(0, 32), slice(0, 32)))

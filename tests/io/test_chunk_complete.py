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

"""Decompression bombs are refused before they are expanded: a zstd frame, a gzip or zlib stream
in a chunk, a TIFF page whose tags declare gigabytes (chunkdic.io.chunkread, io.formats.tiff)."""

from __future__ import annotations

import json
import subprocess
import sys
import tracemalloc

import numpy as np
import pytest
import zarr
from bombs import deflate_bomb, zstd_bomb

import chunkdic
from chunkdic.errors import InputError
from chunkdic.io.formats.anyscan import open_any
from chunkdic.io.handles import ArrayRef, forget_open_arrays

GiB = 1 << 30


def _peak(fn) -> int:
    """Peak bytes Python's allocator held while ``fn`` ran (bytes and bytearrays of decoders included)."""
    tracemalloc.start()
    try:
        fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


def _refused_small(ref: ArrayRef, match: str) -> None:
    def read():
        with pytest.raises(InputError, match=match) as err:
            ref.read((slice(0, 16), slice(0, 16), slice(0, 16)))
        assert "\n" not in str(err.value)
    assert _peak(read) < 4 << 20  # the chunk is 4 kB; the bomb 64 MiB to 4 GiB
    forget_open_arrays()


@pytest.mark.parametrize("fmt", [3, 2])
def test_a_zstd_chunk_declaring_gigabytes_is_refused_before_decoding(tmp_path, fmt):
    """A 128 kB zstd frame that decodes to 4 GiB in a chunk of 16³ bytes (Zarr v3 and v2)."""
    a = zarr.create_array(str(tmp_path / "a.zarr"), shape=(16, 16, 16), chunks=(16, 16, 16), dtype="uint8",
                          zarr_format=fmt, **({"compressors": zarr.codecs.ZstdCodec()} if fmt == 3 else
                                              {"compressors": {"id": "zstd"}}))
    a[...] = 1
    key = "c/0/0/0" if fmt == 3 else "0.0.0"
    bomb = zstd_bomb(4 * GiB)
    assert len(bomb) < 140_000
    (tmp_path / "a.zarr" / key).write_bytes(bomb)
    _refused_small(ArrayRef("zarr", str(tmp_path / "a.zarr"), "", (16, 16, 16), "uint8"),
                   "declares 4294967296 bytes, not the chunk's 4096")


@pytest.mark.parametrize("codec", ["gzip-v3", "zlib-v2", "gzip-v2"])
def test_a_deflate_chunk_is_decoded_into_its_own_size(tmp_path, codec):
    """gzip or zlib streams of 64 MiB in chunks of 4 kB: decoding stops at the chunk's size."""
    fmt = 3 if codec.endswith("v3") else 2
    comp = zarr.codecs.GzipCodec() if fmt == 3 else {"id": codec.split("-")[0]}
    a = zarr.create_array(str(tmp_path / "a.zarr"), shape=(16, 16, 16), chunks=(16, 16, 16), dtype="uint8",
                          zarr_format=fmt, compressors=comp)
    a[...] = 1
    key = "c/0/0/0" if fmt == 3 else "0.0.0"
    (tmp_path / "a.zarr" / key).write_bytes(deflate_bomb(64 << 20, gzip=codec.startswith("gzip")))
    _refused_small(ArrayRef("zarr", str(tmp_path / "a.zarr"), "", (16, 16, 16), "uint8"),
                   "decodes to more than the chunk's 4096 bytes")


def test_a_result_with_a_bomb_chunk_is_refused_when_opened(tmp_path):
    """A result's displacement chunk replaced by a zstd frame of 4 GiB: one line, nothing expanded."""
    rng = np.random.default_rng(0)
    f = rng.random((24, 24, 24)).astype(np.float32)
    chunkdic.correlate(f, np.roll(f, 1, axis=0), element_size=8, coarsest=0, output=str(tmp_path / "r.zarr"))
    meta = json.loads((tmp_path / "r.zarr/displacement/zarr.json").read_text())
    assert [c["name"] for c in meta["codecs"]][-1] == "zstd"  # what the bomb pretends to be
    chunk = next(p for p in (tmp_path / "r.zarr/displacement/c").rglob("*") if p.is_file())
    chunk.write_bytes(zstd_bomb(4 * GiB))

    def read():
        with pytest.raises(InputError, match="cannot be read.*declares 4294967296 bytes"):
            chunkdic.open_result(tmp_path / "r.zarr")
    assert _peak(read) < 16 << 20


def test_a_tiff_page_declaring_60000_squared_is_refused_from_its_tags(tmp_path):
    """Deflate pages whose tags say 60 000 x 60 000 (3.4 GiB each): refused from the tags, nothing decoded."""
    out = subprocess.run([sys.executable, "-c", _TIFF, str(tmp_path / "b.tif"), "60000"], capture_output=True)
    assert out.returncode == 0, out.stderr

    def read():
        with pytest.raises(InputError, match=r"compressed page of 60000 x 60000 uint8 \(3.4 GiB\)"):
            open_any(str(tmp_path / "b.tif"))  # a scan to ingest, or a mask read in place
    assert _peak(read) < 16 << 20


#: a deflate stack of 2 pages of 32², its size tags rewritten to N (the strips stay 1 kB)
_TIFF = r"""
import sys, struct, numpy as np, tifffile
path, n = sys.argv[1], int(sys.argv[2])
tifffile.imwrite(path, np.zeros((2, 32, 32), np.uint8), compression="zlib", metadata=None)
data = bytearray(open(path, "rb").read())
with tifffile.TiffFile(path) as t:
    for pg in t.pages:
        for k in pg.tags.values():
            if k.name in ("ImageWidth", "ImageLength", "RowsPerStrip"):
                struct.pack_into("<I", data, k.valueoffset, n)
open(path, "wb").write(bytes(data))
"""


@pytest.mark.slow
def test_pyramid_of_a_scan_with_a_4_gib_zstd_chunk_stays_small(tmp_path):
    """``chunkdic pyramid`` of a synthetic scan one of whose chunks is a 4 GiB zstd frame: exit 2,
    one error line, the scan unchanged, the process's peak RSS under 600 MB (it was above 3 GB)."""
    from chunkdic.synth import synthetic

    synthetic.synthesize(tmp_path / "s", (32, 32, 32), seed=1, chunks=16)
    (tmp_path / "s/ref.zarr/0/c/1/0/1").write_bytes(zstd_bomb(4 * GiB))
    before = sorted(p.name for p in (tmp_path / "s/ref.zarr").iterdir())
    wrap = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
            "print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); "
            "sys.stderr.write(r.stderr)")
    out = subprocess.run([sys.executable, "-c", wrap, sys.executable, "-m", "chunkdic", "pyramid",
                          str(tmp_path / "s/ref.zarr"), "--levels", "1"], capture_output=True, text=True)
    code, rss_kb = (int(v) for v in out.stdout.split())
    lines = out.stderr.strip().splitlines()
    assert code == 2 and lines[-1].startswith("chunkdic: error:") and "Traceback" not in out.stderr
    assert "declares 4294967296 bytes" in lines[-1]
    assert rss_kb < 600_000
    assert sorted(p.name for p in (tmp_path / "s/ref.zarr").iterdir()) == before

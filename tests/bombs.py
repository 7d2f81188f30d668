"""Decompression bombs: a few bytes that declare (and decode to) far more, made without ever
holding what they decode to. Shared by the tests and the sweep (tests/sweep/bad_inputs.py)."""

from __future__ import annotations

import zlib

#: the largest zstd block (RFC 8878, Block_Maximum_Size)
_ZSTD_BLOCK = 128 * 1024


def zstd_bomb(nbytes: int, value: int = 0) -> bytes:
    """One zstd frame that decodes to ``nbytes`` bytes of ``value``: a header declaring the size
    and run-length blocks of 4 bytes each (RFC 8878: 4 GiB in 128 KiB)."""
    out = bytearray(b"\x28\xb5\x2f\xfd")  # magic number
    out.append(0xE0)  # 8-byte content size, single segment, no checksum, no dictionary
    out += nbytes.to_bytes(8, "little")
    left = nbytes
    while left > 0:
        size = min(left, _ZSTD_BLOCK)
        left -= size
        header = int(left == 0) | (1 << 1) | (size << 3)  # last block?, type RLE, size
        out += header.to_bytes(3, "little") + bytes([value])
    return bytes(out)


def deflate_bomb(nbytes: int, *, gzip: bool = False) -> bytes:
    """A zlib (or gzip) stream of ``nbytes`` zero bytes, compressed a megabyte at a time (about
    1 000:1: 4 GiB in 4 MB)."""
    c = zlib.compressobj(9, zlib.DEFLATED, 16 + zlib.MAX_WBITS if gzip else zlib.MAX_WBITS)
    block = bytes(1 << 20)
    parts = [c.compress(block) for _ in range(nbytes >> 20)]
    parts.append(c.compress(bytes(nbytes & ((1 << 20) - 1))))
    return b"".join(parts) + c.flush()

"""Raw binary scans: a header-less volume whose shape and dtype the user gives (``--shape``,
``--dtype``, ``--byte-order``, ``--offset``); the file size must match them exactly.

The reader reads rows with ``os.preadv`` into one buffer per slab.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ...errors import InputError
from .base import Layout, Reader, Source

DTYPES = ("uint8", "uint16", "int16", "uint32", "int32", "float32", "float64")


class Raw:
    """Any other file; needs ``layout.shape`` and ``layout.dtype``."""

    name = "raw"

    def can_open(self, path: Path, layout: Layout) -> bool:
        return path.is_file()

    def open(self, path: Path, layout: Layout) -> Source:
        return Source(path, _open_raw(path, layout.shape, layout.dtype, layout.byte_order, layout.offset))


def _parse_shape(shape) -> tuple[int, int, int]:
    if isinstance(shape, str):
        shape = [s for s in re.split(r"[,x ]+", shape.strip()) if s]
    try:
        out = tuple(int(s) for s in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape {shape!r} must be 3 integers Z,Y,X") from None
    if len(out) != 3 or min(out) < 1:
        raise InputError(f"shape {shape!r} must be 3 positive integers Z,Y,X")
    return out


def _open_raw(path: Path, shape, dtype, byte_order, offset):
    if shape is None or dtype is None:
        raise InputError(f"{path}: raw binary input needs --shape Z,Y,X and --dtype ({'|'.join(DTYPES)})")
    shape = _parse_shape(shape)
    name = np.dtype(dtype).name if not isinstance(dtype, str) else dtype.strip().lower()
    if name not in DTYPES:
        raise InputError(f"raw dtype {dtype!r} not supported: use one of {', '.join(DTYPES)}")
    order = {"little": "<", "big": ">", "<": "<", ">": ">", "le": "<", "be": ">"}.get(str(byte_order).lower())
    if order is None:
        raise InputError(f"byte order {byte_order!r}: use little or big")
    offset = int(offset or 0)
    if offset < 0:
        raise InputError(f"header offset must be >= 0, got {offset}")
    fdtype = np.dtype(name).newbyteorder(order)
    size = path.stat().st_size
    expected = offset + int(np.prod(shape)) * fdtype.itemsize
    if size != expected:
        hint = ""
        payload = size - offset
        if payload > 0:
            fits = [d for d in DTYPES if payload == int(np.prod(shape)) * np.dtype(d).itemsize and d != name]
            if fits:
                hint = f"; the size matches --dtype {fits[0]}"
            elif size > expected and offset == 0:
                hint = f"; a {size - expected}-byte header? pass --offset {size - expected}"
        raise InputError(f"{path}: file has {size} bytes but shape {shape} {name} + offset {offset} needs "
                         f"{expected}{hint}")
    return RawReader(str(path), shape, fdtype, offset)


class RawReader(Reader):
    """Rows of a raw volume read with ``os.preadv`` into one buffer per slab.

    Not ``np.memmap``: a mapping kept by a worker counts every page it touched in the
    process's RSS, which Dask's nanny watches (the ``.npy`` reads of
    :class:`chunkdic.io.handles.ArrayRef` reached 4.3 GiB at 1024³ that way); explicit reads
    hold a worker to its slab.
    """

    def __init__(self, path: str, shape, dtype: np.dtype, offset: int):
        self.path, self.shape, self.file_dtype, self.offset = path, tuple(shape), np.dtype(dtype), int(offset)
        self.dtype = self.file_dtype.newbyteorder("=")
        self.label = path

    def _read(self, region):
        nz, ny, nx = self.shape
        zs, ys, xs = (r.indices(n) for r, n in zip(region, self.shape))
        row = nx * self.file_dtype.itemsize
        y0, y1 = ys[0], max(ys[0], ys[1])
        zr = range(*zs)
        out = np.empty((len(zr), y1 - y0, nx), self.file_dtype)
        with open(self.path, "rb", buffering=0) as f:
            fd = f.fileno()
            for i, z in enumerate(zr):
                start = self.offset + (z * ny + y0) * row
                want = (y1 - y0) * row
                buf = memoryview(out[i]).cast("B")
                got = 0
                while got < want:
                    n = os.preadv(fd, [buf[got:]], start + got)
                    if n <= 0:
                        raise InputError(f"{self.path}: unexpected end of file at z={z}")
                    got += n
        out = out[:, slice(None, None, ys[2]) if ys[2] != 1 else slice(None), slice(*xs)]
        return out.astype(self.dtype, copy=False)

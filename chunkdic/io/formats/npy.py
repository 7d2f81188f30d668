"""NumPy ``.npy`` scans, memory-mapped by each task for its slab."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputError
from .base import Layout, Reader, Source, check_scan_array


class Npy:
    name = "npy"

    def can_open(self, path: Path, layout: Layout) -> bool:
        return path.is_file() and path.suffix.lower() == ".npy"

    def open(self, path: Path, layout: Layout) -> Source:
        try:
            a = np.load(path, mmap_mode="r")
        except Exception as e:  # noqa: BLE001
            raise InputError(f"{path}: not a readable .npy file ({e})".splitlines()[0]) from None
        check_scan_array(str(path), a.shape, a.dtype)
        return Source(path, NpyReader(str(path), a.shape, a.dtype))


class NpyReader(Reader):
    def __init__(self, path: str, shape, dtype):
        self.path, self.shape, self.file_dtype = path, tuple(shape), np.dtype(dtype)
        self.dtype = self.file_dtype.newbyteorder("=")
        self.label = path

    def _read(self, region):
        a = np.load(self.path, mmap_mode="r")
        return np.array(a[region], dtype=self.dtype)

"""Haloed copies of the reference blocks: written by the ``M`` pass, read by every ``b`` pass.

A block task needs its core of ``f`` plus a one-voxel halo (central differences of ``f``
at the block's faces). Read from the scan, that halo costs whole neighbouring chunks:
with blocks on the chunk grid, a 130³ read decodes 27 chunks of 128³ to use one of them
fully (measured on a blosc-lz4 uint16 array: 95 ms against 7 ms for the aligned 128³
read, as long as the interpolation of the block itself). The ``M`` pass reads every
block's haloed region once anyway; it keeps it as **one chunk** of a scratch Zarr array
(native dtype, uncompressed, like the B-spline coefficients: on a 512³ uint8 pair,
blocks of 128³, the ``b`` pass ran at 40.7 Mvoxel/s per core against 31.0 reading the
scan and 34.5 with a zstd-compressed copy, whose compression also slowed the ``M`` pass),
and the Gauss–Newton passes of the level read one chunk per block. The copy lives in the correlation's scratch directory
(shared with the workers, like the B-spline coefficients) and is deleted with the level.

A low-passed block of a scan level stored as 1- or 2-byte integers is kept **quantised to
16 bits** (``chunkdic.scratch-precision``: ``"uint16"``, the default; ``"float32"`` keeps it
exact): values on the grid ``offset + k * step``, ``step`` the power of two that maps the
dtype's range onto 0 … 65535 (1 grey level for 16-bit scans, 1/256 for 8-bit ones). A
Gaussian low-pass stays within the range of its input, so nothing is clipped; the grid is
the level's, not the block's, so results stay independent of the block size; and the
``M`` pass uses the same rounded values as the ``b`` passes. It halves the largest
scratch store of a level-0 run (17 GB of 35 at 2048³); its effect on the measured field
is in docs/engine.md ("Scratch disk"). Other levels and float scans stay float32.

When the disk cannot hold the run, the plan picks the compact layout
(:mod:`chunkdic.passes.scratchstore`): a 16× coarser grid, chunks compressed with
blosc zstd (0.55 of the bytes). Either way a task reads its chunk's file itself
(:func:`chunkdic.passes.scratchstore.read_chunk`: 2 ms for a 130³ chunk, 18 ms through zarr).

Retried tasks are safe: a task writes exactly one whole chunk, always the same values.

A copy whose every chunk the ``M`` pass wrote is marked complete (:data:`COMPLETE`, a file
in the store written after the pass). A resumed run adopts the copy of the interrupted
run's scratch (:meth:`HaloedBlocks.adopt`) only when it is so marked, laid out as this run
would lay it out, and every chunk file is whole (:func:`chunkdic.io.store.chunk_file_is_whole`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import config
from ..kernels.quantize import quantize_u16
from . import scratchstore

__all__ = ["HaloedBlocks", "COMPLETE"]

#: the file that marks a copy complete (every block's chunk written)
COMPLETE = ".chunkdic-complete"


@dataclass(frozen=True)
class HaloedBlocks:
    """Per-block haloed regions of ``f`` in a 6-D Zarr array, one chunk per block.

    Parameters
    ----------
    path : str
        Zarr array of shape ``grid + chunk``, chunks ``(1, 1, 1) + chunk``.
    grid : tuple of 3 int
        Number of blocks along ``(z, y, x)``.
    chunk : tuple of 3 int
        Largest haloed region shape, voxels; smaller (edge) regions sit at the chunk's
        origin, zero-padded.
    dtype : str
        Dtype of the scan level (stored as read, converted by the reader).
    offset, step : float
        The 16-bit grid of a quantised store (``step`` 0: stored as ``dtype``).
    compressed : bool
        Chunks compressed (the compact layout, :mod:`chunkdic.passes.scratchstore`).
    """

    path: str
    grid: tuple[int, int, int]
    chunk: tuple[int, int, int]
    dtype: str
    offset: float = 0.0
    step: float = 0.0
    compressed: bool = False

    @property
    def quantized(self) -> bool:
        return self.step > 0

    @classmethod
    def create(cls, path: Path, grid, chunk, dtype, *, quantize_from=None) -> "HaloedBlocks":
        """Create the (empty) store on the client: metadata only.

        ``quantize_from``: the scan level's dtype when float blocks (``dtype``) of it are to
        be stored quantised (module docstring); ignored unless an integer of 1 or 2 bytes.
        """
        import zarr

        blocks, stored, codecs = cls._layout(path, grid, chunk, dtype, quantize_from)
        Path(path, COMPLETE).unlink(missing_ok=True)
        zarr.create_array(str(path), shape=blocks.grid + blocks.chunk, chunks=(1, 1, 1) + blocks.chunk, dtype=stored,
                          compressors=codecs, fill_value=0, zarr_format=3, overwrite=True)
        return blocks

    @classmethod
    def _layout(cls, path, grid, chunk, dtype, quantize_from):
        """The store :meth:`create` makes: its descriptor, stored dtype and codecs."""
        grid, chunk, dtype = tuple(map(int, grid)), tuple(map(int, chunk)), np.dtype(dtype)
        offset, step = quantization(quantize_from) if dtype.kind == "f" else (0.0, 0.0)
        stored = np.dtype("uint16") if step > 0 else dtype
        codecs = scratchstore.compressors("f", stored.itemsize) if step > 0 else None
        return cls(str(path), grid, chunk, dtype.name, offset, step, codecs is not None), stored, codecs

    @classmethod
    def adopt(cls, path: Path, grid, chunk, dtype, *, quantize_from=None) -> "HaloedBlocks | None":
        """The copy an interrupted run's ``M`` pass completed at ``path``, when it is the one
        :meth:`create` would make now (same grid, chunk, dtype, 16-bit grid and codecs),
        marked complete, and every block's chunk file is whole; else None."""
        import zarr

        from ..io.store import chunk_file_is_whole

        blocks, stored, codecs = cls._layout(path, grid, chunk, dtype, quantize_from)
        try:
            if not Path(path, COMPLETE).is_file():
                return None
            record = Path(path, COMPLETE).read_text()
            if record != blocks._record():
                return None
            arr = zarr.open_array(str(path), mode="r")
            if (tuple(arr.shape) != blocks.grid + blocks.chunk or tuple(arr.chunks) != (1, 1, 1) + blocks.chunk
                    or arr.dtype != stored or bool(tuple(arr.compressors)) != (codecs is not None)):
                return None
            whole = all(chunk_file_is_whole(arr, tuple(index) + (0, 0, 0)) for index in np.ndindex(*blocks.grid))
        except Exception:  # noqa: BLE001 - anything unreadable is "build it again"
            return None
        return blocks if whole else None

    def _record(self) -> str:
        return json.dumps({"grid": self.grid, "chunk": self.chunk, "dtype": self.dtype, "offset": self.offset,
                           "step": self.step, "compressed": self.compressed})

    def unmark(self) -> None:
        """Client side, before a pass rewrites the copy: no longer complete."""
        Path(self.path, COMPLETE).unlink(missing_ok=True)

    def mark_complete(self) -> None:
        """Client side, after the ``M`` pass: every block's chunk is written."""
        tmp = Path(self.path, COMPLETE + ".tmp")
        tmp.write_text(self._record())
        os.replace(tmp, Path(self.path, COMPLETE))

    def write(self, index: tuple[int, int, int], region: np.ndarray) -> np.ndarray:
        """Task side: store block ``index``'s haloed region (one whole chunk); returns the
        values as :meth:`read` will give them back (the region itself unless quantised)."""
        import zarr

        stored = region
        if self.quantized:  # rounded in float64, as the grid was chosen (kernels.quantize)
            stored, region = quantize_u16(region, self.offset, self.step, wide=True)
        padded = np.zeros(self.chunk, stored.dtype)
        padded[tuple(slice(0, n) for n in stored.shape)] = stored
        arr = zarr.open_array(store=self.path, mode="r+").with_config({"write_empty_chunks": True})
        arr[tuple(index)] = padded
        return region

    def read(self, index: tuple[int, int, int], shape: tuple[int, int, int]) -> np.ndarray:
        """Task side: block ``index``'s haloed region of ``shape`` voxels (stored dtype, or
        float32 when quantised)."""
        stored = np.dtype("uint16") if self.quantized else np.dtype(self.dtype)
        # the chunk's file read directly: 3-6x faster than through zarr (scratchstore.read_chunk)
        chunk = scratchstore.read_chunk(self.path, tuple(index) + (0, 0, 0), (1, 1, 1) + self.chunk, stored,
                                        self.compressed)[0, 0, 0]
        chunk = chunk[tuple(slice(0, n) for n in shape)]
        return self._dequantize(chunk) if self.quantized else chunk

    def _dequantize(self, q: np.ndarray) -> np.ndarray:
        out = q.astype(np.float32)  # offset and step are exact in float32 (powers of two, integers)
        out *= np.float32(self.step)
        out += np.float32(self.offset)
        return out


def quantization(dtype) -> tuple[float, float]:
    """``(offset, step)`` of the 16-bit grid for low-passed values of an integer ``dtype`` of
    1 or 2 bytes (``step`` a power of two, 65535 steps cover the dtype's range; the compact
    layout's steps are :data:`~chunkdic.passes.scratchstore.COMPACT_STEP` times larger);
    ``(0, 0)``: not quantised (other dtypes, or ``chunkdic.scratch-precision`` is ``"float32"``)."""

    if dtype is None or config.get("scratch-precision") != "uint16":
        return 0.0, 0.0
    dtype = np.dtype(dtype)
    if dtype.kind not in "iu" or dtype.itemsize > 2:
        return 0.0, 0.0
    info = np.iinfo(dtype)
    step = 2.0 ** np.ceil(np.log2((float(info.max) - float(info.min)) / 65535.0))
    return float(info.min), float(step * scratchstore.step_factor())

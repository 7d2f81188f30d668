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

Retried tasks are safe: a task writes exactly one whole chunk, always the same values.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.handles import open_zarr_array

__all__ = ["HaloedBlocks"]


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
    """

    path: str
    grid: tuple[int, int, int]
    chunk: tuple[int, int, int]
    dtype: str

    @classmethod
    def create(cls, path: Path, grid, chunk, dtype) -> "HaloedBlocks":
        """Create the (empty) store on the client: metadata only."""
        import zarr

        grid, chunk, dtype = tuple(map(int, grid)), tuple(map(int, chunk)), np.dtype(dtype)
        zarr.create_array(str(path), shape=grid + chunk, chunks=(1, 1, 1) + chunk, dtype=dtype,
                          compressors=None, fill_value=0, zarr_format=3, overwrite=True)
        return cls(str(path), grid, chunk, dtype.name)

    def write(self, index: tuple[int, int, int], region: np.ndarray) -> None:
        """Task side: store block ``index``'s haloed region (one whole chunk)."""
        import zarr

        padded = np.zeros(self.chunk, self.dtype)
        padded[tuple(slice(0, n) for n in region.shape)] = region
        arr = zarr.open_array(store=self.path, mode="r+").with_config({"write_empty_chunks": True})
        arr[tuple(index)] = padded

    def read(self, index: tuple[int, int, int], shape: tuple[int, int, int]) -> np.ndarray:
        """Task side: block ``index``'s haloed region of ``shape`` voxels, stored dtype."""
        chunk = np.asarray(open_zarr_array(self.path, "")[tuple(index)])
        return chunk[tuple(slice(0, n) for n in shape)]

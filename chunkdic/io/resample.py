"""A scan resampled onto another voxel size, chunk by chunk (``chunkdic ingest --resample``).

Two scans compared voxel to voxel must share their voxel size
(:func:`chunkdic.io.units.check_voxel_sizes`); a specimen rescanned at 21 µm is brought onto
the 20 µm grid of its reference by ingesting it with ``--resample 20um``. Voxel ``j`` of the
new grid has its centre at ``j * new`` (shared/DESIGN.md: voxel centres at ``i * size``),
that is at coordinate ``j * new / old`` of the source, and takes the source's trilinear
interpolation there. Trilinear, not the correlation's cubic B-spline: its weights are
positive, so no new extreme grey level appears and integer scans stay in their range (the
interpolation averages neighbouring voxels, and so lowers the scan's noise somewhat).

Out of core: each output chunk is one task that reads the source window it needs (one voxel
of margin) through a small picklable reader.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError

__all__ = ["resampled_shape", "resampled"]


def resampled_shape(shape, ratio) -> tuple[int, int, int]:
    """Voxels per axis of the new grid: every centre ``j * ratio`` within the source's ``0 … n - 1``."""
    return tuple(int(math.floor((n - 1) / r + 1e-9)) + 1 for n, r in zip(shape, ratio))


def _block(source, ratio, dtype, block_info=None) -> np.ndarray:
    import scipy.ndimage as ndi

    loc = block_info[None]["array-location"]
    axes = [np.arange(a, b) * r for (a, b), r in zip(loc, ratio)]
    lo = [int(math.floor(ax[0])) for ax in axes]
    hi = [min(int(math.floor(ax[-1])) + 2, n) for ax, n in zip(axes, source.shape)]
    window = np.asarray(source[tuple(slice(a, b) for a, b in zip(lo, hi))], dtype=np.float64)
    grid = np.meshgrid(*(ax - a for ax, a in zip(axes, lo)), indexing="ij", sparse=False)
    out = ndi.map_coordinates(window, grid, order=1, mode="nearest")
    if np.dtype(dtype).kind in "ui":
        info = np.iinfo(dtype)
        out = np.clip(np.rint(out), info.min, info.max)
    return out.astype(dtype)


def resampled(source, ratio, chunks):
    """The scan ``source`` on a grid of voxels ``ratio`` times the source's (per axis), lazily.

    Parameters
    ----------
    source : array-like
        Picklable, sliceable (``source[z0:z1, y0:y1, x0:x1]`` gives a NumPy array), with
        ``shape`` and ``dtype``: a format reader (:mod:`chunkdic.io.formats`) or a
        :class:`chunkdic.io.handles.RefReader`.
    ratio : tuple of 3 float
        New voxel size over the source's, per axis (z, y, x).
    chunks : tuple of 3 int
        Chunk shape of the new grid (one task each).

    Returns
    -------
    dask.array.Array
        Shape :func:`resampled_shape`, the source's dtype.
    """
    import dask.array as da
    from dask.base import tokenize

    ratio = tuple(float(r) for r in ratio)
    if not all(math.isfinite(r) and r > 0 for r in ratio):
        raise InputError(f"--resample: the ratio of the voxel sizes {ratio} is not a positive number")
    shape = resampled_shape(source.shape, ratio)
    if min(shape) < 2:
        raise InputError(f"--resample: the scan {tuple(source.shape)} would have {shape} voxels on the new grid")
    dtype = np.dtype(source.dtype)
    out_chunks = da.core.normalize_chunks(tuple(min(c, n) for c, n in zip(chunks, shape)), shape)
    return da.map_blocks(_block, source, ratio, dtype, chunks=out_chunks, dtype=dtype, meta=np.empty((0, 0, 0), dtype),
                         name="resample-" + tokenize(source, ratio, out_chunks))

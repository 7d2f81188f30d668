"""Missing pyramid levels of a scan written to scratch by runner tasks, chunk by chunk.

:meth:`chunkdic.io.scan.Scan.refs` gives the correlation its levels on disk. A level that
is not stored is built here from the finest level already on disk below it (stored, or
written to scratch just before): each task reads the ``2^d``-times larger region of that
source it needs (by path, an :class:`~chunkdic.io.handles.ArrayRef`), sums it ``d`` times
2x2x2 (:func:`chunkdic.io.coarsen.coarsen_block`, the kernel of :func:`~chunkdic.io.coarsen.coarsen_sum`,
each step in that level's dtype, so values are those of the lazy
:meth:`~chunkdic.io.scan.Scan.level`, bit for bit) and writes its own whole chunks.

Not a Dask graph of :func:`~chunkdic.io.coarsen.coarsen_sum` written by
:func:`~chunkdic.io.store.store_array`: importing ``dask.array`` costs ~1 s (it imports
xarray and pandas when they are installed), which a correlation of two Zarr scans
without stored levels paid inside the call (1.5 s for the first ``refs([0, 1, 2, 3])`` of
a 300³ scan, 0.25 s for the same work once imported). The runner's tasks need no graph.

Levels are built one after the other, each from the one just written: a level read back
costs ``1/8`` (``1/4`` after widening) of its source, and measured on 300³ uint16 this was
as fast as summing several levels in one task (docs/scans.md, "Scratch levels").
"""

from __future__ import annotations

import itertools

import numpy as np

from .coarsen import coarsen_block
from .handles import ArrayRef, forget_open_arrays
from .levels import create_level, mark_complete
from .store import check_write_alignment, chunk_shape_for, write_region

Region = tuple[slice, slice, slice]


def coarsen_task(src: ArrayRef, out: ArrayRef, depth: int, dtypes: tuple[str, ...], region: Region) -> int:
    """Task: ``region`` (slices of the level ``depth`` steps below ``src``) summed from ``src``.

    Reads the ``2^depth`` larger region of ``src`` (to its end for a region ending at the
    end of ``out``: the trailing voxels that every step trims), sums it ``depth`` times
    2x2x2 in ``dtypes`` (one per step) and writes it into ``out``; the region covers whole
    chunks of ``out``, so concurrent tasks never share one. Returns the voxels written.
    """
    f = 2**depth
    grown = tuple(slice(r.start * f, n if r.stop == m else r.stop * f)
                  for r, n, m in zip(region, src.shape, out.shape))
    data = src.read(grown)
    for dtype in dtypes:
        data = coarsen_block(data, dtype)
    if data.size:
        write_region(out.path, out.key, region, data)
    return int(data.size)


def task_regions(shape, chunk_shape) -> list[Region]:
    """One region per chunk of an array of ``shape`` (at least one, for an empty axis)."""
    starts = [range(0, max(int(n), 1), int(c)) for n, c in zip(shape, chunk_shape)]
    return [tuple(slice(a, min(a + int(c), int(n))) for a, c, n in zip(corner, chunk_shape, shape))
            for corner in itertools.product(*starts)]


def build_level(group: str, s: int, src: ArrayRef, depth: int, dtypes, runner, chunk_shape=None) -> ArrayRef:
    """Write level ``s`` of scratch group ``group`` from ``src`` (level ``s - depth``) by tasks.

    Parameters
    ----------
    group : str
        Path of the scratch Zarr group.
    s : int
        Level written (array ``"s"`` of ``group``).
    src : ArrayRef
        Level ``s - depth`` of the same scan, on disk.
    depth : int
        Pyramid steps from ``src`` to level ``s`` (>= 1).
    dtypes : sequence of dtype-like
        Dtype of each step's result (:meth:`chunkdic.io.scan.Scan.dtype` of levels
        ``s - depth + 1 .. s``): the last is level ``s``'s.
    runner : ThreadRunner or DistributedRunner
        Where the tasks run (:mod:`chunkdic.scheduler`).
    chunk_shape : tuple of 3 int, optional
        Chunks of the level; default ``chunkdic.chunk-size`` (clipped to the shape).

    Returns
    -------
    ArrayRef
        The level, marked complete.
    """
    dtypes = tuple(np.dtype(d).name for d in dtypes)
    if depth < 1 or len(dtypes) != depth:
        raise ValueError(f"depth {depth} needs one dtype per step, got {dtypes}")
    shape = tuple(int(n) // 2**depth for n in src.shape)
    chunk_shape = chunk_shape_for(shape, chunk_shape)
    create_level(group, s, shape, dtypes[-1], chunk_shape)
    forget_open_arrays()  # a handle cached for an earlier array of that name
    out = ArrayRef("zarr", str(group), str(s), shape, dtypes[-1])
    regions = task_regions(shape, chunk_shape)
    # each task owns whole chunks by construction; checked as every writer of chunkdic does
    check_write_alignment(region_chunks(regions, shape), shape, chunk_shape, name=f"{group}/{s}")
    for _ in runner.map_unordered(coarsen_task, [(src, out, depth, dtypes, r) for r in regions]):
        pass
    mark_complete(group, s)
    return out


def region_chunks(regions, shape) -> tuple[tuple[int, ...], ...]:
    """The Dask-style ``chunks`` of the regions' grid (for :func:`check_write_alignment`)."""
    out = []
    for axis, n in enumerate(shape):
        edges = sorted({(r[axis].start, r[axis].stop) for r in regions})
        out.append(tuple(b - a for a, b in edges) if n else (0,))
    return tuple(out)

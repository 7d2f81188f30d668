"""Level arrays of a stored scan group: created flagged incomplete, filled, marked complete.

Every level array ``"s"`` of a scan group is created with
``attrs["chunkdic"] = {"level": s, "complete": False}``, filled region by region by Dask
tasks that each own whole Zarr chunks (:mod:`chunkdic.io.store`), and only then marked
``complete``; readers (:mod:`chunkdic.io.scan`) ignore levels that are not complete. Used
for scans (:mod:`chunkdic.io.scanwrite`, :mod:`chunkdic.io.pyramid`) and for the scratch levels
of :meth:`chunkdic.io.scan.Scan.refs`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .handles import ArrayRef, forget_open_arrays
from .owntree import remove
from .store import aligned, chunk_shape_for, compressors, store_array


def create_level(path: str, s: int, shape, dtype, chunk_shape):
    """(Re)create level array ``s`` of group ``path``, flagged incomplete."""
    import zarr

    remove(Path(path) / str(s))
    g = zarr.open_group(store=path, mode="r+")
    g.create_array(
        str(s), shape=tuple(int(n) for n in shape), dtype=np.dtype(dtype), chunks=tuple(chunk_shape),
        compressors=compressors(dtype), fill_value=0, dimension_names=("z", "y", "x"),
        attributes={"chunkdic": {"level": s, "complete": False}},
    )


def mark_complete(path: str, s: int) -> None:
    import zarr

    arr = zarr.open_array(store=path, path=str(s), mode="r+")
    arr.update_attributes({"chunkdic": {"level": s, "complete": True}})


def write_level(path: str, s: int, data, chunk_shape=None, progress=None, start=0.0, end=1.0) -> ArrayRef:
    """Create level ``s`` in group ``path``, store ``data`` chunk by chunk, mark complete.

    ``data`` is a Dask array (written by tasks, :func:`chunkdic.io.store.store_array`) or an
    array already in this process's memory (a NumPy array, an in-memory Zarr array),
    written from here chunk by chunk: wrapping it in a Dask graph would ship the whole
    array to a distributed scheduler inside the graph.
    """
    chunk_shape = chunk_shape_for(data.shape, chunk_shape)
    create_level(path, s, data.shape, data.dtype, chunk_shape)
    if hasattr(data, "dask"):
        store_array(aligned(data, chunk_shape), path, str(s), progress, start, end)
    else:
        _write_from_memory(data, path, str(s), chunk_shape, progress, start, end)
    mark_complete(path, s)
    forget_open_arrays()
    return ArrayRef("zarr", str(path), str(s), tuple(int(n) for n in data.shape), np.dtype(data.dtype).name)


def _write_from_memory(data, path: str, key: str, chunk_shape, progress, start: float, end: float) -> None:
    """Write an in-memory array into ``path``/``key`` one chunk row (z slab) at a time."""
    import zarr

    arr = zarr.open_array(store=path, path=key, mode="r+").with_config({"write_empty_chunks": True})
    nz = data.shape[0]
    for z0 in range(0, nz, chunk_shape[0]):
        z1 = min(z0 + chunk_shape[0], nz)
        arr[z0:z1] = np.asarray(data[z0:z1])
        if progress is not None:
            progress(start + (end - start) * z1 / nz)


def check_levels(shape, levels: int) -> None:
    if levels < 0:
        raise InputError(f"levels must be >= 0, got {levels}")
    deepest = 0
    n = min(shape)
    while n // 2 >= 1:
        n //= 2
        deepest += 1
    if levels > deepest:
        raise InputError(f"{levels} pyramid levels requested but a scan of shape {tuple(shape)} "
                         f"allows at most {deepest} (level {levels} would be empty)")

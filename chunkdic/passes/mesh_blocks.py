"""``M`` of a level summed into node blocks: the ``M`` pass of a mesh whose data do not fit the client.

A level whose mesh data go to blocks (``chunkdic.mesh-data``, the plan's
``mesh_blocks_from``; docs/distributed.md, "Mesh data beyond one process") never holds the
whole stencil of ``M`` in the client: each block's partial stencil (its nodes ``e0 … e1``,
float32 half, as the client's stencil holds it) and its brightness cells' couplings are
written as they arrive, one whole chunk per block, into Zarr stores under the level's
scratch; the node blocks (unions of the passes' voxel blocks, as large as a task's memory
allows: :func:`~chunkdic.solve.nodeblocks.node_block_elements`) are then the partials with
the next blocks' first planes added, held by the level's holder: persisted on the workers
of a cluster (:func:`~chunkdic.solve.nodeblocks.fold_faces`), or, with the embedded
scheduler, each block with its halo summed straight into a file
(:meth:`~chunkdic.solve.haloedfiles.HaloedFiles.from_partials`) for the
:class:`~chunkdic.solve.partitioned.PartitionedSolver`.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from ..io.owntree import remove
from .. import config
from ..mesh import Mesh
from ..scheduler import release_freed_memory, threads_of

# dask.array (and the node blocks, built on it) are imported by the levels that use them:
# a correlation whose mesh data stay in the client never loads it (about 1 s;
# tests/io/test_scan.py)


def in_blocks(mesh: Mesh) -> bool:
    """Whether this level's mesh data go to node blocks (``chunkdic.mesh-data`` and the plan)."""
    mode = config.get("mesh-data")
    if mode == "blocks":
        return True
    if mode == "client":
        return False
    start = config.get("mesh-blocks-from")
    return start is not None and int(np.prod(mesh.nodes_shape)) >= int(start)


def holder_for(runner, directory: Path):
    """Where node blocks live: the workers of a ``distributed`` runner, else (or where the plan
    puts them on disk, ``chunkdic.mesh-blocks-on``) files in ``directory``."""
    from ..solve.nodeblocks import DiskHolder, WorkerHolder

    client = getattr(runner, "client", None)
    if client is not None and config.get("mesh-blocks-on") != "disk":
        return WorkerHolder(client)
    return DiskHolder(directory, threads_of(None)[0])


class BlockedMatrix:
    """The ``M`` pass's sums into node blocks (module docstring).

    Parameters
    ----------
    mesh : Mesh
    block_elements : int
        Elements per block side (the passes' blocks).
    cell : int
        Elements per side of a brightness cell (1: no cells).
    holder
        Where the node blocks go (:func:`holder_for`).
    directory : Path
        Where the partials are written (removed by :meth:`close`).
    """

    def __init__(self, mesh: Mesh, block_elements: int, cell: int, holder, directory: Path):
        import zarr

        from ..solve.nodeblocks import extended_chunks, node_block_elements, node_chunks

        self.holder, self.directory, self.cell = holder, Path(directory), int(cell)
        m = int(block_elements)
        # the partials come per voxel block; the node blocks are unions of voxel blocks, as
        # large as a task's memory allows (nodeblocks.node_block_elements)
        self.chunks = node_chunks(mesh.nodes_shape, node_block_elements(mesh.shape, m, holder.tasks))
        voxel_chunks = node_chunks(mesh.nodes_shape, m)
        self.ext = extended_chunks(voxel_chunks)
        self.directory.mkdir(parents=True, exist_ok=True)
        # flat chunk keys: the stores are removed once the node blocks are made, and a nested
        # layout's directories cost more to remove than the chunks (1.5 ms each here)
        create = functools.partial(zarr.create_array, dtype=np.float32, fill_value=0, compressors=None,
                                   zarr_format=3, chunk_key_encoding={"name": "default", "separator": "."})
        self._partials = create(str(self.directory / "m_partials.zarr"),
                                shape=tuple(sum(e) for e in self.ext) + (14, 3, 3), chunks=(m + 1,) * 3 + (14, 3, 3))
        self._cells = None
        if self.cell > 1:
            k = self.cell
            n_cells = tuple(-(-n // k) for n in mesh.shape)
            self.voxel_cell_chunks = _cell_chunks(voxel_chunks, n_cells, k)
            self.cell_chunks = _cell_chunks(self.chunks, n_cells, k)
            self._cells = create(str(self.directory / "m_cells.zarr"), shape=n_cells + (k + 1,) * 3 + (3, 4),
                                 chunks=tuple(max(c) for c in self.voxel_cell_chunks) + (k + 1,) * 3 + (3, 4))
        self._m = m
        #: with the blocks on disk, their haloed files (summed from the partials by :meth:`stencil`)
        self._files = None

    def add(self, blk, part: np.ndarray, block_cells: np.ndarray | None) -> None:
        """One block's partial stencil ``part`` (its nodes ``e0 … e1``, 27 offsets, float64) and cells."""
        start = [(e0 // self._m) * (self._m + 1) for e0, _ in blk.elements]
        region = tuple(slice(s, s + n) for s, n in zip(start, part.shape[:3]))
        self._partials[region] = part[..., 13:, :, :].astype(np.float32)
        if self._cells is not None:
            first = [e0 // self.cell for e0, _ in blk.elements]
            self._cells[tuple(slice(c, c + n) for c, n in zip(first, block_cells.shape[:3]))] = block_cells

    def stencil(self):
        """The half stencil in node blocks, held (dask array, shape (nz, ny, nx, 14, 3, 3), float32)."""
        import dask.array as da

        from ..solve.haloedfiles import HaloedFiles
        from ..solve.nodeblocks import fold_faces

        if self.holder.where == "disk":
            self._files = HaloedFiles.from_partials(
                self._partials, self._m, self.chunks, self._cells, None if self._cells is None else self.cell_chunks,
                self.cell, self.holder.directory / "haloed", self.holder.threads)
            release_freed_memory()  # the reads' buffers, freed in the threads' heaps
            return self._files.array()
        partials = da.from_zarr(self._partials, chunks=self.ext + ((14,), (3,), (3,)))
        return self.holder.hold(fold_faces(partials).rechunk(self.chunks + ((14,), (3,), (3,))), "stencil")

    def cells(self):
        """The brightness cells' couplings, chunked by the cells of each node block, held (dask array)."""
        import dask.array as da

        if self._cells is None:
            return None
        if self._files is not None:
            return self._files.cells_array()
        trailing = tuple((n,) for n in self._cells.shape[3:])
        cells = da.from_zarr(self._cells, chunks=self.voxel_cell_chunks + trailing)
        return self.holder.hold(cells.rechunk(self.cell_chunks + trailing), "cells")

    def solver(self, stencil, *, cells=None, cell: int = 1):
        """The :class:`~chunkdic.solve.partitioned.PartitionedSolver` of the blocks
        (:func:`~chunkdic.method.operator.build_operator`'s ``make_solver``)."""
        from ..solve.partitioned import PartitionedSolver

        solver = PartitionedSolver(stencil, self.holder, cells=cells, cell=cell, files=self._files)
        release_freed_memory()  # the sweeps' blocks, freed in the threads' heaps
        return solver

    def close(self) -> None:
        """Remove the partials (the held node blocks stay with the holder)."""
        remove(self.directory)


def _cell_chunks(chunks, n_cells, k: int) -> tuple:
    """The brightness cells of each node block of ``chunks`` (blocks hold whole cells): per axis."""
    return tuple(tuple(-(-c // k) for c in axis[:-1]) + (n - sum(-(-c // k) for c in axis[:-1]),)
                 for axis, n in zip(chunks, n_cells))

"""The node blocks' haloed stencils in files, for the products of a solve whose vectors stay in the process.

With the embedded scheduler, a level whose mesh data go to node blocks keeps the stencil
of ``M`` (504 B per node) and the brightness cells' couplings on the scratch disk, and
CG's vectors (24 B per node each) in the process: a product reads each block's stencil
once, with its one-node halo already in it (written once per level by
:class:`HaloedFiles`), and takes the vector's halo from the in-process vector, so that
nothing but the stencil moves and a CG iteration is one read of the stencil
(docs/distributed.md, "Mesh data beyond one process"). The blocks run as tasks of Dask's
threaded scheduler, each writing its own nodes of the product.
"""

from __future__ import annotations

import threading
from pathlib import Path

import dask
import dask.array as da
import numpy as np
from dask.threaded import get as threaded_get

from ..io.owntree import remove
from .nodeblocks import extended_chunks, haloed
from .stencil import _subtract_cells, half_matvec


def _starts(chunks) -> list[list[int]]:
    return [list(np.cumsum((0,) + tuple(axis))[:-1]) for axis in chunks]


class HaloedFiles:
    """Each node block's half stencil with its one-node halo (and its brightness cells'
    couplings) in one ``.npy`` file under ``directory``, and the block's product with an
    in-process vector.

    Parameters
    ----------
    stencil : dask.array.Array, shape (nz, ny, nx, 126), float32
        The half stencil in node blocks, its trailing axes flat (weak nodes held).
    cells : dask.array.Array, shape (cz, cy, cx, (k+1)³·12), float32, optional
        The cells' couplings, flat, chunked by the cells of each node block.
    cell : int
        ``k``, elements per side of a cell.
    directory : Path
        Created; removed by :meth:`close`.
    threads : int
        Blocks at once.
    """

    def __init__(self, stencil: da.Array, cells: da.Array | None, cell: int, directory, threads: int):
        self.directory, self.threads, self.cell = Path(directory), max(1, int(threads)), int(cell)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.nodes_shape = tuple(int(n) for n in stencil.shape[:3])
        chunks, grid = stencil.chunks[:3], stencil.numblocks[:3]
        self.blocks = [(i, j, k) for i in range(grid[0]) for j in range(grid[1]) for k in range(grid[2])]
        starts, ext = _starts(chunks), extended_chunks(chunks)
        #: per block: (its haloed nodes in the mesh, its own nodes in the mesh, its own nodes
        #: inside the haloed copy, its extended nodes in the mesh: those its cells touch)
        self.geometry = {}
        for b in self.blocks:
            own, halo, local, extended = [], [], [], []
            for a, i in enumerate(b):
                lo, n = int(starts[a][i]), int(chunks[a][i])
                h0, h1 = max(lo - 1, 0), min(lo + n + 1, self.nodes_shape[a])
                own.append(slice(lo, lo + n))
                halo.append(slice(h0, h1))
                local.append(slice(lo - h0, lo - h0 + n))
                extended.append(slice(lo, lo + int(ext[a][i])))
            self.geometry[b] = tuple(map(tuple, (halo, own, local, extended)))
        self._lock = threading.Lock()
        saves = [haloed(stencil, 1).map_blocks(_save_block, self.directory, "stencil", chunks=(1,) * 4,
                                               dtype=np.int8)]
        if cells is not None:
            saves.append(cells.map_blocks(_save_block, self.directory, "cells", chunks=(1,) * 4, dtype=np.int8))
        self.with_cells = cells is not None
        with dask.config.set(scheduler="threads", num_workers=self.threads):
            dask.compute(*saves)

    def _path(self, name: str, block) -> Path:
        return self.directory / f"{name}-{block[0]}-{block[1]}-{block[2]}.npy"

    def product(self, x: np.ndarray, out: np.ndarray, cells: bool = True) -> np.ndarray:
        """``out = (M - Σ_c W_c W_cᵀ) x`` (the cells' term when asked), ``x`` and ``out``
        (nz, ny, nx, 3) float64 in the process: one task per block, each its own nodes of
        ``M x`` from its haloed stencil; then the cells' terms, which reach the next
        block's first planes, added under a lock."""
        self._run(self._stencil_block, x, out)
        if cells and self.with_cells:
            self._run(self._cells_block, x, out)
        return out

    def _run(self, fn, x, out) -> None:
        # a plain graph: the in-process vectors are the closures', not arguments to hash
        graph = {("block", b): (fn, b, x, out) for b in self.blocks}
        threaded_get(graph, list(graph), num_workers=self.threads)

    def _stencil_block(self, b, x, out) -> None:
        halo, own, local, _ = self.geometry[b]
        H = np.asarray(np.load(self._path("stencil", b), mmap_mode="r"))
        xh = np.ascontiguousarray(x[halo])
        y = np.empty(xh.shape)
        half_matvec(H.reshape(H.shape[:3] + (14, 3, 3)), xh, y)
        out[own] = y[local]

    def _cells_block(self, b, x, out) -> None:
        extended = self.geometry[b][3]
        k = self.cell
        W = np.load(self._path("cells", b))
        y = np.zeros(x[extended].shape)
        _subtract_cells(W.reshape(W.shape[:3] + (k + 1,) * 3 + (3, 4)), k, np.ascontiguousarray(x[extended]), y)
        with self._lock:
            out[extended] += y

    def close(self) -> None:
        remove(self.directory)


def _save_block(b, directory, name, block_info=None):
    i, j, k = block_info[0]["chunk-location"][:3]
    np.save(Path(directory) / f"{name}-{i}-{j}-{k}.npy", np.ascontiguousarray(b))
    return np.zeros((1,) * b.ndim, np.int8)

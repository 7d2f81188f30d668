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

import math
import mmap
import threading
from pathlib import Path

import dask
import dask.array as da
import numpy as np
from dask.threaded import get as threaded_get

from ..io.owntree import remove
from .nodeblocks import extended_chunks, haloed
from .stencil import _subtract_cells, block_solve, half_matvec


#: mappings of the blocks' files kept open at most (each holds a file descriptor)
MAX_KEPT_MAPS = 256


def _starts(chunks) -> list[list[int]]:
    return [list(np.cumsum((0,) + tuple(axis))[:-1]) for axis in chunks]


class HaloedFiles:
    """Each node block's half stencil with its one-node halo (and its brightness cells'
    couplings) in one ``.npy`` file under ``directory``, and the block's product with an
    in-process vector. Made by :meth:`from_array` or :meth:`from_partials`.

    Parameters
    ----------
    chunks : tuple of tuple of int
        Nodes per block along each axis (:func:`~chunkdic.solve.nodeblocks.node_chunks`).
    cell_chunks : tuple of tuple of int, optional
        Brightness cells per block along each axis (None: no cells).
    cell : int
        ``k``, elements per side of a cell.
    directory : Path
        Created; removed by :meth:`close`.
    threads : int
        Blocks at once.
    """

    def __init__(self, chunks, cell_chunks, cell: int, directory, threads: int):
        self.directory, self.threads, self.cell = Path(directory), max(1, int(threads)), int(cell)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.chunks, self.cell_chunks = tuple(map(tuple, chunks)), cell_chunks
        self.nodes_shape = tuple(sum(axis) for axis in self.chunks)
        grid = tuple(len(axis) for axis in self.chunks)
        self.blocks = [(i, j, k) for i in range(grid[0]) for j in range(grid[1]) for k in range(grid[2])]
        starts, ext = _starts(self.chunks), extended_chunks(self.chunks)
        #: per block: (its haloed nodes in the mesh, its own nodes in the mesh, its own nodes
        #: inside the haloed copy, its extended nodes in the mesh: those its cells touch)
        self.geometry = {}
        for b in self.blocks:
            own, halo, local, extended = [], [], [], []
            for a, i in enumerate(b):
                lo, n = int(starts[a][i]), int(self.chunks[a][i])
                h0, h1 = max(lo - 1, 0), min(lo + n + 1, self.nodes_shape[a])
                own.append(slice(lo, lo + n))
                halo.append(slice(h0, h1))
                local.append(slice(lo - h0, lo - h0 + n))
                extended.append(slice(lo, lo + int(ext[a][i])))
            self.geometry[b] = tuple(map(tuple, (halo, own, local, extended)))
        self.with_cells, self.with_diagonal = cell_chunks is not None, False
        self._lock = threading.Lock()
        #: each thread's two vectors over its largest haloed block, used by every product: a
        #: product's copies come from no allocator (glibc's heaps would keep freed ones resident)
        self._buffers = threading.local()
        self._maps: dict = {}
        self._largest = max(math.prod(s.stop - s.start for s in self.geometry[b][0]) for b in self.blocks)

    @classmethod
    def from_array(cls, stencil: da.Array, cells: da.Array | None, cell: int, directory,
                   threads: int) -> "HaloedFiles":
        """The files of a half stencil in node blocks (dask array (nz, ny, nx, 126), float32)
        and its cells' couplings (dask array (cz, cy, cx, (k+1)³·12), chunked by the cells of
        each node block)."""
        files = cls(stencil.chunks[:3], None if cells is None else cells.chunks[:3], cell, directory, threads)
        saves = [haloed(stencil, 1).map_blocks(_save_block, files.directory, "stencil", chunks=(1,) * 4,
                                               dtype=np.int8)]
        if cells is not None:
            saves.append(cells.map_blocks(_save_block, files.directory, "cells", chunks=(1,) * 4, dtype=np.int8))
        with dask.config.set(scheduler="threads", num_workers=files.threads):
            dask.compute(*saves)
        return files

    @classmethod
    def from_partials(cls, partials, block_elements: int, chunks, cells=None, cell_chunks=None, cell: int = 1,
                      directory=".", threads: int = 1) -> "HaloedFiles":
        """The files summed straight from the ``M`` pass's partials: ``partials`` (a Zarr array,
        each voxel block of ``block_elements`` elements its extended nodes, (…, 14, 3, 3)
        float32) folded over each node block's haloed nodes (a node on a voxel block's first
        plane is also the previous block's last), so that a task holds one haloed block and
        the planes it adds. ``cells``: the Zarr array of the cells' couplings (cz, cy, cx,
        k+1, k+1, k+1, 3, 4); ``cell_chunks``: the cells of each node block."""
        files = cls(chunks, cell_chunks, cell, directory, threads)
        m = int(block_elements)
        voxel_blocks = tuple(-(-(n - 1) // m) for n in files.nodes_shape)
        cell_starts = None if cell_chunks is None else _starts(cell_chunks)

        def write(b):
            halo = files.geometry[b][0]
            np.save(files._path("stencil", b), _folded(partials, halo, m, voxel_blocks))
            if cell_starts is not None:
                region = tuple(slice(s[i], s[i] + c[i]) for s, c, i in zip(cell_starts, cell_chunks, b))
                W = np.asarray(cells[region])
                np.save(files._path("cells", b), W.reshape(W.shape[:3] + (-1,)))

        graph = {("write", b): (write, b) for b in files.blocks}
        threaded_get(graph, list(graph), num_workers=files.threads)
        return files

    def array(self) -> da.Array:
        """The half stencil (nz, ny, nx, 14, 3, 3), float32, in node blocks read from the files' own nodes."""
        return self._read("stencil", self.chunks, (14, 3, 3))

    def cells_array(self) -> da.Array | None:
        """The cells' couplings (cz, cy, cx, k+1, k+1, k+1, 3, 4), float32, one chunk per node
        block (None: no cells)."""
        return self._read("cells", self.cell_chunks, (self.cell + 1,) * 3 + (3, 4)) if self.with_cells else None

    def _read(self, name: str, chunks, trailing) -> da.Array:
        grid = da.zeros(tuple(sum(a) for a in chunks), chunks=chunks, dtype=np.int8)
        return grid.map_blocks(_read_own, self, name, trailing, new_axis=list(range(3, 3 + len(trailing))),
                               chunks=tuple(chunks) + tuple((n,) for n in trailing), dtype=np.float32)

    def __dask_tokenize__(self):
        return str(self.directory)

    def _path(self, name: str, block) -> Path:
        return self.directory / f"{name}-{block[0]}-{block[1]}-{block[2]}.npy"

    def product(self, x: np.ndarray, out: np.ndarray, cells: bool = True) -> np.ndarray:
        """``out = (M - Σ_c W_c W_cᵀ) x`` (the cells' term when asked), ``x`` and ``out``
        (nz, ny, nx, 3) float64 in the process: one task per block, each its own nodes of
        ``M x`` from its haloed stencil; then the cells' terms, which reach the next
        block's first planes, added under a lock."""
        # one plain graph (the in-process vectors are the tasks' arguments, not hashed): the
        # cells' tasks after every block's own nodes are written
        graph = {("stencil", b): (self._stencil_block, b, x, out) for b in self.blocks}
        if cells and self.with_cells:
            graph["written"] = (len, list(graph))
            graph.update({("cells", b): (self._cells_block, b, x, out, "written") for b in self.blocks})
        threaded_get(graph, list(graph), num_workers=self.threads)
        return out

    def save_diagonal(self, diagonal: da.Array) -> None:
        """Write block-Jacobi's diagonal blocks (dask array (nz, ny, nx, 1, 3, 3), float32, in
        this object's node blocks), one file per block: the preconditioner reads them block by
        block (:meth:`precondition`) instead of holding them in the process (36 B per node)."""
        save = diagonal.map_blocks(_save_block, self.directory, "diagonal", chunks=(1,) * diagonal.ndim,
                                   dtype=np.int8)
        with dask.config.set(scheduler="threads", num_workers=self.threads):
            save.compute()
        self.with_diagonal = True

    def precondition(self, r: np.ndarray, z: np.ndarray, Rd: np.ndarray, index, lam: float) -> np.ndarray:
        """``z = D⁻¹ r`` (:func:`~chunkdic.solve.stencil.block_solve`; ``D`` the diagonal blocks
        of :meth:`save_diagonal` plus ``lam`` times the penalty's ``Rd`` of each node's class,
        ``index``: the class indices per axis), ``r`` and ``z`` (nz, ny, nx, 3) float64 in the
        process: one task per block."""
        graph = {("diagonal", b): (self._jacobi_block, b, r, z, Rd, index, lam) for b in self.blocks}
        threaded_get(graph, list(graph), num_workers=self.threads)
        return z

    def _jacobi_block(self, b, r, z, Rd, index, lam) -> None:
        own = self.geometry[b][1]
        D = self._mapped("diagonal", b)
        rb, zb = self._vectors(own, r)
        block_solve(np.asarray(D), Rd, *(np.ascontiguousarray(i[s]) for i, s in zip(index, own)), lam, rb, zb)
        self._unmapped(D)
        z[own] = zb

    def _mapped(self, name: str, b) -> np.ndarray:
        """The block's file memory-mapped: kept for the next products when the blocks are few
        (opening one costs about 0.4 ms, and each mapping holds a file descriptor)."""
        key = (name, b)
        a = self._maps.get(key)
        if a is None:
            a = np.load(self._path(name, b), mmap_mode="r")
            if len(self.blocks) * (1 + self.with_cells + self.with_diagonal) <= MAX_KEPT_MAPS:
                self._maps[key] = a
        return a

    @staticmethod
    def _unmapped(a: np.ndarray) -> None:
        """The pages of a mapped block out of the process's resident memory (the page cache keeps
        them): a product holds the blocks it is reading, not every block it has read."""
        a._mmap.madvise(mmap.MADV_DONTNEED)

    def _vectors(self, region, x) -> tuple[np.ndarray, np.ndarray]:
        """This thread's buffers as ``x[region]`` and a vector of its shape (float64)."""
        buffers = getattr(self._buffers, "pair", None)
        if buffers is None:
            buffers = self._buffers.pair = (np.empty(3 * self._largest), np.empty(3 * self._largest))
        shape = tuple(s.stop - s.start for s in region) + (3,)
        xb, yb = (a[:math.prod(shape)].reshape(shape) for a in buffers)
        xb[...] = x[region]
        return xb, yb

    def _stencil_block(self, b, x, out) -> None:
        halo, own, local, _ = self.geometry[b]
        H = self._mapped("stencil", b)
        xh, y = self._vectors(halo, x)
        half_matvec(np.asarray(H).reshape(H.shape[:3] + (14, 3, 3)), xh, y)
        self._unmapped(H)
        out[own] = y[local]

    def _cells_block(self, b, x, out, _written=None) -> None:
        extended = self.geometry[b][3]
        k = self.cell
        W = self._mapped("cells", b)
        xe, y = self._vectors(extended, x)
        y[...] = 0.0
        _subtract_cells(np.asarray(W).reshape(W.shape[:3] + (k + 1,) * 3 + (3, 4)), k, xe, y)
        self._unmapped(W)
        with self._lock:
            out[extended] += y

    def close(self) -> None:
        self._maps.clear()
        remove(self.directory)


def _fold_positions(lo: int, hi: int, m: int, blocks: int):
    """Where the nodes ``lo … hi-1`` of an axis sit in the partials (each voxel block of ``m``
    elements its ``m + 1`` extended nodes): their own block's plane, and for the nodes on a
    voxel block's first plane (but the first block's) which of them also sit as the previous
    block's last plane, and where."""
    n = np.arange(lo, hi)
    i = np.minimum(n // m, blocks - 1)
    primary = i * (m + 1) + (n - i * m)
    shared = np.flatnonzero((n % m == 0) & (n >= m) & (n // m <= blocks - 1))
    return primary, shared, (n[shared] // m - 1) * (m + 1) + m


def _folded(partials, region, m: int, blocks) -> np.ndarray:
    """The half stencil of the nodes ``region`` (three slices), (…, 126) float32: their
    partials added over the voxel blocks that share them (:func:`_fold_positions`), from one
    read of the partials those voxel blocks hold."""
    axes = [_fold_positions(s.start, s.stop, m, nb) for s, nb in zip(region, blocks)]
    lo = [int(min(a[0].min(), a[2].min() if len(a[2]) else a[0].min())) for a in axes]
    hi = [int(a[0].max()) + 1 for a in axes]
    read = np.asarray(partials[tuple(slice(a, b) for a, b in zip(lo, hi))])
    read = read.reshape(read.shape[:3] + (-1,))
    out = read[np.ix_(*(a[0] - o for a, o in zip(axes, lo)))]
    for pick in range(1, 8):  # every choice, per axis, of the own plane or the previous block's
        second = [(pick >> a) & 1 for a in range(3)]
        if any(s and not len(axes[a][1]) for a, s in enumerate(second)):
            continue
        rows = tuple((ax[2] if s else ax[0]) - o for ax, s, o in zip(axes, second, lo))
        where = tuple(ax[1] if s else np.arange(len(ax[0])) for ax, s in zip(axes, second))
        out[np.ix_(*where)] += read[np.ix_(*rows)]
    return out


def _read_own(placeholder, files, name, trailing, block_info=None):
    """The block's own nodes (or cells) from its file, their entries of shape ``trailing``."""
    b = tuple(block_info[0]["chunk-location"][:3])
    a = np.load(files._path(name, b), mmap_mode="r")
    if name == "stencil":
        a = a[files.geometry[b][2]]
    return np.array(a).reshape(a.shape[:3] + tuple(trailing))


def _save_block(b, directory, name, block_info=None):
    i, j, k = block_info[0]["chunk-location"][:3]
    np.save(Path(directory) / f"{name}-{i}-{j}-{k}.npy", np.ascontiguousarray(b))
    return np.zeros((1,) * b.ndim, np.int8)

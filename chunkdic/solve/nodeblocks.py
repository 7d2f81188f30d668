"""Mesh-sized arrays in blocks of nodes, held where the memory is: on Dask workers or in a Zarr store.

A mesh whose stencil and solver vectors do not fit one process is cut into *node blocks*,
unions of the voxel blocks of the passes as large as a task's memory allows
(:func:`node_block_elements`): the block of elements ``[e0, e1)`` per axis owns the nodes
``[e0, e1)``, the last block also the mesh's last node. A block's product
with the 27-point stencil of ``M`` needs its neighbours' nodes one node away (two for the
penalty ``R``): :func:`haloed` gives each block that halo (``dask.array.overlap``, nothing
beyond the mesh's faces) and :func:`core_slices` the block's own nodes inside it. What a
block sums over its elements reaches one node further, onto the next block's first
planes: :func:`fold_faces` adds those planes where they belong.

Where the blocks live is a :class:`Holder`: :class:`WorkerHolder` persists them on the
workers of a ``distributed`` cluster (products run there as tasks, only scalars come
back); :class:`DiskHolder` writes them to a Zarr store under the run's scratch and reads
them back block by block with Dask's threaded scheduler, so that one process holds a few
blocks per thread whatever the mesh (there the stencil's blocks are files of their own,
:mod:`chunkdic.solve.haloedfiles`, and the solver's vectors stay in the process;
docs/distributed.md, "Mesh data beyond one process").
"""

from __future__ import annotations

import math
from pathlib import Path

import dask
import dask.array as da
import numpy as np
from dask.array.core import slices_from_chunks

from ..io.owntree import remove


#: bytes a block task holds per node of its haloed block: the float32 half stencil read from
#: its file (504 B), the vector's haloed copy and the block's product (48 B), the brightness
#: cells' couplings (94 B with cells of 4 elements)
TASK_BYTES_PER_NODE = 650
#: largest block task (bytes; 48³ elements, 86 MiB): the halo adds an eighth to such a block's
#: reads, and larger blocks save little more while each thread holds one
MAX_TASK_BYTES = 96 * 2**20


def node_block_elements(elements_shape, block_elements: int, tasks: int) -> int:
    """Elements per side of a node block: the largest multiple of the passes' ``block_elements``
    (node blocks are unions of voxel blocks) whose task, its haloed block at
    :data:`TASK_BYTES_PER_NODE`, stays within :data:`MAX_TASK_BYTES`, that leaves at least two
    blocks per task at once (as many as the voxel blocks allow), and whose last block along
    each axis is at least half a block (the tasks balanced).

    >>> node_block_elements((64, 64, 64), 16, 2)
    32
    >>> node_block_elements((96, 96, 96), 16, 2)
    48
    """
    m0 = max(1, int(block_elements))

    def count(m):
        return math.prod(-(-int(e) // m) for e in elements_shape)

    want = min(2 * max(1, int(tasks)), count(m0))
    best = m0
    for m in range(2 * m0, max(elements_shape) + 1, m0):
        fits = TASK_BYTES_PER_NODE * math.prod(min(m, int(e)) + 3 for e in elements_shape) <= MAX_TASK_BYTES
        balanced = all(int(e) % m == 0 or int(e) % m >= m / 2 or int(e) < m for e in elements_shape)
        if fits and balanced and count(m) >= want:
            best = m
    return best


def node_chunks(nodes_shape, block_elements: int) -> tuple[tuple[int, ...], ...]:
    """Nodes per block along each axis: ``block_elements`` per block, the last block one more.

    >>> node_chunks((24, 24, 9), 12)
    ((12, 12), (12, 12), (9,))
    """
    m = max(1, int(block_elements))
    out = []
    for n in nodes_shape:
        elements = int(n) - 1
        sizes = [min(m, elements - e0) for e0 in range(0, max(elements, 1), m)]
        sizes[-1] += 1
        out.append(tuple(sizes))
    return tuple(out)


def extended_chunks(chunks) -> tuple[tuple[int, ...], ...]:
    """Each block's nodes with the next block's first plane (the nodes its elements touch)."""
    return tuple(tuple(c + 1 for c in axis[:-1]) + (axis[-1],) for axis in chunks)


def core_slices(block_id, numblocks, depth: int, shape) -> tuple[slice, slice, slice]:
    """The block's own nodes inside its haloed copy (:func:`haloed`: no halo beyond the mesh)."""
    out = []
    for i, n, size in zip(block_id[:3], numblocks[:3], shape[:3]):
        lo = depth if i > 0 else 0
        hi = depth if i < n - 1 else 0
        out.append(slice(lo, size - hi))
    return tuple(out)


def haloed(x: da.Array, depth: int) -> da.Array:
    """``x`` with ``depth`` nodes of its neighbours on each side of each block (node axes only)."""
    if depth == 0:
        return x
    return da.overlap.overlap(x, depth={a: (depth if a < 3 else 0) for a in range(x.ndim)},
                              boundary={a: "none" for a in range(x.ndim)})


def fold_faces(x: da.Array) -> da.Array:
    """Per-block sums over each block's extended nodes (:func:`extended_chunks`) to the node
    blocks: the last plane of a block (the next block's first) added into that block, axis by
    axis (edges and corners follow)."""
    for axis in range(3):
        ext = x.chunks[axis]
        if len(ext) == 1:
            continue
        own = tuple(c - 1 for c in ext[:-1]) + (ext[-1],)
        h = da.overlap.overlap(x, depth={a: (1 if a == axis else 0) for a in range(x.ndim)},
                               boundary={a: "none" for a in range(x.ndim)})
        chunks = list(x.chunks)
        chunks[axis] = own
        x = h.map_blocks(_fold_block, axis, own, chunks=tuple(chunks), dtype=x.dtype)
    return x


def _fold_block(b, axis, own, block_id=None):
    i = block_id[axis]
    lo = 1 if i > 0 else 0
    take = [slice(None)] * b.ndim
    take[axis] = slice(lo, lo + own[i])
    out = b[tuple(take)].copy()
    if lo:
        first = [slice(None)] * b.ndim
        first[axis] = slice(0, 1)
        out[tuple(first)] += b[tuple(first)]
    return out


class WorkerHolder:
    """Node blocks persisted on the workers of a ``distributed`` client; scalars gathered.

    Parameters
    ----------
    client : distributed.Client
    """

    where = "workers"

    def __init__(self, client):
        self.client = client

    @property
    def tasks(self) -> int:
        """Tasks at once on the cluster (its workers' threads)."""
        workers = self.client.scheduler_info().get("workers", {})
        return max(1, sum(int(w.get("nthreads", 1)) for w in workers.values()))

    def hold(self, x: da.Array, name: str) -> da.Array:
        """``x`` computed and kept on the workers (its blocks where they were computed)."""
        return self.step({name: x})[0][name]

    def step(self, arrays: dict, values=None) -> tuple[dict, list]:
        """Hold ``arrays`` (name → lazy array) and gather ``values(held)`` (small results)."""
        from distributed import wait

        held = dict(zip(arrays, self.client.persist(list(arrays.values())))) if arrays else {}
        wait(list(held.values()))
        return held, (self.values(*values(held)) if values else [])

    def values(self, *xs):
        """The (small) results of ``xs`` in the client."""
        return self.client.compute(list(xs), sync=True)

    def gather(self, x: da.Array, out: np.ndarray | None = None) -> np.ndarray:
        """``x`` in the client, each block written into ``out`` as it arrives (allocated if
        None): no list of blocks beside their concatenated copy (24 B per node for a vector)."""
        from distributed import as_completed

        out = np.empty(x.shape, x.dtype) if out is None else out
        regions = dict(zip(np.ndindex(x.numblocks), slices_from_chunks(x.chunks)))
        blocks = x.to_delayed()
        indices = list(np.ndindex(blocks.shape))
        # one submission of every block (one graph), then each written where it goes as it arrives
        futures = dict(zip(self.client.compute([blocks[i] for i in indices]), (regions[i] for i in indices)))
        for future, block in as_completed(list(futures), with_results=True):
            out[futures.pop(future)] = block
            future.release()
            del future, block
        return out

    def close(self) -> None:
        """Nothing kept: persisted blocks go with their last reference."""


class DiskHolder:
    """Node blocks in Zarr stores under ``directory``, computed by Dask's threaded scheduler.

    Each name has two stores, written in turn (double buffering): a :meth:`step` writes the
    one its expressions do not read (they read the name's last one), with no store created
    or removed per step.

    Parameters
    ----------
    directory : Path
        Created if missing; removed by :meth:`close`.
    threads : int
        Tasks at once.
    """

    where = "disk"

    def __init__(self, directory, threads: int = 1):
        self.directory, self.threads = Path(directory), max(1, int(threads))
        self.tasks = self.threads
        self.directory.mkdir(parents=True, exist_ok=True)
        self._stores: dict[str, list] = {}
        self._turn: dict[str, int] = {}

    def hold(self, x: da.Array, name: str) -> da.Array:
        """``x`` computed into the store ``name`` not read now, read back lazily."""
        return self.step({name: x})[0][name]

    def _target(self, name: str, x: da.Array):
        """The store of ``name`` to write now (made on first use; again if ``x``'s shape changed)."""
        import zarr

        stores = self._stores.get(name)
        if stores is None or stores[0].shape != x.shape or stores[0].dtype != x.dtype:
            # zarr chunks of the regular blocks; the last block, up to one node longer, owns the
            # chunks its nodes start: every zarr chunk written by one task
            chunks = tuple(axis[0] for axis in x.chunks)
            stores = [zarr.create_array(str(self.directory / f"{name}-{k}.zarr"), shape=x.shape, chunks=chunks,
                                        dtype=x.dtype, fill_value=0, compressors=None, zarr_format=3,
                                        overwrite=True) for k in (0, 1)]
            self._stores[name], self._turn[name] = stores, 1
        self._turn[name] = 1 - self._turn[name]
        return stores[self._turn[name]]

    def step(self, arrays: dict, values=None) -> tuple[dict, list]:
        """Write ``arrays`` (name → lazy array) and compute ``values(arrays)`` in the same
        pass (each block computed once, stored and used by the values), then read them back."""
        targets = [self._target(name, x) for name, x in arrays.items()]
        lazy = [] if values is None else list(values(arrays))
        with dask.config.set(scheduler="threads", num_workers=self.threads):
            stored = [da.store(list(arrays.values()), targets, lock=False, compute=False)] if arrays else []
            out = dask.compute(*stored, *lazy)[len(stored):]
        held = {name: da.from_zarr(z, chunks=x.chunks) for (name, x), z in zip(arrays.items(), targets)}
        return held, list(out)

    def values(self, *xs):
        with dask.config.set(scheduler="threads", num_workers=self.threads):
            return list(dask.compute(*xs))

    def gather(self, x: da.Array, out: np.ndarray | None = None) -> np.ndarray:
        """``x`` in the process, each block written into ``out`` as it is computed (allocated
        if None): no list of blocks beside their concatenated copy (24 B per node for a vector)."""
        out = np.empty(x.shape, x.dtype) if out is None else out
        with dask.config.set(scheduler="threads", num_workers=self.threads):
            da.store(x, out, lock=False)
        return out

    def close(self) -> None:
        remove(self.directory)
        self._stores.clear()


def from_client(a: np.ndarray, chunks, holder, name: str) -> da.Array:
    """A client array ``a`` (nodes first) cut into node blocks and held by ``holder``."""
    return holder.hold(da.from_array(a, chunks=tuple(chunks) + tuple((n,) for n in a.shape[3:])), name)

"""Writing Dask arrays into Zarr arrays chunk by chunk, safely.

Every task owns whole Zarr chunks (shards): :func:`check_write_alignment` refuses
anything else, because zarr 3.1 silently loses data when concurrent tasks write parts of
the same chunk. Progress is reported from the local threaded scheduler or from the futures
of a ``distributed`` client; on failure the local pool is drained before returning so that
callers can remove a half-written output safely.
"""

from __future__ import annotations

import concurrent.futures
import itertools
import os

import numpy as np

from .. import config
from ..errors import InputError


def drain_zarr_io(timeout: float = 10.0) -> None:
    """Wait until zarr's I/O event loop has no task in flight (at most ``timeout`` s).

    zarr 3 writes the chunks of one assignment concurrently on its event loop; when one
    write fails (a full disk), the assignment raises at once while the others go on
    (``asyncio.gather`` does not cancel them), and a store removed right then is partly
    written again a moment later (measured: a staged output left behind under load).
    Cleanup calls this first.
    """
    import asyncio

    from zarr.core import sync as zsync

    loop = zsync.loop[0]
    if loop is None or not loop.is_running():
        return

    async def idle() -> None:
        me = asyncio.current_task()
        pending = [t for t in asyncio.all_tasks() if t is not me]
        if pending:
            await asyncio.wait(pending, timeout=timeout)

    try:
        asyncio.run_coroutine_threadsafe(idle(), loop).result(timeout + 1)
    except Exception:  # noqa: BLE001 - best effort: cleanup goes on
        pass


def compressors(dtype):
    """Compressor of every array chunkdic writes (measurements in docs/scans.md).

    ``chunkdic.compressor`` (dask config): ``"auto"`` (default: zstd level 1 for 1-byte
    samples, blosc-lz4 with bit shuffle for wider ones, i.e. 16/32-bit scans and every
    pyramid level), ``"zstd"``, ``"lz4"`` (blosc-lz4 + bit shuffle) or ``"none"``.
    """
    import dask.config
    from zarr.codecs import BloscCodec, ZstdCodec

    name = str(dask.config.get("chunkdic.compressor", default="auto")).lower()
    itemsize = np.dtype(dtype).itemsize
    if name == "auto":
        name = "zstd" if itemsize == 1 else "lz4"
    if name == "zstd":
        return (ZstdCodec(level=1),)
    if name == "lz4":
        return (BloscCodec(cname="lz4", clevel=5, shuffle="bitshuffle", typesize=itemsize),)
    if name == "none":
        return None
    raise InputError(f"chunkdic.compressor={name!r}: use auto, zstd, lz4 or none")


def chunk_shape_for(shape, chunks) -> tuple[int, int, int]:
    if chunks is None:
        chunks = config.get("chunk-size")
    c = tuple(int(v) for v in np.broadcast_to(np.asarray(chunks), (3,)))
    if any(v < 1 for v in c):
        raise InputError(f"chunk edge must be a positive integer, got {chunks!r}")
    return tuple(max(1, min(v, n)) for v, n in zip(c, shape))


def check_write_alignment(dask_chunks, shape, unit, name: str = "array") -> None:
    """Raise :class:`InputError` unless each Dask block covers whole write units.

    Zarr 3.1 loses data silently when concurrent tasks write parts of the same chunk or
    shard, so every block boundary must fall on a multiple of the write unit (the shard
    shape for a sharded array, else the chunk shape) or on the array end.

    Parameters
    ----------
    dask_chunks : tuple of 3 tuples of int
        ``dask_array.chunks``.
    shape : tuple of 3 int
        Array shape.
    unit : tuple of 3 int
        Zarr shard shape (sharded) or chunk shape.
    """
    for axis, (cs, n, u) in enumerate(zip(dask_chunks, shape, unit)):
        edges = np.cumsum((0,) + tuple(cs))
        if edges[-1] != n:
            raise InputError(f"{name}: dask chunks cover {edges[-1]} voxels along axis {'zyx'[axis]}, the array has {n}")
        bad = [int(e) for e in edges[1:-1] if e % u]
        if bad:
            raise InputError(
                f"{name}: dask block boundaries along {'zyx'[axis]} at {bad[:4]} are not multiples of the "
                f"Zarr chunk/shard edge {u}; every writing task must own whole chunks/shards "
                f"(zarr 3.1 silently loses data otherwise): rechunk to multiples of {u}"
            )


def write_region(path: str, key: str, region, data: np.ndarray) -> None:
    """Write ``data`` into ``region`` (slices) of the Zarr array ``path``/``key``.

    The caller owns the whole chunks (shards) ``region`` covers (:func:`check_write_alignment`).
    """
    import zarr

    arr = zarr.open_array(store=path, path=key or None, mode="r+")
    # Skipping the per-chunk "all fill value?" test makes zarr 3.1 writes 2-3x faster
    # (measured, docs/scans.md); a chunk of zeros then costs a few bytes on disk.
    arr = arr.with_config({"write_empty_chunks": True})
    arr[tuple(region)] = data


def _write_block(block: np.ndarray, path: str, key: str, z0: int = 0, block_info=None) -> np.ndarray:
    """Write one block where it belongs (``z0``: the first plane of the slab it came from)."""
    loc = block_info[0]["array-location"]
    write_region(path, key, tuple(slice(a + (z0 if i == 0 else 0), b + (z0 if i == 0 else 0))
                                  for i, (a, b) in enumerate(loc)), block)
    return np.ones((1, 1, 1), np.int64)


class _Progress:
    """A ``dask`` local-scheduler callback reporting finished tasks to ``fn(fraction)``.

    ``start``/``end`` map this computation into a sub-range of a longer operation.
    """

    def __init__(self, fn, start=0.0, end=1.0):
        self.fn, self.start, self.end = fn, start, end
        self._cb = None

    def __enter__(self):
        if self.fn is None:
            return self
        from dask.callbacks import Callback

        total, done, last = [1], [0], [-1.0]

        def _start_state(dsk, state):
            total[0] = max(1, len(state["ready"]) + len(state["waiting"]) + len(state["running"]))

        def _posttask(key, result, dsk, state, worker_id):
            done[0] += 1
            frac = self.start + (self.end - self.start) * min(1.0, done[0] / total[0])
            if frac - last[0] >= 0.01:
                last[0] = frac
                self.fn(frac)

        self._cb = Callback(start_state=_start_state, posttask=_posttask)
        self._cb.__enter__()
        return self

    def __exit__(self, *exc):
        if self._cb is not None:
            self._cb.__exit__(*exc)
        if exc[0] is None and self.fn is not None:
            self.fn(self.end)
        return False


def _compute(x, progress=None, start=0.0, end=1.0):
    """Compute the dask array ``x`` (one small block per written chunk), reporting progress.

    On the local threaded scheduler use our own pool and, on failure, wait for the running
    tasks before returning so that callers can clean up safely. On a ``distributed``
    client, progress comes from the blocks' futures as they finish (local-scheduler
    callbacks never fire there).
    """
    import dask
    import dask.threaded
    from dask.base import get_scheduler

    many = isinstance(x, list)  # a list of delayed blocks (a resumed write) or one array
    sched = get_scheduler(collections=x if many else [x])
    client = getattr(sched, "__self__", None)  # the bound ``Client.get`` of a distributed client
    if progress is not None and client is not None:
        from distributed import Client

        if isinstance(client, Client):
            return _compute_on_client(client, x, progress, start, end)
    with _Progress(progress, start, end):
        if sched is None or sched is dask.threaded.get:
            n = config.get("num-threads") or os.cpu_count() or 1
            pool = concurrent.futures.ThreadPoolExecutor(n)
            try:
                out = dask.compute(*(x if many else [x]), scheduler="threads", pool=pool)
            finally:
                pool.shutdown(wait=True, cancel_futures=True)
        else:
            out = dask.compute(*(x if many else [x]))
        return list(out) if many else out[0]


def _compute_on_client(client, x, progress, start: float, end: float) -> None:
    """Run the blocks of ``x`` on a distributed ``client``, calling ``progress(fraction)``
    (at most every 1 %) as their futures finish; on failure cancel what has not run."""
    from distributed import as_completed

    futures = client.compute(x if isinstance(x, list) else list(x.to_delayed().ravel()))
    done, last = 0, -1.0
    try:
        for fut in as_completed(futures):
            fut.result()  # raises the task's error here
            done += 1
            frac = start + (end - start) * done / len(futures)
            if frac - last >= 0.01:
                last = frac
                progress(float(frac))
    except BaseException:
        client.cancel(futures)
        raise
    if last < end:
        progress(end)


#: blocks of one computed graph at most: a larger array is written in slabs of whole block
#: planes, each its own graph (a Zarr input declaring 10 000³ voxels in 128³ chunks, 493 039
#: blocks, grew the graph of one compute past 1 GiB in 60 s before a chunk was written)
MAX_GRAPH_BLOCKS = 8192


def _batches(numblocks) -> list[tuple[int, int]]:
    """Ranges of block planes (along z) of at most :data:`MAX_GRAPH_BLOCKS` blocks (one plane at least)."""
    per_plane = max(1, int(np.prod(numblocks[1:])))
    step = max(1, MAX_GRAPH_BLOCKS // per_plane)
    return [(z, min(z + step, numblocks[0])) for z in range(0, numblocks[0], step)]


def _writes(data, path, key: str, z0: int = 0):
    """One task per block of ``data`` writing it into ``path``/``key`` from plane ``z0`` on."""
    out_chunks = tuple((1,) * len(c) for c in data.chunks)
    return data.map_blocks(_write_block, path=str(path), key=key, z0=z0, dtype=np.int64, chunks=out_chunks,
                           meta=np.empty((0, 0, 0), np.int64))


def store_array(data, path: str, key: str, progress=None, start=0.0, end=1.0, resume: bool = False) -> int:
    """Write dask array ``data`` into the existing Zarr array ``path``/``key``, block by block.

    Each task owns whole chunks (shards): checked up front. ``resume``: blocks whose every
    chunk is already stored and complete (:func:`chunk_is_complete`: present, decodable,
    the right shape) are neither computed nor written again, the rest are (an interrupted
    ``chunkdic synth`` continues; the data must be a deterministic function of the block,
    as every synthetic scan is). Returns the number of blocks written.

    Not ``dask.array.store``: it neither checks that tasks own whole shards (zarr 3.1
    silently loses data otherwise, shared/DESIGN.md) nor reports progress from a
    distributed client's futures, and it cannot skip zarr's per-chunk "all fill value?"
    test, which made writes 2-3x slower (docs/scans.md).
    """
    import zarr

    arr = zarr.open_array(store=path, path=key or None, mode="r+")
    if tuple(arr.shape) != tuple(data.shape):
        raise InputError(f"cannot write an array of shape {data.shape} into {path}/{key} of shape {arr.shape}")
    unit = arr.shards if getattr(arr, "shards", None) else arr.chunks
    check_write_alignment(data.chunks, data.shape, unit, name=f"{path}/{key}")
    if not resume:
        # slab by slab: map_blocks builds a record per block up front (its block_info)
        batches = _batches(data.numblocks)
        planes = np.cumsum((0,) + data.chunks[0])
        for i, (k0, k1) in enumerate(batches):
            z0, z1 = int(planes[k0]), int(planes[k1])
            a, b = start + (end - start) * i / len(batches), start + (end - start) * (i + 1) / len(batches)
            _compute(_writes(data[z0:z1], path, key, z0), progress, a, b)
        return int(np.prod(data.numblocks))
    done = _writes(data, path, key)
    # only the blocks still missing: computing a subset of the delayed blocks culls the
    # graph, so the source tasks of complete blocks never run
    # checked in threads (reading and decoding release the GIL): one by one, the 8192
    # chunks of a 2048³ pair took ~7 min of a resumed synth on one core
    idxs = list(np.ndindex(*done.numblocks))
    with concurrent.futures.ThreadPoolExecutor(max(1, os.cpu_count() or 1)) as pool:
        complete = list(pool.map(lambda idx: _block_complete(arr, data.chunks, idx, unit), idxs))
    todo = [blk for ok, blk in zip(complete, done.to_delayed().ravel()) if not ok]
    if todo:
        _compute(todo, progress, start, end)
    elif progress is not None:
        progress(end)
    return len(todo)


def chunk_is_complete(arr, coords) -> bool:
    """Whether chunk ``coords`` of the Zarr array ``arr`` is stored and decodes to its shape.

    A chunk file cut short (a copy, a disk) counts as missing; so does an absent one.
    Reads the one chunk.

    A Blosc chunk is first checked against its frame header (:func:`blosc_frame_is_whole`):
    the Blosc 1 decoder does not know the length of the buffer it is given, trusts the
    header's and reads past the end of a cut-short one, so a truncated chunk decodes, or
    not, depending on what lies beyond it in memory (the rest of the same chunk, freed
    after an earlier read of the whole file, decodes to the former voxels; a few bytes of
    it changed, to a few wrong ones). A resumed ``chunkdic synth`` then kept the cut
    chunk, or failed in its pyramid: 3 runs in 34 (docs/safety.md, "Resuming a synthetic
    pair").
    """
    import zarr

    if chunk_file_is_whole(arr, coords) is False:
        return False
    region = tuple(slice(c * e, min((c + 1) * e, n)) for c, e, n in zip(coords, arr.chunks, arr.shape))
    try:
        block = zarr.open_array(store=arr.store, path=arr.path, mode="r")[region]
    except Exception:  # noqa: BLE001 - any decoding failure means "write it again"
        return False
    return tuple(block.shape) == tuple(s.stop - s.start for s in region)


def chunk_file_is_whole(arr, coords) -> bool | None:
    """Whether the file of chunk ``coords`` of the Zarr array ``arr`` is there at its whole length,
    without decoding it: an uncompressed chunk (the bytes codec alone) by its size, a Blosc
    chunk by its frame header (:func:`blosc_frame_is_whole`). ``None``: present, but other
    codecs cannot tell without decoding (:func:`chunk_is_complete` decodes).

    A file that a killed writer left cut short fails; its bytes that a killed process had
    written are in the page cache and on disk later, so a whole-length file holds them.
    """
    key = arr.metadata.encode_chunk_key(tuple(int(c) for c in coords))
    root = getattr(arr.store, "root", None)
    path = None if root is None else os.path.join(str(root), arr.path, key)
    if path is None or not os.path.isfile(path):
        return False
    nbytes = blosc_frame_bytes(arr)
    if nbytes is not None:
        return blosc_frame_is_whole(path, nbytes)
    if _uncompressed(arr):  # edge chunks are stored at the full chunk shape
        return os.path.getsize(path) == int(np.prod(arr.chunks)) * np.dtype(arr.dtype).itemsize
    return None


def _uncompressed(arr) -> bool:
    """Chunks stored as their raw bytes (Zarr v3, the bytes codec alone)."""
    from zarr.codecs import BytesCodec

    codecs = tuple(getattr(arr.metadata, "codecs", ()) or ())
    return len(codecs) == 1 and isinstance(codecs[0], BytesCodec)


#: bytes of a Blosc 1 frame header: version, versionlz, flags, typesize, then
#: nbytes, blocksize, cbytes as little-endian uint32 (c-blosc README_HEADER.rst)
BLOSC_HEADER = 16


def blosc_frame_is_whole(path: str, nbytes: int) -> bool:
    """Whether the file ``path`` holds one whole Blosc 1 frame of ``nbytes`` decoded bytes.

    The frame's ``cbytes`` (header included) must equal the file's size, and its
    ``nbytes`` the chunk's: checked before decoding because the decoder reads ``cbytes``
    bytes whatever the buffer's length (numcodecs issue #228; c-blosc2 issue #40: "you
    cannot trust the output of blosc_cbuffer_sizes(), but you can trust your buffer.len").
    """
    return blosc_frame_fault(path, os.path.getsize(path), nbytes) is None


def blosc_frame_fault(path: str, size: int, nbytes: int) -> str | None:
    """What is wrong with the file ``path`` of ``size`` bytes as one Blosc 1 frame of
    ``nbytes`` decoded bytes (a few words), or None when its header matches both.

    Reads the frame header only (:data:`BLOSC_HEADER` bytes): the header's ``cbytes`` against
    the file's size (a cut-short or overlong file) and its ``nbytes`` against the chunk's
    (a frame of another chunk shape or dtype).
    """
    fd = os.open(path, os.O_RDONLY)  # no buffered file object: the header check runs on every chunk file
    try:
        head = os.pread(fd, BLOSC_HEADER, 0)
    finally:
        os.close(fd)
    return blosc_header_fault(head, size, nbytes)


def blosc_header_fault(head: bytes, size: int, nbytes: int) -> str | None:
    """:func:`blosc_frame_fault` on a frame's first bytes ``head`` (at least
    :data:`BLOSC_HEADER` of them when the frame has them) already read, ``size`` the frame's length."""
    head = head[:BLOSC_HEADER]
    if len(head) < BLOSC_HEADER:
        return f"holds {len(head)} bytes, less than a Blosc frame header ({BLOSC_HEADER})"
    frame_nbytes = int.from_bytes(head[4:8], "little")
    cbytes = int.from_bytes(head[12:16], "little")
    if cbytes != size:
        return f"holds {size} bytes where its Blosc frame header announces {cbytes}"
    if frame_nbytes != nbytes:
        return f"is a Blosc frame of {frame_nbytes} decoded bytes where a chunk holds {nbytes}"
    return None


def blosc_frame_bytes(arr) -> int | None:
    """Decoded bytes of one chunk when every chunk file of the Zarr array ``arr`` is one whole
    Blosc 1 frame of a whole chunk, else None (no frame to check).

    Zarr v3: Blosc the outermost codec with no other bytes-to-bytes codec before it (those
    change the length), not sharded (a shard file is an index and inner chunks, a sharding
    codec the outermost); v2: the Blosc compressor without filters. Edge chunks are stored
    at the full chunk shape in both.
    """
    import numcodecs
    from zarr.abc.codec import BytesBytesCodec
    from zarr.codecs import BloscCodec

    meta = arr.metadata
    if meta.zarr_format == 2:
        blosc = isinstance(meta.compressor, numcodecs.Blosc) and not meta.filters
    else:
        codecs = tuple(getattr(meta, "codecs", ()) or ())
        blosc = (bool(codecs) and isinstance(codecs[-1], BloscCodec)
                 and not any(isinstance(c, BytesBytesCodec) for c in codecs[:-1]))
    return int(np.prod(arr.chunks)) * np.dtype(arr.dtype).itemsize if blosc else None


def _block_complete(arr, dask_chunks, idx, unit) -> bool:
    """Whether every chunk of Dask block ``idx`` is stored complete in ``arr`` (a sharded
    array is always written again: its shard files are not checked chunk by chunk)."""
    if tuple(unit) != tuple(arr.chunks):
        return False
    lo = [int(sum(c[:i])) for c, i in zip(dask_chunks, idx)]
    hi = [a + int(c[i]) for a, c, i in zip(lo, dask_chunks, idx)]
    grid = [range(a // e, -(-b // e)) for a, b, e in zip(lo, hi, arr.chunks)]
    return all(chunk_is_complete(arr, c) for c in itertools.product(*grid))


def aligned(data, chunk_shape):
    """``data`` unchanged if its blocks own whole chunks, else rechunked to the chunk grid."""
    try:
        check_write_alignment(data.chunks, data.shape, chunk_shape)
        return data
    except InputError:
        return data.rechunk(chunk_shape)

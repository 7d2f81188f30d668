"""The cost model of a correlation: memory per task and per process, scratch and output bytes, time.

From the scans' shapes and dtypes and the settings alone: a process holds a base (Python,
NumPy, numba, zarr and the kernels: :data:`BASE_BYTES` when it compiles them,
:data:`WARM_BASE_BYTES` when they load from numba's cache), the client's mesh-sized data
(:data:`CLIENT_BYTES_PER_NODE` per node of the finest mesh) and, with the embedded thread
pool, one task per thread (:func:`task_bytes`, :func:`prepare_bytes`, the reads' buffers and
the cache of decoded chunks); the scratch disk holds the missing pyramid levels for the whole
run and per level the haloed copy of ``f`` and the prepared ``g`` (:func:`level_disk`,
:func:`peak_scratch`); the time comes from per-voxel costs measured on this machine
(:data:`COSTS`, relative to the prefilter of ``g``) scaled by a short calibration on the real
data (:func:`calibrate`). :mod:`chunkdic.engine.runplan` puts them together into a plan.
docs/engine.md, "Plan, memory target and disk".
"""

from __future__ import annotations

import concurrent.futures
import math
import time

import numpy as np

from .. import config
from ..kernels.jit import kernels_cached
from ..mesh import Mesh
from ..passes.haloed import quantization
from ..passes.prefilter import gaussian_radius, prepare_deformed, prepared_grid, prepared_halo
from ..passes.stored_matrix import BYTES_PER_NODE, cells_bytes, stored_bytes

GiB, MiB = 2**30, 2**20
#: resident memory of a running correlation's process besides its tasks and mesh data
#: when it compiles its numba kernels (bytes; measured: a 128³ run whose tasks and mesh
#: are planned at 84 MiB peaks at 450-456 MiB with an empty numba cache, NUMBA_CACHE_DIR=$(mktemp -d))
BASE_BYTES = 372 * MiB
#: the same when every kernel the run uses loads from numba's cache (:func:`kernels_cached`;
#: compiling holds LLVM's memory besides). That of a fresh install (a new virtual
#: environment, as the CI's), whose warm 128³ run peaks at 359-366 MiB, a base of ~282 MiB:
#: a long-lived development environment with the same code and package versions peaks
#: 52 MiB lower (base ~246 MiB; cause unknown), where the estimate errs on the safe side
WARM_BASE_BYTES = 285 * MiB
#: client bytes per node of the finest mesh: the float32 half stencil of ``M`` (504 B), the
#: V-cycle's coarse ``M``, the fields of the Gauss–Newton state, a ``b`` pass's nodal and
#: element rows and a solve's vectors at their peak (measured at 128³ nodes with 182 MiB of
#: kernels, ``bench_client_memory.py --steps --iterations 2``: 2 157 MiB with a length that
#: takes the V-cycle, 988 B per node; 1 967 MiB, 892 B, with block-Jacobi, to which the
#: two-lane CG (solve.lanes) adds one vector, 24 B; docs/distributed.md, "Where the client's
#: memory goes"). The automatic length is not known before the run: the larger.
CLIENT_BYTES_PER_NODE = 1000
#: client bytes per node when the level's mesh data are in node blocks
#: (docs/distributed.md, "Mesh data beyond one process"): the current field and the field
#: ``M`` was built at, a ``b`` pass's nodal and element rows while they are summed (the drift
#: cells' compact rows, 88 B), a solve's vectors (CG's four, 96 B), the penalty's setup
#: (plane waves); the best field, the element fields and a pass's ``b`` while it is solved for
#: are parked on the scratch (:mod:`chunkdic.passes.parked`), block-Jacobi's diagonal blocks
#: are in files beside the stencil's, and the blocks in flight are counted apart
#: (:data:`~chunkdic.solve.nodeblocks.MAX_TASK_BYTES` per thread). Measured with
#: ``bench_client_memory.py --element-size 8 --regularize 2 --solves 1 --mesh-data blocks
#: --iterations 2 --steps``: the Gauss–Newton passes' peak 563 MiB at 885 k nodes (``--sizes
#: 768``), 745 MiB at 2.10 M nodes (``--sizes 1024``) and 1 552 MiB at 7.08 M nodes
#: (``--sizes 1536``): 157 and 170 B per node between them; the rest, about 400 MiB with
#: 190 MiB of kernels, is the process's base and the products' blocks in flight, which the
#: plan counts apart
BLOCKED_CLIENT_BYTES_PER_NODE = 180
#: bytes per node the node blocks hold together (spread over the workers, or on the scratch
#: disk with the embedded scheduler): the float32 half stencil (504 B) with its blocks'
#: one-node halos (an eighth at blocks of 48³ elements), and on the workers CG's vectors
#: held at once (``x``, ``r``, ``p``, ``q``: 4 × 24 B)
BLOCKS_BYTES_PER_NODE = 680
#: scratch bytes per node of the arrays a client holding node blocks parks
#: (:mod:`chunkdic.passes.parked`): the best field and a pass's ``b`` (24 B each), the element
#: fields of the current and of the best pass (8 float64 per element each)
PARKED_BYTES_PER_NODE = 176
#: float32 copies of its (haloed) region that a block task holds at its peak, the memory-
#: mapped pages of the prepared ``g`` it touches included (fitted on 128³-256³ runs,
#: blocks of 32-128 voxels)
TASK_COPIES = 12.0
#: float32 copies of its haloed region a task of the prefilter of ``g`` holds besides its
#: raw read: the copy the low-pass and B-spline sweeps work in and the z sweep's source
#: (measured by ``validation/scale/bench_prefilter_memory.py``: +43.6 MiB for a 179³ region,
#: +52.2 MiB for 190³: 2.0). The task's peak adds the raw region in its dtype, the cropped
#: float32 copy and its uint16 quantisation (6 bytes per voxel of the task) and the read's
#: buffers (:data:`READ_BUFFERS_PER_CHUNK`); two tasks at once hold twice one's (measured:
#: 20 tasks of 147³ on 2 threads peak at 194-242 MiB, one alone at 117-128 MiB); the
#: store is written by ``pwrite`` and adds nothing (docs/distributed.md, "The plan's memory
#: at 512³-2048³")
PREPARE_COPIES = 2.0
#: decoded chunks' worth of memory zarr holds per chunk it is reading, for up to
#: ``async.concurrency`` (10) of the chunks a region crosses (their compressed bytes and the
#: decoded chunks; ``validation/scale/bench_prefilter_memory.py``): a scan's own chunks, taken as
#: noisy CT (measured: 92-100 MiB beyond the region for reads of 179³-190³ regions crossing
#: 27 uint16 chunks of 128³, 4 MiB each, which blosc cannot compress); the scratch
#: pyramid's uint32 sums, which compress (66 MiB for a 144³ region crossing 8 chunks of 8 MiB)
READ_BUFFERS_PER_CHUNK = {"scan": 2.4, "scratch": 1.1}
#: chunks' worth a read by :mod:`chunkdic.io.chunkread` holds beyond its region: one chunk's
#: compressed bytes and one decoded chunk at a time (the decoded chunks it keeps are the
#: process's cache, :func:`chunk_cache_bytes`)
DIRECT_READ_CHUNKS = 2
#: smallest edge of a prefilter task under a memory target (its halo grows its work)
MIN_PREPARE_EDGE = 48
#: per-voxel costs relative to the prefilter of ``g`` per filtered voxel (fitted on this
#: machine's 128³-512³ runs, validation/scale/bench_plan.py; the 2048³ passes of
#: docs/distributed.md give 0.58 and 0.65): the ``M`` pass (with the low-pass of ``f``),
#: one ``b`` pass, one level of the scratch pyramid (per level-0 voxel of one scan)
COSTS = {"m": 0.9, "b": 0.5, "pyramid": 0.12}
#: Gauss–Newton passes counted per level: coarse levels (rigid step included on the
#: coarsest), the finest level (its passes around the length choice: 3-4 on the 300³-1024³
#: band pairs, whose start gaps are summed inside the first pass and whose stopping rule
#: predicts the passes still to come: 5 counted, an upper bound)
PASSES = {"coarse": 4, "coarsest-extra": 3, "finest": 5}
#: client seconds per finest node and solve, and solves counted (iterations, length choice)
SOLVE_SECONDS_PER_NODE, SOLVES = 1.0e-5, 14
#: fixed seconds: kernels loaded from the cache, runner, output
FIXED_SECONDS = 6.0
#: seconds per filtered voxel of a prefilter task assumed without a calibration
UNCALIBRATED = 1.0 / 6e6
#: edge of each calibration region (voxels of ``g``, before its halo)
CALIBRATION_EDGE = 64
#: times the calibration runs (the fastest counts)
CALIBRATION_REPEATS = 3


def base_bytes() -> int:
    """A process's memory besides its tasks and mesh data: :data:`WARM_BASE_BYTES` when
    every kernel loads from numba's cache, else :data:`BASE_BYTES`."""
    return WARM_BASE_BYTES if kernels_cached() else BASE_BYTES


def blocks_bytes(mesh: Mesh, cell: int = 1) -> int:
    """Bytes of a level's node blocks (stencil, cells' couplings, CG vectors) together."""
    return BLOCKS_BYTES_PER_NODE * math.prod(mesh.nodes_shape) + cells_bytes(mesh.shape, cell)


def mesh_blocks_scratch(mesh: Mesh, block_elements: int, cell: int = 1, on_disk: bool = True) -> int:
    """Scratch bytes of a level's mesh data in node blocks, kept until the level ends
    (:class:`chunkdic.passes.mesh_blocks.BlockedMatrix`): the partials (a float32 half stencil
    per voxel block of ``block_elements``, each with its own boundary nodes, and the cells'
    couplings), the client's parked arrays (:data:`PARKED_BYTES_PER_NODE`) and, ``on_disk``
    (the embedded scheduler, or a cluster's blocks on disk), the node blocks' haloed files."""
    m = int(block_elements)
    partials = BYTES_PER_NODE * math.prod(e + -(-e // m) for e in mesh.shape) + cells_bytes(mesh.shape, cell)
    parked = PARKED_BYTES_PER_NODE * math.prod(mesh.nodes_shape)
    return int(partials + parked + (blocks_bytes(mesh, cell) if on_disk else 0))


def task_bytes(block_edge: int, sigma: float, interpolation: str, span: float = 0.0) -> int:
    """A block task's peak memory: its haloed ``f`` and window of ``g`` (float32 copies)."""
    halo_f = 1 + gaussian_radius(sigma)
    halo_g = 2  # the window of the prepared g: cubic support (a window outside it: rare)
    f = (block_edge + 2 * halo_f) ** 3
    g = (block_edge + 2 * halo_g + span) ** 3
    return int(TASK_COPIES * 4 * max(f, g))


def prepare_bytes(edges, sigma: float, interpolation: str, *, shape=None, raw_itemsize: int = 4,
                  quantized: bool = False, read_bytes: int = 0) -> int:
    """A prefilter task's peak memory (bytes).

    Parameters
    ----------
    edges : int or tuple of 3 int
        The task's region (voxels per axis, before the halo).
    sigma, interpolation
        The preparation (its halo, :func:`~chunkdic.passes.prefilter.prepared_halo`).
    shape : tuple of 3 int, optional
        The level's shape: the region grown by the halo is clipped to it.
    raw_itemsize : int
        Bytes per voxel of ``g`` as read (its dtype at the level).
    quantized : bool
        The store is uint16 (:func:`~chunkdic.passes.prefilter.prepared_grid`): the task
        holds the cropped float32 copy and the uint16 one too.
    read_bytes : int
        The read's buffers beyond the region (:func:`read_buffer_bytes`).
    """
    edges = np.broadcast_to(np.asarray(edges, dtype=np.int64), (3,))
    h = prepared_halo(sigma, interpolation, int(config.get("bspline-halo")))
    grown = [e + 2 * h if shape is None else min(e + 2 * h, n) for e, n in zip(edges, shape or (0, 0, 0))]
    held = math.prod(grown) * (raw_itemsize + 4 * PREPARE_COPIES)
    if quantized:
        held += 6 * math.prod(int(e) for e in edges)
    return int(held + read_bytes)


def read_buffer_bytes(g_scan, s: int, edges) -> int:
    """Bytes that reading a region of ``edges`` voxels (halo included) of level ``s`` of
    ``g_scan`` holds besides the region, at most.

    A Zarr array that :mod:`chunkdic.io.chunkread` reads from its chunk files (the
    scratch pyramid, and scans in its layouts) holds one chunk compressed and one decoded
    at a time (:data:`DIRECT_READ_CHUNKS`; the chunks it keeps are the process's cache,
    :func:`chunk_cache_bytes`). Through zarr-python, zarr decodes up to
    ``async.concurrency`` of the chunks the region crosses at once, each held compressed
    and decoded (:data:`READ_BUFFERS_PER_CHUNK` chunks' worth); a level not stored in the
    scan is read from the scratch pyramid, in ``chunkdic.chunk-size`` chunks. A ``.npy`` file is read through a memory map, which
    holds the pages of the rows the region crosses while it is copied.

    For level 0 of a 1024³ uint16 scan in chunks of 128³ and a 179³ region (a prefilter
    task of 147³ with its halo): 8 MiB from the chunk files; through zarr, 27 chunks
    crossed, 10 at once, 2.4 × 4 MiB each, 96 MiB.
    """
    import zarr

    from ..io.chunkread import layout_of

    shape, item = g_scan.shape(s), np.dtype(g_scan.dtype(s)).itemsize
    ref = g_scan.stored_refs().get(s)
    edges = [min(int(e), n) for e, n in zip(np.broadcast_to(edges, (3,)), shape)]
    if ref is not None and ref.kind == "npy":
        return int(edges[0] * edges[1] * shape[2] * item)
    source = "scan" if ref is not None else "scratch"
    chunks = _chunks_of(g_scan, s)
    if ref is None or layout_of(ref.path, ref.key) is not None:
        # read from the chunk files (the scratch pyramid's always are: chunkdic writes it)
        return int(DIRECT_READ_CHUNKS * math.prod(chunks) * item)
    # chunks an unaligned run of e voxels crosses along an axis, at most
    crossed = math.prod(min((e + c - 2) // c + 1, -(-n // c)) for e, c, n in zip(edges, chunks, shape))
    at_once = min(crossed, int(zarr.config.get("async.concurrency")))
    return int(READ_BUFFERS_PER_CHUNK[source] * at_once * math.prod(chunks) * item)


def chunk_cache_bytes(scans, s: int) -> int:
    """Bytes the process's cache of decoded chunks (:func:`chunkdic.io.chunkread.chunk_cache`,
    ``chunkdic.chunk-cache``) holds while the tasks of level ``s`` read ``scans``, at most:
    its capacity, or one whole level of the largest of them when that is smaller. Emptied
    after the ``M`` pass and after the prefilter of ``g`` (the ``b`` passes read the scratch
    copies)."""
    capacity = int(config.get("chunk-cache") or 0)
    if capacity <= 0:
        return 0

    def whole(sc) -> int:  # its chunks decoded: edge chunks too are whole chunks
        chunks = _chunks_of(sc, s)
        return math.prod(-(-n // c) * c for n, c in zip(sc.shape(s), chunks)) * np.dtype(sc.dtype(s)).itemsize

    return min(capacity, max(whole(sc) for sc in scans))


def _chunks_of(scan, s: int) -> tuple[int, ...]:
    """Chunk shape of level ``s`` of ``scan`` as read: its own Zarr array's, else the
    scratch pyramid's (``chunkdic.chunk-size``)."""
    from ..io.store import chunk_shape_for

    ref = scan.stored_refs().get(s)
    if ref is not None and ref.kind == "zarr":
        return tuple(ref.open().chunks)
    return chunk_shape_for(scan.shape(s), None)


def pyramid_scratch(scans, levels) -> dict[int, int]:
    """Scratch bytes of the pyramid levels the scans lack, per level, the scans together
    (uncompressed: an upper bound)."""
    pyramids: dict[int, int] = {}
    for scan in scans:
        for s, b in pyramid_levels(scan, levels).items():
            pyramids[s] = pyramids.get(s, 0) + b
    return pyramids


def pyramid_levels(scan, levels) -> dict[int, int]:
    """Scratch bytes of each pyramid level a scan lacks (uncompressed: an upper bound); a
    scan held in memory has its level 0 written to scratch too."""
    stored = set(scan.stored_levels())
    out = {}
    for s in sorted(set(levels) | ({0} if not stored else set())):
        if s not in stored:
            out[s] = int(math.prod(scan.shape(s)) * np.dtype(scan.dtype(s)).itemsize)
    return out


def peak_scratch(pyramids: dict[int, int], stores: dict[int, int]) -> int:
    """Peak scratch bytes of a run: every missing pyramid level is built at the start, and
    a level's (``stores``: its haloed ``f`` and prepared ``g``) is held with the pyramid levels
    at or below it (coarser ones are deleted when their level ends,
    :func:`chunkdic.engine.coarse_to_fine.release_scan_levels`)."""
    held = [sum(pyramids.values())]
    held += [stores[s] + sum(b for t, b in pyramids.items() if t <= s) for s in stores]
    return int(max(held))


def level_disk(mesh: Mesh, g_shape, m: int, sigma: float, f_dtype, prepared: bool, g_dtype=None,
               interpolation: str = "cubic") -> tuple[int, int, list]:
    """``(haloed f copy, prepared g)`` scratch bytes of a level with blocks of ``m`` elements,
    and the edges of the box of ``g`` prepared (the current field's reach plus its margin,
    :meth:`chunkdic.passes.level.LevelPasses.prepare`, taken for a small field)."""
    grid = [-(-n // m) for n in mesh.shape]
    chunk = [min(m, n) * mesh.element_size + 2 for n in mesh.shape]
    item = np.dtype(f_dtype).itemsize
    if sigma > 0:
        item = 2 if quantization(f_dtype)[1] > 0 else 4
    f_copy = math.prod(grid) * math.prod(chunk) * item
    if not prepared:
        return int(f_copy), 0, [0, 0, 0]
    margin = max(8, mesh.element_size)
    box = [min(r.stop + margin + 3, n) - max(r.start - margin - 1, 0) for r, n in zip(mesh.roi, g_shape)]
    item = 2 if prepared_grid(g_dtype, sigma, interpolation)[1] > 0 else 4
    return int(f_copy), int(math.prod(box) * item), box


def output_bytes(mesh: Mesh, cell: int = 1, keeps_matrix: bool = True) -> int:
    """The output's peak size: a result's nodal fields, flags, uncertainty, history, the
    checkpoint (float64), and, while the run is incomplete, the finest level's ``M`` kept for
    a resumed run (:func:`chunkdic.passes.stored_matrix.stored_bytes`, 504 bytes per node:
    0.98 GiB at 2048³, ℓ = 16), which the complete result replaces with the rest of the
    checkpoint; ``keeps_matrix`` False: a level whose mesh data are in node blocks, whose ``M``
    is not kept (a resumed run sums it again)."""
    kept = stored_bytes(mesh.nodes_shape, cell) if keeps_matrix else 0
    return int(math.prod(mesh.nodes_shape) * 8 * 16 + kept + MiB)


def calibrate(g_ref, sigma: float, interpolation: str, threads: int) -> float:
    """Seconds per filtered voxel per task of the prefilter of ``g``, measured on the data.

    ``threads`` regions of :data:`CALIBRATION_EDGE` voxels near the centre of ``g`` are read
    with the prefilter's halo and prepared concurrently, :data:`CALIBRATION_REPEATS` times;
    the fastest wall time, times ``threads``, over the voxels filtered: what one task pays
    per voxel now (load included; about 0.3 s).
    """

    h = prepared_halo(sigma, interpolation, int(config.get("bspline-halo")))
    shape = g_ref.shape
    edge = [min(CALIBRATION_EDGE + 2 * h, n) for n in shape]
    regions = []
    for k in range(threads):
        corner = [max(0, min(n - e, n // 2 - e // 2 + (k - threads // 2) * e * (a == 2)))
                  for a, (n, e) in enumerate(zip(shape, edge))]
        regions.append(tuple(slice(c, c + e) for c, e in zip(corner, edge)))
    prepare_deformed(np.zeros((8, 8, 8), np.float32), sigma, interpolation)  # kernels loaded, not timed

    def one(region):
        return prepare_deformed(g_ref.read(region), sigma, interpolation).size

    best = math.inf
    with concurrent.futures.ThreadPoolExecutor(threads) as pool:
        for _ in range(CALIBRATION_REPEATS):  # the faster: the first also reads from the disk
            t0 = time.perf_counter()
            voxels = sum(pool.map(one, regions))
            best = min(best, (time.perf_counter() - t0) * threads / max(voxels, 1))
    return best


def pyramid_tasks(scan, levels) -> tuple[int, int]:
    """``(bytes, count)`` of the largest tasks building a missing pyramid level: each reads
    its chunk's source region (2x the chunk per side) and sums it into the wider dtype."""
    stored, chunk = set(scan.stored_levels()), int(config.get("chunk-size"))
    out = (0, 0)
    for s in levels:
        if s not in stored and s > 0:
            shape = scan.shape(s)
            edge = [min(2 * chunk, n) for n in scan.shape(s - 1)]
            items = np.dtype(scan.dtype(s - 1)).itemsize + np.dtype(scan.dtype(s)).itemsize
            out = max(out, (math.prod(edge) * items, math.prod(-(-n // chunk) for n in shape)))
    return out

"""The plan of a correlation before anything runs: what it holds, writes and costs.

:func:`plan` (and every :func:`chunkdic.correlate`, before it writes anything) works out,
from the scans' shapes and dtypes and the settings alone,

- the levels, their meshes and blocks;
- the memory of one task and of the client, hence the peak of each process: a process
  holds a base (Python, NumPy, numba, zarr and the kernels: :data:`BASE_BYTES` when it
  compiles them, :data:`WARM_BASE_BYTES` when they load from numba's cache), the
  client's mesh-sized data (:data:`CLIENT_BYTES_PER_NODE` per node of the finest mesh) and,
  with the embedded thread pool, one task per thread;
- the scratch disk (missing pyramid levels for the whole run; per level the haloed copy of
  ``f`` and the prepared ``g``, deleted when the level ends) and the output's size;
- the time, from per-voxel costs measured on this machine (:data:`COSTS`, relative to the
  prefilter of ``g``) scaled by a short calibration on the real data: the prefilter of one
  region of ``g`` per thread, run concurrently and timed (so the load of the machine and
  the speed of the disk count).

A memory target (``memory_target=``, ``--memory-target``, ``chunkdic.memory-target``) picks
the largest block (and prefilter task) edge whose estimated peak fits; a run that cannot
fit it, or whose scratch or output does not fit the free disk, is refused
(:class:`~chunkdic.errors.InputError`, one line, exit 2) before anything is written.
docs/engine.md, "Plan, memory target and disk".
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import dataclasses
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from .. import config
from ..errors import DiskSpaceError, InputError
from ..io.diskspace import DISK_MARGIN
from ..io.diskspace import existing_parent as _existing_parent
from ..io.diskspace import free_bytes as _free
from ..io.scan import open_scan
from ..io.scratch import kept_scratch, reclaimable_scratch_bytes
from ..mesh import Mesh
from ..scheduler import local_workers
from .greylevel import aligned_block_elements, offset_cell
from .haloed import quantization
from .initial import open_init
from .planning import plan_meshes
from .prefilter import (
    face_margin,
    gaussian_radius,
    prepare_deformed,
    prepare_voxels,
    prepared_grid,
    prepared_halo,
    task_edge,
)
from .scratchstore import COMPACT_RATIO, COMPACT_WORK, layout
from .stored_matrix import cells_bytes, stored_bytes
from .settings import Settings

GiB, MiB = 2**30, 2**20

#: resident memory of a running correlation's process besides its tasks and mesh data
#: when it compiles its numba kernels (bytes; measured: a 128³ run whose tasks and mesh
#: planned 84 MiB peaked at 450-456 MiB with an empty numba cache, NUMBA_CACHE_DIR=$(mktemp -d))
BASE_BYTES = 372 * MiB
#: the same when every kernel the run uses loads from numba's cache (:func:`kernels_cached`;
#: the same runs peaked at 303-312 MiB: compiling holds LLVM's memory besides). Set from a
#: fresh install (the CI's new virtual environment), whose warm 128³ run peaked at
#: 359-366 MiB, a base of ~282 MiB; the same code and package versions in a long-lived
#: development environment peaked 52 MiB lower (base ~246 MiB; cause not found, session 28)
WARM_BASE_BYTES = 285 * MiB
#: modules whose numba kernels a correlation runs: the block kernels, the pyramid's sums,
#: the client's solver (a run compiles those missing from numba's cache)
KERNEL_MODULES = ("chunkdic.kernels.b", "chunkdic.kernels.m", "chunkdic.kernels.interp", "chunkdic.kernels.rows",
                  "chunkdic.kernels.warp", "chunkdic.kernels.lowpass", "chunkdic.kernels.pwrite", "chunkdic.kernels.quantize",
                  "chunkdic.io.coarsen",
                  "chunkdic.solve.stencil", "chunkdic.solve.galerkin", "chunkdic.solve.multigrid",
                  "chunkdic.solve.regularization")
#: client bytes per node of the finest mesh: the float32 half stencil of ``M`` (504 B), the
#: V-cycle's coarse ``M``, the fields of the Gauss–Newton state, a ``b`` pass's nodal and
#: element rows and a solve's vectors at their peak (measured at 128³ nodes with 182 MiB of
#: kernels, ``bench_client_memory.py --steps --iterations 2``: 2 157 MiB with a length that
#: takes the V-cycle, 988 B per node; 1 967 MiB, 892 B, with block-Jacobi, to which the
#: two-lane CG (solve.lanes) adds one vector, 24 B; 1 300 before the
#: cuts of docs/distributed.md, "Where the client's memory goes"). The automatic length is
#: not known before the run: the larger.
CLIENT_BYTES_PER_NODE = 1000
#: float32 copies of its (haloed) region that a block task holds at its peak, the memory-
#: mapped pages of the prepared ``g`` it touches included (fitted on 128³-256³ runs,
#: blocks of 32-128 voxels)
TASK_COPIES = 12.0
#: float32 copies of its haloed region a task of the prefilter of ``g`` holds besides its
#: raw read: the copy the low-pass and B-spline sweeps work in and the z sweep's source
#: (measured by ``benchmarks/bench_prefilter_memory.py``: +43.6 MiB for a 179³ region,
#: +52.2 MiB for 190³: 2.0). The task's peak adds the raw region in its dtype, the cropped
#: float32 copy and its uint16 quantisation (6 bytes per voxel of the task) and the read's
#: buffers (:data:`READ_BUFFERS_PER_CHUNK`); two tasks at once hold twice one's (measured:
#: 20 tasks of 147³ on 2 threads peaked at 194-242 MiB, one alone at 117-128 MiB); the
#: store is written by ``pwrite`` and adds nothing (docs/distributed.md, "The plan's memory
#: at 512³-2048³")
PREPARE_COPIES = 2.0
#: decoded chunks' worth of memory zarr holds per chunk it is reading, for up to
#: ``async.concurrency`` (10) of the chunks a region crosses (their compressed bytes and the
#: decoded chunks; ``benchmarks/bench_prefilter_memory.py``): a scan's own chunks, taken as
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
#: machine's 128³-512³ runs, benchmarks/bench_plan.py; the 2048³ passes of
#: docs/distributed.md give 0.58 and 0.65): the ``M`` pass (with the low-pass of ``f``),
#: one ``b`` pass, one level of the scratch pyramid (per level-0 voxel of one scan)
COSTS = {"m": 0.9, "b": 0.5, "pyramid": 0.12}
#: Gauss–Newton passes counted per level: coarse levels (rigid step included on the
#: coarsest), the finest level (its passes around the length choice: 3-4 on the 300³-1024³
#: band pairs since the start gaps are summed inside the first one and the stopping rule
#: predicts the passes still to come, 5 before; 7 counted then, with the 2 gap passes)
PASSES = {"coarse": 4, "coarsest-extra": 3, "finest": 5}
#: client seconds per finest node and solve, and solves counted (iterations, length choice)
SOLVE_SECONDS_PER_NODE, SOLVES = 1.0e-5, 14
#: fixed seconds: kernels loaded from the cache, runner, output
FIXED_SECONDS = 6.0
#: seconds per filtered voxel of a prefilter task assumed without a calibration
UNCALIBRATED = 1.0 / 6e6
#: edge of each calibration region (voxels of ``g``, before its halo)
CALIBRATION_EDGE = 64
#: least interval between two :func:`release_freed_memory` calls of a pass (seconds)
TRIM_SECONDS = 0.1
#: times the calibration runs (the fastest counts)
CALIBRATION_REPEATS = 3


@dataclasses.dataclass(frozen=True)
class LevelPlan:
    """One level of a :class:`Plan` (voxels of the level)."""

    level: int
    nodes: tuple[int, int, int]
    roi_voxels: int
    block_elements: int
    block_edge: int
    blocks: int
    f_copy_bytes: int
    prepared_bytes: int
    task_bytes: int
    work: float
    seconds: float = math.nan


@dataclasses.dataclass(frozen=True)
class Plan:
    """What a correlation will hold, write and cost (estimates, bytes and seconds).

    Attributes
    ----------
    levels : tuple of LevelPlan
        Coarsest first.
    threads : int
        Tasks at once (threads of the embedded pool, or workers' threads).
    separate_client : bool
        Tasks run in other processes (a LocalCluster or a cluster): the client's process
        holds no task, each worker one task per thread.
    client_bytes, task_bytes : int
        The client's mesh-sized data; the largest task.
    process_bytes : int
        Estimated peak resident memory of the largest process.
    pyramid_bytes, scratch_bytes, output_bytes : int
        Scratch pyramid levels (all of them at the start; each deleted when its level
        ends); peak scratch (the largest, over levels, of a level's haloed ``f`` and
        prepared ``g`` plus the pyramid levels still held); the result.
    layout : {"fast", "compact"}
        How the levels' scratch stores are kept (:mod:`chunkdic.engine.scratchstore`):
        compact when the fast layout's ``fast_scratch_bytes`` do not fit the free disk
        (``chunkdic.scratch-layout: auto``), or when forced.
    scratch_dir, output_dir : str
        Where they go; ``scratch_free``, ``output_free`` their free bytes now.
    seconds : float
        Estimated wall time of the correlation; ``calibration`` says from what.
    block_voxels, prepare_edge : int
        Block edge target (``chunkdic.block-voxels``) and prefilter task edge chosen.
    memory_target : int or None
        Bytes per process asked for.
    """

    levels: tuple
    threads: int
    separate_client: bool
    client_bytes: int
    task_bytes: int
    process_bytes: int
    pyramid_bytes: int
    scratch_bytes: int
    output_bytes: int
    scratch_dir: str
    scratch_free: int
    output_dir: str | None
    output_free: int | None
    seconds: float
    calibration: str
    block_voxels: int
    prepare_edge: int
    memory_target: int | None = None
    fixed_work: float = 0.0
    solve_seconds: float = 0.0
    smallest_bytes: int = 0
    layout: str = "fast"
    fast_scratch_bytes: int = 0
    base_bytes: int = BASE_BYTES

    def timed(self, seconds_per_voxel: float | None, label: str | None = None) -> "Plan":
        """The plan with its times from ``seconds_per_voxel`` of one task's prefilter of ``g``
        (:func:`calibrate`; ``None``: :data:`UNCALIBRATED` assumed)."""
        unit = UNCALIBRATED if seconds_per_voxel is None else seconds_per_voxel
        if label is None:
            label = (f"calibrated now: prefilter of g at {1e-6 / unit:.1f} Mvoxel/s per task, {self.threads} at once"
                     if seconds_per_voxel is not None else
                     f"not calibrated: prefilter of g at {1e-6 / unit:.0f} Mvoxel/s per task assumed")
        levels = tuple(dataclasses.replace(lv, seconds=lv.work * unit / self.threads) for lv in self.levels)
        seconds = sum(lv.seconds for lv in levels) + self.fixed_work * unit / self.threads
        return dataclasses.replace(self, levels=levels, seconds=seconds + FIXED_SECONDS + self.solve_seconds,
                                   calibration=label)

    def summary(self) -> str:
        """Several lines for a person: one per level, then memory, disk and time."""
        out = [f"plan: levels {[lv.level for lv in self.levels]}, {self.threads} tasks at once"
               + (" in worker processes" if self.separate_client else " in this process")]
        for lv in self.levels:
            out.append(f"  level {lv.level}: {'x'.join(map(str, lv.nodes))} nodes, {lv.roi_voxels / 1e6:.1f} Mvoxel, "
                       f"{lv.blocks} blocks of {lv.block_edge}³ voxels ({lv.block_elements}³ elements), "
                       f"task {_b(lv.task_bytes)}, scratch {_b(lv.f_copy_bytes + lv.prepared_bytes)}, "
                       f"~{lv.seconds:.0f} s")
        target = "" if self.memory_target is None else f" (target {_b(self.memory_target)})"
        out.append(f"  memory: client {_b(self.client_bytes)} of mesh data, tasks {_b(self.task_bytes)} at once; "
                   f"peak per process ~{_b(self.process_bytes)}{target}")
        disk = f"  disk: scratch {_b(self.scratch_bytes)} (pyramids {_b(self.pyramid_bytes)}) in {self.scratch_dir} " \
               f"({_b(self.scratch_free)} free), {self._layout_words()}"
        if self.output_dir is not None:
            disk += f"; output {_b(self.output_bytes)} in {self.output_dir} ({_b(self.output_free)} free)"
        out.append(disk)
        out.append(f"  time: ~{_duration(self.seconds)} ({self.calibration})")
        return "\n".join(out)

    def line(self) -> str:
        """The plan in one line (printed at the start of every run)."""
        finest = self.levels[-1]
        return (f"plan: levels {[lv.level for lv in self.levels]}, level {finest.level} "
                f"{'x'.join(map(str, finest.nodes))} nodes in {finest.blocks} blocks of {finest.block_edge}³; "
                f"memory ~{_b(self.process_bytes)} per process (client {_b(self.client_bytes)}, tasks "
                f"{_b(self.task_bytes)}); scratch {_b(self.scratch_bytes)} {self.layout}; ~{_duration(self.seconds)}")

    def _layout_words(self) -> str:
        if self.layout == "fast":
            return "fast layout (uncompressed)"
        why = (f"the fast layout's {_b(self.fast_scratch_bytes)} do not fit"
               if self.fast_scratch_bytes * DISK_MARGIN > self.scratch_free else "chunkdic.scratch-layout")
        return f"compact layout (coarser grid, compressed; {why}; passes slower)"

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    def check(self) -> None:
        """Refuse (:class:`InputError`, one line) a run the memory target or the disk cannot hold."""
        if self.memory_target is not None and self.process_bytes > self.memory_target:
            finest = self.levels[-1]
            raise InputError(
                f"memory target {_b(self.memory_target)} per process cannot hold this run: the client alone needs "
                f"{_b(self.base_bytes + self.client_bytes)} for {math.prod(finest.nodes)} nodes, and the estimated peak "
                f"is {_b(self.smallest_bytes)} with the smallest blocks: raise the target, or use larger elements "
                f"or a coarser level")
        same_disk = self.output_dir is not None and _device(self.scratch_dir) == _device(self.output_dir)
        need = self.scratch_bytes + (self.output_bytes if same_disk else 0)
        if need * DISK_MARGIN > self.scratch_free:
            what = "scratch and output need" if same_disk else "scratch needs"
            what += " in the compact layout" if self.layout == "compact" else ""
            raise DiskSpaceError(f"not enough disk: this run's {what} {_b(need)} in {self.scratch_dir}, "
                                 f"{_b(self.scratch_free)} free: free some, or set chunkdic.scratch-directory "
                                 f"(DASK_CHUNKDIC__SCRATCH_DIRECTORY) to a larger disk{_kept_words(self.scratch_dir)}")
        if self.output_dir is not None and not same_disk and self.output_bytes * DISK_MARGIN > self.output_free:
            raise DiskSpaceError(f"not enough disk for the output: {_b(self.output_bytes)} needed in "
                                 f"{self.output_dir}, {_b(self.output_free)} free")


def _kept_words(scratch_dir) -> str:
    """What the scratch kept for other outputs' resumes holds in ``scratch_dir`` (a refusal's
    hint: resuming or removing those outputs frees it), or ``""``."""
    kept = kept_scratch(Path(scratch_dir))
    if not kept:
        return ""
    outputs = ", ".join(dict.fromkeys(out for _, out, _ in kept))
    return (f" ({_b(sum(n for _, _, n in kept))} there is kept for the resume of {outputs}: resume, or remove "
            "the output to free it)")


def kernels_cached() -> bool:
    """Whether numba's on-disk cache holds every kernel of :data:`KERNEL_MODULES`, so a run
    loads them rather than compiling (its base memory is then :data:`WARM_BASE_BYTES`).

    Probing only the ``b`` and ``M`` kernels (:func:`chunkdic.kernels.compiled_on_disk`) is
    not enough: on a fresh clone whose first test ran those, the next run still compiled
    the solver's and the low-pass's kernels, and peaked 21 % above a plan that assumed
    the warm base. Reads numba's cache locator (not a public API): any surprise answers
    False, the higher estimate.
    """
    import importlib

    try:
        from numba.core.dispatcher import Dispatcher

        for name in KERNEL_MODULES:
            module = importlib.import_module(name)
            for obj in vars(module).values():
                if (isinstance(obj, Dispatcher) and obj.py_func.__module__ == name
                        and obj.targetoptions.get("inline") != "always"):  # inlined helpers have no cache
                    if not os.path.exists(obj._cache._cache_file._index_path):
                        return False
    except Exception:  # noqa: BLE001 - numba internals changed: assume a compiling run
        return False
    return True


def base_bytes() -> int:
    """A process's memory besides its tasks and mesh data: :data:`WARM_BASE_BYTES` when
    every kernel loads from numba's cache, else :data:`BASE_BYTES`."""
    return WARM_BASE_BYTES if kernels_cached() else BASE_BYTES


_LIBC: list = []


def release_freed_memory() -> None:
    """Return to the system the pages that freed buffers leave in glibc's heaps (``malloc_trim``).

    glibc raises its mmap threshold to the largest buffer freed (up to 32 MB), after which
    a task's NumPy arrays come from heaps whose freed pages stay resident: in the embedded
    pool, where the tasks' threads are the client's process, a 512³ run's peak grew to
    0.73 GiB over the level-0 passes, against 0.40 GiB with ``MALLOC_MMAP_THRESHOLD_=65536``
    in the environment. Called by the passes (:meth:`chunkdic.engine.level.Level._map`) at
    most every :data:`TRIM_SECONDS`, it brought the peak to 0.61-0.62 GiB (0.62 GiB every
    0.25 s); a no-op without glibc. (Dask's nanny sets ``MALLOC_TRIM_THRESHOLD_`` for its
    workers itself.)
    """
    if not _LIBC:
        try:
            libc = ctypes.CDLL("libc.so.6")
            libc.malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):
            libc = None
        _LIBC.append(libc)
    if _LIBC[0] is not None:
        _LIBC[0].malloc_trim(0)


def parse_memory(value) -> int | None:
    """Bytes from ``"2GiB"``, ``"1.5 GB"``, ``2e9`` or ``None``; refuse anything else."""
    if value is None or value == "":
        return None
    from dask.utils import parse_bytes

    try:
        out = int(parse_bytes(value)) if isinstance(value, str) else int(value)
    except (TypeError, ValueError):
        raise InputError(f"memory target {value!r}: expected a size such as 2GiB or 1500MB") from None
    if out <= 0:
        raise InputError(f"memory target {value!r} must be positive")
    return out


def memory_target_of(value=None) -> int | None:
    """``value``, else ``chunkdic.memory-target`` from dask.config, as bytes (or ``None``)."""
    return parse_memory(value if value is not None else config.get("memory-target"))


def threads_of(scheduler) -> tuple[int, int, bool]:
    """``(tasks at once per process, tasks at once in all, tasks in other processes)`` for a
    ``scheduler`` argument (an address not yet reached counts as one worker per core here)."""
    cores = os.cpu_count() or 1
    if scheduler is None or scheduler == "threads":
        n = int(config.get("num-threads") or cores)
        return n, n, False
    if isinstance(scheduler, str) and scheduler.startswith("local"):
        # a LocalCluster of single-threaded workers (chunkdic.scheduler.open_runner)
        return 1, local_workers(scheduler) or cores, True
    info = getattr(scheduler, "scheduler_info", None)
    if callable(info):
        nthreads = [int(w.get("nthreads", 1)) for w in info().get("workers", {}).values()] or [1]
        return max(nthreads), sum(nthreads), True
    return 1, cores, True


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
        The preparation (its halo, :func:`~chunkdic.engine.prefilter.prepared_halo`).
    shape : tuple of 3 int, optional
        The level's shape: the region grown by the halo is clipped to it.
    raw_itemsize : int
        Bytes per voxel of ``g`` as read (its dtype at the level).
    quantized : bool
        The store is uint16 (:func:`~chunkdic.engine.prefilter.prepared_grid`): the task
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


def pyramid_bytes(scan, levels) -> int:
    """Scratch bytes of the pyramid levels a scan lacks (uncompressed: an upper bound)."""
    return sum(pyramid_levels(scan, levels).values())


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
    :func:`chunkdic.engine.steps.release_scan_levels`)."""
    held = [sum(pyramids.values())]
    held += [stores[s] + sum(b for t, b in pyramids.items() if t <= s) for s in stores]
    return int(max(held))


def level_disk(mesh: Mesh, g_shape, m: int, sigma: float, f_dtype, prepared: bool, g_dtype=None,
               interpolation: str = "cubic") -> tuple[int, int, list]:
    """``(haloed f copy, prepared g)`` scratch bytes of a level with blocks of ``m`` elements,
    and the edges of the box of ``g`` prepared (the current field's reach plus its margin,
    :meth:`chunkdic.engine.level.Level.prepare_interpolation`, taken for a small field)."""
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


def output_bytes(mesh: Mesh, cell: int = 1) -> int:
    """The output's peak size: a result's nodal fields, flags, uncertainty, history, the
    checkpoint (float64), and, while the run is incomplete, the finest level's ``M`` kept for
    a resumed run (:func:`chunkdic.engine.stored_matrix.stored_bytes`, 504 bytes per node:
    0.98 GiB at 2048³, ℓ = 16), which the complete result replaces with the rest of the checkpoint."""
    return int(math.prod(mesh.nodes_shape) * 8 * 16 + stored_bytes(mesh.nodes_shape, cell) + MiB)


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


def make_plan(f_scan, g_scan, meshes: dict, settings, *, scheduler=None, output=None, target=None,
              scratch_dir=None) -> Plan:
    """The :class:`Plan` of a run; ``target`` (bytes per process) chooses the block edge and
    the prefilter's task edge: the largest (up to ``chunkdic.block-voxels`` and
    :data:`~chunkdic.engine.prefilter.TASK_EDGE`) whose estimated peak fits."""
    threads, concurrency, separate = threads_of(scheduler)
    base = base_bytes()
    levels = sorted(meshes, reverse=True)
    sigma, interp = settings.smoothing, settings.interpolation
    prepared = interp == "cubic" or sigma > 0
    finest = meshes[levels[-1]]

    def cell_of(mesh: Mesh) -> int:
        return offset_cell(settings.grey, mesh.element_size, settings.grey_cell)

    def client_bytes(mesh: Mesh) -> int:
        # the mesh-sized data and the brightness cells' couplings (stored_matrix.cells_bytes)
        return CLIENT_BYTES_PER_NODE * math.prod(mesh.nodes_shape) + cells_bytes(mesh.shape, cell_of(mesh))

    client = client_bytes(finest)
    pyr_task, pyr_tasks = max(_pyramid_tasks(scan, levels) for scan in (f_scan, g_scan))

    h = prepared_halo(sigma, interp, int(config.get("bspline-halo")))

    def prepare_task_bytes(s: int, edges) -> int:
        """The largest prefilter task of level ``s`` with tasks of ``edges`` voxels."""
        shape = g_scan.shape(s)
        return prepare_bytes(edges, sigma, interp, shape=shape, raw_itemsize=np.dtype(g_scan.dtype(s)).itemsize,
                             quantized=prepared_grid(g_scan.dtype(s), sigma, interp)[1] > 0,
                             read_bytes=read_buffer_bytes(g_scan, s, [e + 2 * h for e in edges]))

    def elements(edge: int, mesh: Mesh) -> int:
        # as the level makes its blocks (whole brightness cells, chunkdic.engine.level.Level)
        m = aligned_block_elements(settings.block_elements or max(1, edge // mesh.element_size), cell_of(mesh))
        return min(m, max(mesh.shape))

    def peak(edge: int, prep_edge: int) -> tuple[int, int]:
        """(largest task, peak of the largest process) with blocks of ``edge`` voxels: a kind
        of task runs at most ``threads`` at once, and never more than there are of it; in
        this process, with the client's data of the level the tasks belong to (a coarse
        level's prefilter, whose reads decode the scratch pyramid's uint32 chunks, may hold
        more than the finest level's tasks, but beside a small mesh)."""
        held = [(pyr_task * min(threads, pyr_tasks), 0)]  # (tasks at once, the client's data then)
        for s in levels:
            mesh = meshes[s]
            on_client = client_bytes(mesh)
            m = elements(edge, mesh)
            n_blocks = math.prod(-(-n // m) for n in mesh.shape)
            cache = chunk_cache_bytes((f_scan, g_scan), s)  # once per process, shared by its threads
            held.append((task_bytes(m * mesh.element_size, sigma, interp) * min(threads, n_blocks) + cache,
                         on_client))
            if prepared:
                box = level_disk(mesh, g_scan.shape(s), m, sigma, f_scan.dtype(s), prepared, g_scan.dtype(s), interp)[2]
                edges = [task_edge(b, 1, prep_edge) for b in box]
                n_prep = math.prod(-(-b // e) for b, e in zip(box, edges))
                held.append((prepare_task_bytes(s, edges) * min(threads, n_prep) + cache, on_client))
        task = max(t for t, _ in held)
        if separate:
            return task, base + max(client, task)
        return task, base + max(client, max(t + c for t, c in held))

    edge, prep_edge = int(config.get("block-voxels")), prepare_voxels()
    smallest = peak(1, MIN_PREPARE_EDGE)[1]
    if target is not None and smallest <= target:  # else refused, the plan showing the default blocks
        ell_min = min(m.element_size for m in meshes.values())
        while peak(edge, prep_edge)[1] > target and edge > ell_min and settings.block_elements is None:
            edge = max(ell_min, int(edge * 0.8))
            prep_edge = max(MIN_PREPARE_EDGE, min(prep_edge, edge + 32))
        while peak(edge, prep_edge)[1] > target and prep_edge > MIN_PREPARE_EDGE:
            prep_edge = max(MIN_PREPARE_EDGE, prep_edge - 16)
    task, process = peak(edge, prep_edge)

    plans = []
    for i, s in enumerate(levels):
        mesh = meshes[s]
        m = elements(edge, mesh)
        n_blocks = math.prod(-(-n // m) for n in mesh.shape)
        f_copy, prep, box = level_disk(mesh, g_scan.shape(s), m, sigma, f_scan.dtype(s), prepared, g_scan.dtype(s), interp)
        passes = PASSES["finest"] if i == len(levels) - 1 else PASSES["coarse"]
        passes += PASSES["coarsest-extra"] if i == 0 else 0
        filtered = math.prod(b + 2 * h * -(-b // task_edge(b, 1, prep_edge)) for b in box) if prep else 0
        work = mesh.n_voxels * (COSTS["m"] + passes * COSTS["b"]) + filtered
        plans.append(LevelPlan(s, tuple(mesh.nodes_shape), int(mesh.n_voxels), int(m), int(m * mesh.element_size),
                               int(n_blocks), f_copy, prep, task_bytes(m * mesh.element_size, sigma, interp), work))
    pyramids = {}
    for scan in (f_scan, g_scan):
        for s, b in pyramid_levels(scan, levels).items():
            pyramids[s] = pyramids.get(s, 0) + b
    pyr = sum(pyramids.values())
    root = Path(scratch_dir or config.get("scratch-directory") or tempfile.gettempdir())
    # what dead runs left there is this run's to reclaim or (a resume) to reuse: free for the plan,
    # or a resume would find its own interrupted run's scratch filling the disk it needs
    free = _free(root) + reclaimable_scratch_bytes(root, release=output)
    fast = peak_scratch(pyramids, {lv.level: lv.f_copy_bytes + lv.prepared_bytes for lv in plans})
    chosen = layout()
    if chosen == "auto":
        chosen = "compact" if fast * DISK_MARGIN > free else "fast"
    if chosen == "compact":
        plans = [compact_level(lv, f_scan.dtype(lv.level), g_scan.dtype(lv.level), sigma, interp) for lv in plans]
    scratch = peak_scratch(pyramids, {lv.level: lv.f_copy_bytes + lv.prepared_bytes for lv in plans})
    pyr_work = 2 * COSTS["pyramid"] * math.prod(f_scan.shape(0)) if pyr else 0.0
    solve_seconds = SOLVE_SECONDS_PER_NODE * SOLVES * math.prod(finest.nodes_shape)
    out_dir = None if output is None else _existing_parent(Path(output).absolute().parent)
    return Plan(tuple(plans), concurrency, separate, client, task, process, pyr, scratch, output_bytes(finest, cell_of(finest)),
                str(_existing_parent(root.absolute())), free, None if out_dir is None else str(out_dir),
                None if out_dir is None else _free(out_dir), math.nan, "", edge, prep_edge, target, pyr_work,
                solve_seconds, smallest, chosen, fast, base).timed(None)


def compact_level(lv: LevelPlan, f_dtype, g_dtype, sigma: float, interpolation: str) -> LevelPlan:
    """``lv`` with its 16-bit scratch stores planned at :data:`COMPACT_RATIO` of their bytes
    (the compact layout compresses those only: float32 stores stay as they are), and its
    work :data:`COMPACT_WORK` times larger when it has such stores."""
    f_copy, prep = lv.f_copy_bytes, lv.prepared_bytes
    if sigma > 0 and quantization(f_dtype)[1] > 0:
        f_copy = int(f_copy * COMPACT_RATIO["f"])
    if prep and prepared_grid(g_dtype, sigma, interpolation)[1] > 0:
        prep = int(prep * COMPACT_RATIO["g"])
    slower = COMPACT_WORK if (f_copy, prep) != (lv.f_copy_bytes, lv.prepared_bytes) else 1.0
    return dataclasses.replace(lv, f_copy_bytes=f_copy, prepared_bytes=prep, work=lv.work * slower)


def _pyramid_tasks(scan, levels) -> tuple[int, int]:
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


def plan(ref, deformed, settings=None, *, roi=None, scheduler=None, output=None, init=None, mask=None,
         memory_target=None, calibrate: bool = True, **options) -> Plan:
    """The plan of ``correlate(ref, deformed, ...)`` with the same arguments, without running it.

    Reads only the scans' metadata (and, with ``calibrate``, one region of ``g`` per task,
    timed); writes nothing. :meth:`Plan.summary` prints it; :meth:`Plan.check` raises the
    :class:`~chunkdic.errors.InputError` that :func:`chunkdic.correlate` would refuse the
    run with (memory target or disk).

    Parameters
    ----------
    ref, deformed, settings, roi, scheduler, output, init, mask, **options
        As for :func:`chunkdic.correlate` (the mask's scratch levels, uint8 sums, are not counted).
    memory_target : str or int, optional
        Peak resident memory per process, ``"2GiB"`` or bytes; default
        ``chunkdic.memory-target`` (dask.config), else none.
    calibrate : bool
        Time the prefilter of one region of ``g`` per task for the time estimate.

    Returns
    -------
    Plan

    Examples
    --------
    >>> import numpy as np, chunkdic
    >>> f = np.random.default_rng(0).random((64, 64, 64)).astype(np.float32)
    >>> p = chunkdic.plan(f, f, element_size=16, memory_target="4GiB")
    >>> [lv.level for lv in p.levels], p.process_bytes < 2**32
    ([1, 0], True)
    """

    unknown = set(options) - set(Settings.names())
    if unknown:
        raise TypeError(f"plan() got unexpected keyword arguments {sorted(unknown)}")
    settings = dataclasses.replace(settings, **options) if settings is not None else Settings(**options)
    f_scan, g_scan = open_scan(ref), open_scan(deformed)
    if init is not None:
        open_init(init, f_scan.shape(0))
    coarsest = settings.level if init is not None and settings.coarsest is None else settings.coarsest
    meshes = plan_meshes(f_scan.shape(0), element_size=settings.element_size, roi=roi, level=settings.level,
                         coarsest=coarsest, min_margin=face_margin(settings.smoothing))
    out = make_plan(f_scan, g_scan, meshes, settings, scheduler=scheduler, output=output,
                    target=memory_target_of(memory_target))
    return calibrated(out, g_scan, settings) if calibrate else out


def calibrated(p: Plan, g_scan, settings) -> Plan:
    """``p`` timed by :func:`calibrate` on ``g_scan``'s first stored level (as it is without one)."""
    stored = g_scan.stored_refs()
    if not stored or not (settings.interpolation == "cubic" or settings.smoothing > 0):
        return p
    return p.timed(calibrate(stored[min(stored)], settings.smoothing, settings.interpolation, p.threads))


def _device(path) -> int:
    return os.stat(_existing_parent(path)).st_dev


def _b(n: float) -> str:
    for unit, size in (("GiB", GiB), ("MiB", MiB)):
        if n >= size or unit == "MiB":
            return f"{n / size:.2f} {unit}" if unit == "GiB" else f"{n / size:.0f} MiB"
    return f"{n} B"


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"

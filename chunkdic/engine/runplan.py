"""The plan of a correlation before anything runs: what it holds, writes and costs.

:func:`plan` (and every :func:`chunkdic.correlate`, before it writes anything) works out
the levels, their meshes and blocks, the peak memory of each process, the scratch disk and
the output's size, and the time, from the cost model of :mod:`chunkdic.engine.costs`.

A memory target (``memory_target=``, ``--memory-target``, ``chunkdic.memory-target``) picks
the largest block (and prefilter task) edge whose estimated peak fits; a run that cannot
fit it, or whose scratch or output does not fit the free disk, is refused
(:class:`~chunkdic.errors.InputError`, one line, exit 2) before anything is written.
docs/engine.md, "Plan, memory target and disk".
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
from pathlib import Path

from .. import config
from ..errors import DiskSpaceError, InputError
from ..inputs import memory_target_of
from ..io.diskspace import DISK_MARGIN
from ..io.diskspace import existing_parent as _existing_parent
from ..io.diskspace import free_bytes as _free
from ..io.scratch import kept_scratch, reclaimable_scratch_bytes
from ..method.settings import Settings
from ..passes.haloed import quantization
from ..passes.prefilter import prepared_grid, task_edge
from ..passes.scratchstore import COMPACT_RATIO, COMPACT_WORK, layout
from .costs import (
    BASE_BYTES,
    COSTS,
    FIXED_SECONDS,
    MIN_PREPARE_EDGE,
    PASSES,
    SOLVE_SECONDS_PER_NODE,
    SOLVES,
    UNCALIBRATED,
    GiB,
    MiB,
    base_bytes,
    blocks_bytes,
    calibrate,
    mesh_blocks_scratch,
    output_bytes,
    peak_scratch,
    pyramid_scratch,
    task_bytes,
)
from .front import prepare_run
from .processmemory import MemoryModel, fitting_edges, mesh_placement


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
    mesh_data : {"client", "workers", "disk"}
        Where the finest level's mesh data live: the client, or node blocks on the workers
        (a cluster) or on the scratch disk (the embedded scheduler);
        ``mesh_why`` says why. ``mesh_blocks_from``: levels of at least this many nodes go
        to blocks (None: none); ``blocks_bytes``: their blocks together (spread over the
        ``workers``, the processes the tasks run in, or on disk).
    layout : {"fast", "compact"}
        How the levels' scratch stores are kept (:mod:`chunkdic.passes.scratchstore`):
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
    mesh_data: str = "client"
    mesh_why: str = ""
    mesh_blocks_from: int | None = None
    blocks_bytes: int = 0
    workers: int = 1

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
        out.append(f"  mesh data: {self._mesh_words()}")
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
                f"{_b(self.task_bytes)}); mesh data {self.mesh_data}; scratch {_b(self.scratch_bytes)} {self.layout}; "
                f"~{_duration(self.seconds)}")

    def _mesh_words(self) -> str:
        if self.mesh_data == "client":
            return f"in the client ({self.mesh_why})"
        where = (f"on the {self.workers} workers ({_b(self.blocks_bytes / self.workers)} each)"
                 if self.mesh_data == "workers" else f"in files under the scratch ({_b(self.blocks_bytes)}), the solver's vectors in the client")
        return f"in node blocks {where}, levels of {self.mesh_blocks_from}+ nodes ({self.mesh_why})"

    def _layout_words(self) -> str:
        if self.layout == "fast":
            return "fast layout (uncompressed)"
        why = (f"the fast layout's {_b(self.fast_scratch_bytes)} do not fit"
               if self.fast_scratch_bytes * DISK_MARGIN > self.scratch_free else "chunkdic.scratch-layout")
        return f"compact layout (coarser grid, compressed; {why}; passes slower)"

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    def check(self, *, crack: bool = False) -> None:
        """Refuse (:class:`InputError`, one line) a run the memory target or the disk cannot hold
        (``crack``: a known crack, whose second node copies the node blocks do not hold)."""
        if crack and self.mesh_data != "client":
            raise InputError(f"--crack needs the mesh data in the client, and the plan puts them in node blocks "
                             f"({self.mesh_why}): raise --memory-target or set chunkdic.mesh-data to client")
        if self.memory_target is not None and self.process_bytes > self.memory_target:
            finest = self.levels[-1]
            client = self.base_bytes + self.client_bytes
            who = f"the client alone needs {_b(client)} for {math.prod(finest.nodes)} nodes"
            if client <= self.memory_target and self.mesh_data == "workers":
                who = (f"each worker needs {_b(self.process_bytes)} with its share of the node blocks "
                       f"({_b(self.blocks_bytes / self.workers)})")
            raise InputError(
                f"memory target {_b(self.memory_target)} per process cannot hold this run: {who}, and the estimated "
                f"peak is {_b(self.smallest_bytes)} with the smallest blocks: raise the target, or use larger elements "
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


def make_plan(f_scan, g_scan, meshes: dict, settings, *, scheduler=None, output=None, target=None,
              scratch_dir=None) -> Plan:
    """The :class:`Plan` of a run; ``target`` (bytes per process) chooses the block edge and
    the prefilter's task edge: the largest (up to ``chunkdic.block-voxels`` and
    :data:`~chunkdic.passes.prefilter.TASK_EDGE`) whose estimated peak fits."""
    model = MemoryModel.of(f_scan, g_scan, meshes, settings, scheduler)
    # the mesh data go to node blocks when the client's cannot fit the target even with the
    # smallest blocks
    mesh_data, why, blocks_from = mesh_placement(model, target)
    model = dataclasses.replace(model, blocks_from=blocks_from, blocks_on_disk=mesh_data == "disk")
    edge, prep_edge = fitting_edges(model, target)
    task, process = model.peak(edge, prep_edge)
    plans = [level_plan(model, s, edge, prep_edge, coarsest=i == 0, finest=i == len(model.levels) - 1)
             for i, s in enumerate(model.levels)]
    pyramids = pyramid_scratch((f_scan, g_scan), model.levels)
    root, free = scratch_room(scratch_dir, output)
    finest = model.meshes[model.levels[-1]]
    in_blocks = mesh_data != "client"
    blocks_scratch = {}  # the finest level's M partials (and, on disk, node blocks) beside its stores
    if in_blocks:
        blocks_scratch[plans[-1].level] = mesh_blocks_scratch(finest, plans[-1].block_elements,
                                                              model.cell_of(finest), on_disk=mesh_data == "disk")
    fast = peak_scratch(pyramids, _stores_bytes(plans, blocks_scratch))
    chosen = scratch_layout(fast, free)
    if chosen == "compact":
        plans = [compact_level(lv, f_scan.dtype(lv.level), g_scan.dtype(lv.level), settings.smoothing,
                               settings.interpolation) for lv in plans]
    pyr = sum(pyramids.values())
    out_dir = None if output is None else _existing_parent(Path(output).absolute().parent)
    return Plan(
        levels=tuple(plans), threads=model.concurrency, separate_client=model.separate, client_bytes=model.client,
        task_bytes=task, process_bytes=process, pyramid_bytes=pyr,
        scratch_bytes=peak_scratch(pyramids, _stores_bytes(plans, blocks_scratch)),
        output_bytes=output_bytes(finest, model.cell_of(finest), keeps_matrix=not in_blocks),
        scratch_dir=str(_existing_parent(root.absolute())),
        scratch_free=free, output_dir=None if out_dir is None else str(out_dir),
        output_free=None if out_dir is None else _free(out_dir), seconds=math.nan, calibration="",
        block_voxels=edge, prepare_edge=prep_edge, memory_target=target,
        fixed_work=2 * COSTS["pyramid"] * math.prod(f_scan.shape(0)) if pyr else 0.0,
        solve_seconds=SOLVE_SECONDS_PER_NODE * SOLVES * math.prod(finest.nodes_shape),
        smallest_bytes=model.peak(1, MIN_PREPARE_EDGE)[1], layout=chosen, fast_scratch_bytes=fast,
        base_bytes=model.base, mesh_data=mesh_data, mesh_why=why, mesh_blocks_from=blocks_from,
        blocks_bytes=model.blocks, workers=model.workers).timed(None)


def scratch_room(scratch_dir, output) -> tuple[Path, int]:
    """The scratch directory (``scratch_dir``, else ``chunkdic.scratch-directory``, else the
    system's temporary directory) and its free bytes for this run: what dead runs left there
    counts as free, as this run reclaims it or (a resume of ``output``) reuses it; else a
    resume would find its own interrupted run's scratch filling the disk it needs."""
    root = Path(scratch_dir or config.get("scratch-directory") or tempfile.gettempdir())
    return root, _free(root) + reclaimable_scratch_bytes(root, release=output)


def level_plan(model: MemoryModel, s: int, edge: int, prep_edge: int, *, coarsest: bool, finest: bool) -> LevelPlan:
    """Level ``s``'s blocks, scratch stores and work (voxel operations of its passes, weighted
    by :data:`~chunkdic.engine.costs.COSTS`) with blocks of ``edge`` voxels."""
    mesh, sigma, interp = model.meshes[s], model.settings.smoothing, model.settings.interpolation
    m = model.elements(edge, mesh)
    n_blocks = math.prod(-(-n // m) for n in mesh.shape)
    f_copy, prep, box = model.level_disk(s, m)
    passes = PASSES["finest"] if finest else PASSES["coarse"]
    passes += PASSES["coarsest-extra"] if coarsest else 0
    filtered = math.prod(b + 2 * model.halo * -(-b // task_edge(b, 1, prep_edge)) for b in box) if prep else 0
    work = mesh.n_voxels * (COSTS["m"] + passes * COSTS["b"]) + filtered
    return LevelPlan(s, tuple(mesh.nodes_shape), int(mesh.n_voxels), int(m), int(m * mesh.element_size),
                     int(n_blocks), f_copy, prep, task_bytes(m * mesh.element_size, sigma, interp), work)


def _stores_bytes(plans, extra: dict[int, int]) -> dict[int, int]:
    """Each level's scratch stores (its low-passed ``f`` and prepared ``g``, and ``extra``:
    its mesh data in node blocks, :func:`~chunkdic.engine.costs.mesh_blocks_scratch`), bytes."""
    return {lv.level: lv.f_copy_bytes + lv.prepared_bytes + extra.get(lv.level, 0) for lv in plans}


def scratch_layout(fast_bytes: int, free: int) -> str:
    """``chunkdic.scratch-layout``; ``auto``: compact when the fast layout's peak scratch does
    not fit the free disk (with the margin of :data:`~chunkdic.io.diskspace.DISK_MARGIN`)."""
    chosen = layout()
    if chosen == "auto":
        chosen = "compact" if fast_bytes * DISK_MARGIN > free else "fast"
    return chosen


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


def plan(ref, deformed, settings: Settings | None = None, *, roi=None, scheduler=None, output=None, init=None,
         mask=None, roi_unit: str | None = None, memory_target=None, calibrate: bool = True, **options) -> Plan:
    """The plan of ``correlate(ref, deformed, ...)`` with the same arguments, without running it.

    Reads only the scans' metadata (and, with ``calibrate``, one region of ``g`` per task,
    timed); writes nothing. :meth:`Plan.summary` prints it; :meth:`Plan.check` raises the
    :class:`~chunkdic.errors.InputError` that :func:`chunkdic.correlate` would refuse the
    run with (memory target or disk).

    Parameters
    ----------
    ref, deformed, settings, roi, scheduler, output, init, mask, roi_unit, **options
        As for :func:`chunkdic.correlate` (lengths in a physical unit too, ``element_size="80um"``;
        the mask's scratch levels, uint8 sums, are not counted).
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

    spec = prepare_run(ref, deformed, settings, roi=roi, roi_unit=roi_unit, init=init, mask=mask, caller="plan",
                       **options)
    out = make_plan(spec.f_scan, spec.g_scan, spec.meshes, spec.settings, scheduler=scheduler, output=output,
                    target=memory_target_of(memory_target))
    return calibrated(out, spec.g_scan, spec.settings) if calibrate else out


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

"""The memory a run's processes hold, as a function of the block and prefilter task edges,
and where the mesh data live: the client, or node blocks on the workers or on disk
(:mod:`chunkdic.solve.nodeblocks`) when the client's cannot fit the memory target."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from .. import config
from ..io.diskspace import format_bytes
from ..mesh import Mesh
from ..method.brightness import aligned_block_elements, offset_cell
from ..method.settings import Settings
from ..passes.prefilter import prepare_voxels, prepared_grid, prepared_halo, task_edge
from ..passes.stored_matrix import cells_bytes
from ..scheduler import threads_of
from .costs import (
    BLOCKED_CLIENT_BYTES_PER_NODE,
    CLIENT_BYTES_PER_NODE,
    MIN_PREPARE_EDGE,
    base_bytes,
    blocks_bytes,
    chunk_cache_bytes,
    level_disk,
    prepare_bytes,
    pyramid_tasks,
    read_buffer_bytes,
    task_bytes,
)


def mesh_placement(model: MemoryModel, target: int | None) -> tuple[str, str, int | None]:
    """Where the mesh data go (``chunkdic.mesh-data``): ``(place, why, nodes from which a level
    goes to blocks)``. Under ``auto``, the levels whose client data (:data:`CLIENT_BYTES_PER_NODE`)
    with the process's base and smallest tasks exceed the memory target; ``blocks`` puts every
    level there."""
    mode = config.get("mesh-data")
    nodes = {math.prod(m.nodes_shape): m for m in model.meshes.values()}
    if mode == "blocks":
        where, why = blocks_place(model, target)
        return where, f"chunkdic.mesh-data: blocks{why}", min(nodes)
    if mode == "client":
        return "client", "chunkdic.mesh-data: client", None
    if target is None:
        return "client", "no memory target", None
    rest = model.peak(1, MIN_PREPARE_EDGE)[1] - model.client
    need = {n: rest + model.client_bytes(m) for n, m in nodes.items()}
    over = [n for n, b in need.items() if b > target]
    if not over:
        return "client", f"they fit the memory target {format_bytes(target)}", None
    first = min(over)
    where, why = blocks_place(model, target)
    return where, (f"{format_bytes(need[first])} with them in the client would exceed the memory target "
                   f"{format_bytes(target)}{why}"), first


def blocks_place(model: MemoryModel, target: int | None) -> tuple[str, str]:
    """Where node blocks go, and why when it is not the rule's first choice: on the workers of
    a cluster (``workers``), or on the scratch disk with the products in the client
    (``disk``): the embedded scheduler's, and a cluster's whose workers' share of the finest
    level's blocks, beside their smallest tasks, exceeds ``target`` while the client, with
    the products' blocks in flight, holds it."""
    if not model.separate:
        return "disk", ""
    finest = model.meshes[model.levels[-1]]
    share = blocks_bytes(finest, model.cell_of(finest)) // model.workers
    worker = model.base + model.peak(1, MIN_PREPARE_EDGE)[0] + share
    on_disk = dataclasses.replace(model, blocks_from=math.prod(finest.nodes_shape), blocks_on_disk=True)
    if target is None or worker <= target or model.base + on_disk.client > target:
        return "workers", ""
    return "disk", (f"; in files, as each worker's share, {format_bytes(worker)} with its tasks, would exceed "
                    f"the memory target")


@dataclasses.dataclass(frozen=True)
class MemoryModel:
    """The memory a run's processes hold, as a function of the block and prefilter task edges:
    the scans, meshes and settings of the run, and how many tasks run at once where."""

    f_scan: Any
    g_scan: Any
    meshes: dict
    settings: Settings
    levels: list  # coarsest first
    threads: int  # tasks at once per process
    concurrency: int  # tasks at once in all
    separate: bool  # tasks in other processes than the client's
    base: int  # bytes of a process before any data
    halo: int  # the prefilter's halo, voxels
    pyramid_task: int  # bytes of the largest pyramid task
    pyramid_tasks: int  # and how many there are
    blocks_from: int | None = None  # levels of at least this many nodes hold their mesh data in node blocks
    blocks_on_disk: bool = False  # ...on the scratch disk, their products in the client (else on the workers)

    @classmethod
    def of(cls, f_scan, g_scan, meshes: dict, settings, scheduler) -> "MemoryModel":
        threads, concurrency, separate = threads_of(scheduler)
        levels = sorted(meshes, reverse=True)
        halo = prepared_halo(settings.smoothing, settings.interpolation, int(config.get("bspline-halo")))
        pyr_task, pyr_tasks = max(pyramid_tasks(scan, levels) for scan in (f_scan, g_scan))
        return cls(f_scan, g_scan, meshes, settings, levels, threads, concurrency, separate, base_bytes(), halo,
                   pyr_task, pyr_tasks)

    @property
    def workers(self) -> int:
        """Processes the tasks run in: the client's alone, or the workers (their tasks at once
        over the threads of the largest, at least one; uneven workers count as fewer)."""
        return max(1, -(-self.concurrency // max(self.threads, 1))) if self.separate else 1

    @property
    def prepared(self) -> bool:
        """Whether ``g`` is prefiltered into scratch (cubic interpolation or a low-pass)."""
        return self.settings.interpolation == "cubic" or self.settings.smoothing > 0

    @property
    def client(self) -> int:
        """The client's data: that of the finest level."""
        return self.client_bytes(self.meshes[self.levels[-1]])

    def cell_of(self, mesh: Mesh) -> int:
        return offset_cell(self.settings.grey, mesh.element_size, self.settings.grey_cell)

    @property
    def blocks(self) -> int:
        """Bytes of the finest level's node blocks together (0: its mesh data in the client)."""
        finest = self.meshes[self.levels[-1]]
        return 0 if self.blocks_from is None else blocks_bytes(finest, self.cell_of(finest))

    def client_bytes(self, mesh: Mesh) -> int:
        nodes = math.prod(mesh.nodes_shape)
        if self.blocks_from is not None and nodes >= self.blocks_from:
            # and with the embedded scheduler, one block in flight per thread (the mesh cut in at
            # least two blocks per thread: nodeblocks.node_block_elements; imported here, as
            # nodeblocks imports dask.array, which a run in the client never loads)
            from ..solve.nodeblocks import MAX_TASK_BYTES, TASK_BYTES_PER_NODE

            # (the products' threads in the client when the blocks are on disk with a cluster)
            threads = threads_of(None)[0] if self.separate else self.threads
            in_flight = min(threads * MAX_TASK_BYTES, TASK_BYTES_PER_NODE * nodes // 2)
            if self.separate and not self.blocks_on_disk:
                in_flight = 0
            return BLOCKED_CLIENT_BYTES_PER_NODE * nodes + in_flight
        # the mesh-sized data and the brightness cells' couplings (stored_matrix.cells_bytes)
        return CLIENT_BYTES_PER_NODE * nodes + cells_bytes(mesh.shape, self.cell_of(mesh))

    def elements(self, edge: int, mesh: Mesh) -> int:
        # as the level makes its blocks (whole brightness cells, chunkdic.passes.level.LevelPasses)
        wanted = self.settings.block_elements or max(1, edge // mesh.element_size)
        m = aligned_block_elements(wanted, self.cell_of(mesh))
        return min(m, max(mesh.shape))

    def level_disk(self, s: int, m: int) -> tuple[int, int, list]:
        """:func:`~chunkdic.engine.costs.level_disk` of level ``s`` with blocks of ``m`` elements."""
        st = self.settings
        return level_disk(self.meshes[s], self.g_scan.shape(s), m, st.smoothing, self.f_scan.dtype(s), self.prepared,
                          self.g_scan.dtype(s), st.interpolation)

    def prepare_task_bytes(self, s: int, edges) -> int:
        """The largest prefilter task of level ``s`` with tasks of ``edges`` voxels."""
        g, sigma, interp = self.g_scan, self.settings.smoothing, self.settings.interpolation
        return prepare_bytes(edges, sigma, interp, shape=g.shape(s), raw_itemsize=np.dtype(g.dtype(s)).itemsize,
                             quantized=prepared_grid(g.dtype(s), sigma, interp)[1] > 0,
                             read_bytes=read_buffer_bytes(g, s, [e + 2 * self.halo for e in edges]))

    def held(self, edge: int, prep_edge: int) -> list[tuple[int, int]]:
        """``(bytes of the tasks at once, the client's data then)`` of each kind of task with
        blocks of ``edge`` voxels: a kind runs at most ``threads`` at once, and never more
        than there are of it, beside the client's data of the level it belongs to (a coarse
        level's prefilter, whose reads decode the scratch pyramid's uint32 chunks, may hold
        more than the finest level's tasks, but beside a small mesh)."""
        sigma, interp = self.settings.smoothing, self.settings.interpolation
        held = [(self.pyramid_task * min(self.threads, self.pyramid_tasks), 0)]
        for s in self.levels:
            mesh = self.meshes[s]
            on_client = self.client_bytes(mesh)
            m = self.elements(edge, mesh)
            n_blocks = math.prod(-(-n // m) for n in mesh.shape)
            cache = chunk_cache_bytes((self.f_scan, self.g_scan), s)  # once per process, shared by its threads
            held.append((task_bytes(m * mesh.element_size, sigma, interp) * min(self.threads, n_blocks) + cache,
                         on_client))
            if self.prepared:
                box = self.level_disk(s, m)[2]
                edges = [task_edge(b, 1, prep_edge) for b in box]
                n_prep = math.prod(-(-b // e) for b, e in zip(box, edges))
                held.append((self.prepare_task_bytes(s, edges) * min(self.threads, n_prep) + cache, on_client))
        return held

    def peak(self, edge: int, prep_edge: int) -> tuple[int, int]:
        """(largest task, peak of the largest process) with blocks of ``edge`` voxels and
        prefilter tasks of ``prep_edge``: with the tasks in other processes, the client and
        a worker each hold their own; in this process, the tasks beside the client's data."""
        held = self.held(edge, prep_edge)
        task = max(t for t, _ in held)
        if self.separate:  # a worker holds its tasks and its share of the node blocks (none on disk)
            share = 0 if self.blocks_on_disk else self.blocks // self.workers
            return task, self.base + max(self.client, task + share)
        return task, self.base + max(self.client, max(t + c for t, c in held))


def fitting_edges(model: MemoryModel, target: int | None) -> tuple[int, int]:
    """The block edge and prefilter task edge: the defaults, shrunk (blocks first, by a fifth
    at a time, then the prefilter's tasks) until the peak fits ``target``. A target that even
    the smallest blocks exceed keeps the defaults: :meth:`Plan.check` refuses the run, the
    plan showing the blocks it would have used."""
    edge, prep_edge = int(config.get("block-voxels")), prepare_voxels()
    if target is None or model.peak(1, MIN_PREPARE_EDGE)[1] > target:
        return edge, prep_edge
    ell_min = min(m.element_size for m in model.meshes.values())
    while model.peak(edge, prep_edge)[1] > target and edge > ell_min and model.settings.block_elements is None:
        edge = max(ell_min, int(edge * 0.8))
        prep_edge = max(MIN_PREPARE_EDGE, min(prep_edge, edge + 32))
    while model.peak(edge, prep_edge)[1] > target and prep_edge > MIN_PREPARE_EDGE:
        prep_edge = max(MIN_PREPARE_EDGE, prep_edge - 16)
    return edge, prep_edge

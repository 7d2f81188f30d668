"""The passes over one pyramid level out of core: the method's protocol on block tasks over Zarr stores.

A :class:`LevelPasses` implements :class:`chunkdic.method.protocol.Passes` for one level:
each pass maps one task per block of whole elements (:mod:`chunkdic.passes.tasks`; in
Z-order), each task reads its own block of ``f`` and the window of ``g`` it needs and
returns mesh-sized partials, which the client adds up into the value the pass returns
(shared/DESIGN.md, "Out-of-core shape"). It owns the level's scratch stores, the haloed
copy of ``f`` that the ``M`` pass writes for the ``b`` passes and the prepared ``g`` of
:meth:`LevelPasses.prepare`, and deletes them in :meth:`LevelPasses.release`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np

from .. import config
from ..errors import InputError
from ..io.chunkread import forget_chunks, z_order_key
from ..io.handles import ArrayRef, forget_open_arrays
from ..io.owntree import remove
from ..kernels.blocks import LAGS
from ..mesh import Mesh
from ..method.brightness import aligned_block_elements, offset_cell
from ..method.events import Blocks, FCopy, Matrix, Prepared, emit
from ..method.operator import Assembled, Operator, build_operator
from ..method.protocol import Pass, stack_rows
from ..method.settings import Settings
from ..scheduler import pin_mmap_threshold, release_freed_memory
from ..solve.cg import StencilSolver
from .crack_cut import CrackLabels
from .haloed import HaloedBlocks
from .masks import MIN_MATERIAL, active_elements
from .mesh_blocks import BlockedMatrix, holder_for, in_blocks
from .parked import Parked
from .prefilter import adopt_prepared, build_prepared, face_margin, reachable_box, record_path
from .reduction import PassSums
from .scratchstore import f_store, g_store
from .stored_matrix import StoredMatrix, field_hash
from .tasks import BlockJob, LevelInputs, b_task, f_copy_task, m_task
from .translation import translation_task

log = logging.getLogger(__name__)

#: interval of block-count progress events during a long pass over the voxels (seconds)
PROGRESS_SECONDS = 5.0
#: least interval between two :func:`release_freed_memory` calls of a pass (seconds)
TRIM_SECONDS = 0.1
#: a diagnostic gap (:meth:`LevelPasses.gap`) is measured on one element in 8 when the mesh has
#: at least this many elements (the sample then holds 512 or more), and on one in 64, 512, …
#: while the sample keeps this many (large meshes: 1024³ at ℓ = 16 samples one in 64)
GAP_SAMPLE_MIN = 4096


def gap_stride(shape) -> int:
    """Element stride of the regular sample a diagnostic gap is measured on (:data:`GAP_SAMPLE_MIN`).

    >>> gap_stride((25, 25, 25)), gap_stride((32, 32, 32)), gap_stride((64, 64, 64)), gap_stride((128,) * 3)
    (2, 2, 4, 8)
    >>> gap_stride((15, 15, 15))
    1
    """
    if int(np.prod(shape)) < GAP_SAMPLE_MIN:
        return 1
    stride = 2
    while int(np.prod([-(-int(n) // (2 * stride)) for n in shape])) >= GAP_SAMPLE_MIN:
        stride *= 2
    return stride


def gap_sample(shape, active: np.ndarray | None) -> np.ndarray | None:
    """The elements a diagnostic gap is measured on (uint8, the element ``shape``), or None
    for every ``active`` element: every element in :func:`gap_stride` along each axis."""
    stride = gap_stride(shape)
    if stride == 1:
        return None
    sample = np.zeros(shape, np.uint8)
    sample[::stride, ::stride, ::stride] = 1
    if active is not None:
        sample &= active.astype(np.uint8)
    return sample if sample.any() else None


class LevelPasses:
    """The passes over one pyramid level, block by block (:class:`chunkdic.method.protocol.Passes`).

    Parameters
    ----------
    s : int
        Pyramid level.
    mesh : Mesh
        The level's mesh.
    f_ref, g_ref : ArrayRef
        Reference and deformed scans at this level.
    runner
        Where tasks run (:func:`chunkdic.scheduler.open_runner`).
    settings : Settings
    scratch : Path
        The run's scratch directory (shared with the workers).
    progress : callable, optional
        Receives the passes' events (:func:`chunkdic.method.events.emit`).
    mask : ArrayRef, optional
        The specimen mask at this level.
    matrix : StoredMatrix, optional
        Where ``M`` is kept for a resumed run (the output); None: not kept.
    adopt : bool
        The scratch is an interrupted run's: its complete stores of this level are reused.
    crack : ArrayRef, optional
        A known crack surface at this level (non-zero voxels; :mod:`chunkdic.passes.crack_cut`).
    """

    def __init__(self, s: int, mesh: Mesh, f_ref: ArrayRef, g_ref: ArrayRef, runner, settings: Settings,
                 scratch: Path, progress=None, mask: ArrayRef | None = None, *, matrix: StoredMatrix | None = None,
                 adopt: bool = False, crack: ArrayRef | None = None):
        self.level, self.mesh, self.runner, self.settings = s, mesh, runner, settings
        self.scratch, self.progress, self.matrix = Path(scratch), progress, matrix
        self.cell = cell = offset_cell(settings.grey, mesh.element_size, settings.grey_cell)
        self.block_elements = aligned_block_elements(
            settings.block_elements or max(1, config.get("block-voxels") // mesh.element_size), cell)
        # in Z-order: neighbouring blocks, whose low-pass halos share the scan's chunks, run
        # close in time and find those chunks decoded (io.chunkread.chunk_cache)
        self.jobs = sorted(BlockJob.for_mesh(mesh, self.block_elements), key=lambda job: z_order_key(job.index))
        margin = face_margin(settings.smoothing)
        if min(g_ref.shape) <= 2 * margin + 1:
            raise InputError(f"the deformed scan is too small at level {s} ({g_ref.shape}) for a low-pass of "
                             f"{settings.smoothing} voxels: choose a finer coarsest level or less smoothing")
        # the haloed f store, and whether it holds every block (adopted complete, or once a pass wrote it)
        f_copy, self.f_ready = self._f_copy(f_ref, settings.smoothing, adopt)
        self.f_adopted = self.f_ready
        #: what every task reads, but the centring of an operator and the prepared g (task_inputs)
        self.inputs = LevelInputs.for_settings(f_ref, g_ref, f_copy, level=s,
                                               interpolation=settings.interpolation, smoothing=settings.smoothing,
                                               grey=settings.grey, mask=mask, grey_cell=cell,
                                               crack=None if crack is None else CrackLabels(crack, mesh.origin,
                                                                                            mesh.shape, margin))
        #: the prepared g and how many were built (each a store of its own): prepare(), release()
        self.prepared, self.builds = None, 0
        #: where the level's mesh data live when they go to node blocks (mesh_blocks.in_blocks), else None
        self.holder = holder_for(runner, self.scratch / f"mesh{s}") if in_blocks(mesh) else None
        if self.holder is not None:  # the client's memory: the mesh data it holds, not freed buffers' heaps
            pin_mmap_threshold()
        if adopt and self.inputs.g_needs_preparing:
            self._adopt_prepared()

    def task_inputs(self, op: Operator | None = None) -> LevelInputs:
        """What the tasks of a pass read: the level's inputs with the prepared ``g`` and the
        centring of ``op``'s brightness sums."""
        return dataclasses.replace(self.inputs, prepared=self.prepared,
                                   center=self.inputs.center if op is None else op.center)

    def _map(self, fn, args, label: str, voxels: int | None = None, total: int | None = None):
        """Run one task per argument tuple, yield results as they come, report long passes.

        A pass that lasts more than ``PROGRESS_SECONDS`` emits ``stage="blocks"`` events
        (done/total, voxel rate, ETA) at that interval, for a person at a terminal.
        ``voxels``: what the tasks cover together (default: the mesh's ROI). ``total``: the
        number of tasks when ``args`` is a generator (default ``len(args)``).
        """
        total = len(args) if total is None else total
        voxels_per_block = (self.mesh.n_voxels if voxels is None else voxels) / max(total, 1)
        t0 = last = trimmed = time.perf_counter()
        for done, result in enumerate(self.runner.map_unordered(fn, args), start=1):
            yield result
            now = time.perf_counter()
            if now - trimmed >= TRIM_SECONDS:  # freed task buffers back to the system
                release_freed_memory()
                trimmed = now
            if now - last >= PROGRESS_SECONDS and done < total:
                last = now
                rate = done * voxels_per_block / (now - t0)
                emit(self.progress, Blocks(level=self.level, label=label, done=done, total=total, rate=rate, eta=(total - done) * voxels_per_block / rate))

    def _f_copy(self, f_ref: ArrayRef, sigma: float, adopt: bool) -> tuple[HaloedBlocks, bool]:
        """The store of the blocks' haloed ``f`` (see :mod:`chunkdic.passes.haloed`): with
        ``adopt``, the complete copy an interrupted run of the same run left in the adopted
        scratch (then ``True``), else an empty store.

        Low-passed blocks are float32; without the low-pass the scan's own dtype (1-2
        bytes per voxel for most scans) keeps the scratch small.
        """
        grid = tuple(max(job.index[a] for job in self.jobs) + 1 for a in range(3))
        regions = [job.haloed_region(f_ref.shape)[0] for job in self.jobs]
        chunk = tuple(max(r[a].stop - r[a].start for r in regions) for a in range(3))
        dtype = "float32" if sigma > 0 else f_ref.dtype
        path = f_store(self.scratch, self.level)
        if adopt:
            found = HaloedBlocks.adopt(path, grid, chunk, dtype, quantize_from=f_ref.dtype)
            if found is not None:
                return found, True
        return HaloedBlocks.create(path, grid, chunk, dtype, quantize_from=f_ref.dtype), False

    def _adopt_prepared(self) -> None:
        """Take the prepared ``g`` an interrupted run completed in the adopted scratch
        (:func:`chunkdic.passes.prefilter.adopt_prepared`), when there is one."""
        found = adopt_prepared(self.scratch, self.level, self.inputs.g_grid, local=self.runner.local)
        if found is not None:
            self.prepared, self.builds = found
            log.info("level %d: g prepared by the interrupted run over %s reused", self.level, self.prepared.box)

    def matrix_key(self, u: np.ndarray) -> dict:
        """What ``M`` depends on beyond the run's fingerprint: the level, its mesh and blocks,
        the 16-bit grid of the haloed ``f`` and the field ``u`` it is built at."""
        mesh, f_copy = self.mesh, self.inputs.f_copy
        return {"level": self.level, "nodes": list(mesh.nodes_shape), "roi": [[r.start, r.stop] for r in mesh.roi],
                "element_size": mesh.element_size, "blocks": self.block_elements,
                "brightness_cell": self.cell,
                "f_grid": [f_copy.offset, f_copy.step, f_copy.dtype], "field": field_hash(u)}

    def assemble_m(self, u: np.ndarray) -> Operator:
        """``M`` for the field ``u`` (3, nz, ny, nx), voxels of the level, as an
        :class:`~chunkdic.method.operator.Operator`: summed by a pass over the voxels
        (:meth:`_m_pass`), or read from the output where an interrupted run of the same run
        kept it (:mod:`chunkdic.passes.stored_matrix`); a pass that built it keeps it there."""
        t0, c0 = time.perf_counter(), time.process_time()
        # M in node blocks, or with a crack (the stored M keeps no second copies' couplings), is
        # not kept in the output: a resumed run sums it again
        key = (None if self.matrix is None or self.holder is not None or self.inputs.crack is not None
               else self.matrix_key(u))
        m = None if key is None else self.matrix.load(key)
        reused = m is not None
        if m is None:
            m = self._m_pass(u)
        # M read and the haloed f not adopted: the first b pass writes it (_f_copy_pass), not
        # here (a finished level resumed for its uncertainty runs none)
        self._check(m)
        if key is not None and not reused:
            # for a run that resumes this level after a kill; before the solver, which holds
            # the weak nodes' blocks in place (StencilSolver): M is kept as the pass summed it
            self.matrix.save(key, m)
        try:
            op = build_operator(m, u, cell=self.cell, reused=reused,
                                make_solver=StencilSolver if self.holder is None else self._blocked.solver)
        except InputError as exc:  # M is empty: name the cause when it is not the reference itself
            raise InputError(self._why_no_gradient(u, m.active) or str(exc)) from None
        emit(self.progress, Matrix(level=self.level, nodes=list(self.mesh.nodes_shape), blocks=len(self.jobs), voxels=self.mesh.n_voxels, seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0, reused=reused, f_adopted=self.f_adopted))
        return op

    def _check(self, m: Assembled) -> None:
        """Refuse an ``M`` with nothing to correlate: a mask without material, a constant reference."""
        if m.active is not None and not m.active.any():
            raise InputError(f"the mask has no element with material in the ROI at level {self.level} "
                             f"(at least {MIN_MATERIAL:.0%} of an element must be material)")
        if not float(m.fmax - m.fmin) > 0:
            raise InputError(f"the reference is constant over the ROI at level {self.level}: nothing to correlate")

    def _m_pass(self, u: np.ndarray) -> Assembled:
        """The ``M`` pass for the field ``u``: every block's stencil summed, the haloed ``f`` written."""
        mesh = self.mesh
        # float32 and only the symmetric half (solve.HALF_OFFSETS): M only steers the
        # modified Gauss-Newton steps (the converged field solves b = λ R a whatever M),
        # and at 128³ nodes a full float64 stencil alone would be 4 GB. Each block's
        # partial is summed in float64 by its task.
        blocked = self._blocked = (None if self.holder is None else
                                   BlockedMatrix(mesh, self.block_elements, self.cell, self.holder,
                                                 self.scratch / f"mesh{self.level}" / "partials"))
        S = np.zeros(mesh.nodes_shape + (14, 3, 3), dtype=np.float32) if blocked is None else None
        fmin, fmax = np.inf, -np.inf
        # a generator: each block's slice of u is made as its task is submitted (the embedded
        # runner holds a window of them, not a pass's worth)
        inputs = self.task_inputs()
        args = ((inputs, job, _nodes_of(u, job)) for job in self.jobs)
        lags = np.zeros((3, LAGS + 1))
        fractions = np.zeros(mesh.shape) if inputs.mask is not None else None
        k = self.cell
        cells = (np.zeros(tuple(-(-n // k) for n in mesh.shape) + (k + 1,) * 3 + (3, 4), np.float32)
                 if k > 1 and blocked is None else None)  # the mesh's cells' couplings (kernels.m.cell_couplings)
        inputs.f_copy.unmark()  # rewritten (a start chosen later builds M again): complete once every block is
        pairs, released = {}, []
        for blk, part, lo, hi, block_lags, frac, block_cells, block_crack in self._map(m_task, args, "M pass",
                                                                                       total=len(self.jobs)):
            if blocked is not None:
                blocked.add(blk, part, block_cells)
            else:
                S[blk.node_slices] += part[..., 13:, :, :]
            if block_crack is not None:
                for key, value in block_crack[0].items():
                    pairs[key] = pairs.get(key, 0.0) + value
                released.append(block_crack[1])
            if cells is not None:  # blocks hold whole cells from a cell's first element
                first = [e0 // k for e0, _ in blk.elements]
                cells[tuple(slice(c, c + n) for c, n in zip(first, block_cells.shape[:3]))] = block_cells
            fmin, fmax = min(fmin, lo), max(fmax, hi)
            lags += block_lags
            if fractions is not None:
                fractions[tuple(slice(e0, e1) for e0, e1 in blk.elements)] = frac
        inputs.f_copy.mark_complete()
        self.f_ready = True  # written whole by this pass
        self.runner.run_everywhere(forget_chunks)  # the b passes read the haloed copy, not the scan
        active = None if fractions is None else active_elements(fractions)
        if blocked is not None:
            S, cells = blocked.stencil(), blocked.cells()
            blocked.close()
        crack = (pairs, np.concatenate(released)) if released else None
        return Assembled(S, lags, active, float(fmin), float(fmax), cells, crack)

    def _f_copy_pass(self) -> None:
        """Write the haloed ``f`` alone (``M`` read from the output, the interrupted run's copy
        not adopted): the ``M`` pass's reads and low-pass without its sums
        (:func:`chunkdic.passes.tasks.f_copy_task`); before the first ``b`` pass."""
        t0 = time.perf_counter()
        inputs = self.task_inputs()
        inputs.f_copy.unmark()
        for _ in self._map(f_copy_task, [(inputs, job) for job in self.jobs], "low-pass of f"):
            pass
        inputs.f_copy.mark_complete()
        self.f_ready = True
        self.runner.run_everywhere(forget_chunks)
        emit(self.progress, FCopy(level=self.level, blocks=len(self.jobs), seconds=time.perf_counter() - t0))

    def _why_no_gradient(self, u: np.ndarray, active: np.ndarray | None) -> str | None:
        """The real cause of an empty ``M`` when it is not the reference's texture.

        ``M`` sums only voxels that the start field maps inside ``g`` and that a mask keeps,
        so "the reference has no gradient" misled when the start field (``--init``, or the
        field carried from the coarser level) moved the ROI out of the deformed scan, or when
        the mask kept only untextured voxels. Both are told from mesh-sized data: the start
        field at the element centres, the mask's element activity. None: the reference.
        """
        mesh = self.mesh
        centres = mesh.element_axes()
        moved = np.stack(np.meshgrid(*centres, indexing="ij")) + mesh.evaluate_grid(u, centres)
        upper = np.asarray(self.inputs.g.shape, dtype=float).reshape(3, 1, 1, 1) - 1.0
        outside = np.any((moved < 0) | (moved > upper), axis=0)
        if outside.mean() >= 0.5:
            shift = ", ".join(f"{float(c.mean()):+.1f}" for c in u)
            return (f"the start field of level {self.level} maps {outside.mean():.0%} of the ROI's elements outside "
                    f"the deformed scan (mean displacement {shift} voxels of the level): nothing left to correlate; "
                    "check --init (a result of another pair or level?) or the ROI")
        if active is not None:
            return (f"the mask keeps no textured voxel of the ROI at level {self.level} ({int(active.sum())} of "
                    f"{active.size} elements kept, most without a gradient): the textured material lies outside "
                    "the mask; check the mask (inverted? of another scan?)")
        return None

    def covers(self, u: np.ndarray) -> bool:
        """Whether ``u`` (3, nz, ny, nx) reads only the part of ``g`` already prepared (no prefilter pass)."""
        if not self.inputs.g_needs_preparing:
            return True
        needed = reachable_box(self.mesh, u, self.inputs.g.shape, margin=0)
        return needed is None or (self.prepared is not None
                                  and self.prepared.covers(tuple(slice(a, b) for a, b in needed)))

    def prepare(self, u: np.ndarray) -> None:
        """Prepare once the part of ``g`` that ``u`` (± a margin) can reach (low-pass, B-spline)
        into a scratch store the ``b`` passes read, unless :meth:`covers` says it is done."""
        if self.covers(u):
            return
        g_ref = self.inputs.g
        box = reachable_box(self.mesh, u, g_ref.shape, margin=max(8, self.mesh.element_size))
        self._release_prepared()
        self.builds += 1
        t0 = time.perf_counter()
        voxels = int(np.prod([b - a for a, b in box]))
        inp = self.inputs
        self.prepared = build_prepared(
            g_ref, box, g_store(self.scratch, self.level, self.builds),
            lambda fn, args: self._map(fn, args, "prefilter of g", voxels),
            halo=inp.g_halo, local=self.runner.local, sigma=inp.sigma, interpolation=inp.interpolation,
        )
        self.runner.run_everywhere(forget_chunks)  # the b passes read the prepared store, not the scan
        emit(self.progress, Prepared(level=self.level, box=[list(b) for b in box], voxels=voxels, seconds=time.perf_counter() - t0))

    def _release_prepared(self) -> None:
        if self.prepared is not None:
            path = Path(self.prepared.ref.path)
            self.prepared = None
            self._delete([record_path(path), path])

    def release(self) -> None:
        """Delete this level's scratch data (prepared ``g``, haloed ``f``) and open handles on them."""
        paths = [Path(self.inputs.f_copy.path)]
        if self.holder is not None:
            self.holder.close()
        if self.prepared is not None:
            paths += [record_path(self.prepared.ref.path), Path(self.prepared.ref.path)]
        self._delete(paths)

    def _delete(self, paths: list[Path]) -> None:
        self.runner.run_everywhere(forget_open_arrays)
        for path in paths:
            remove(path)

    def translation(self) -> np.ndarray:
        """The phase-correlation translation over the ROI, as one task (:mod:`chunkdic.passes.translation`)."""
        return next(iter(self.runner.map_unordered(translation_task, [(self.inputs.f, self.inputs.g,
                                                                       self.mesh.roi)])))

    def gap(self, u: np.ndarray, op: Operator) -> float:
        """The matching gap of the nodal field ``u`` (3, nz, ny, nx) alone: a diagnostic
        (the gaps that choose the start), not a step of the iterations.

        On a mesh of at least :data:`GAP_SAMPLE_MIN` elements it is measured on a regular
        sample of elements (:func:`gap_stride`: one in 8, even indices along every axis, or
        one in 64, 512 on meshes large enough that the sample keeps that many; rows of voxels
        with no sampled element are skipped): a pass at an eighth of the cost or less. The
        gap is a root mean square over elements, so the sample estimates it closely
        (measured on the 300³ CT pair, ℓ = 12 and 8: within 0.9 % of the full pass; on the
        1024³ band pair, ℓ = 16, one in 64 against one in 8: docs/engine.md, "The start").
        :meth:`assemble_b` measures the same gaps with its ``probes`` inside a
        pass of the iterations (the finest level's reported gaps: no pass of their own).
        """
        return self.assemble_b(u, op, sample=gap_sample(self.mesh.shape, op.active)).gap

    def park(self, array):
        """``array`` itself (rows stacked, :func:`~chunkdic.method.protocol.stack_rows`), or with
        the level's mesh data in node blocks a :class:`~chunkdic.passes.parked.Parked` copy of it
        in a file under the scratch (``parked<level>/``), read back by ``np.asarray``."""
        if self.holder is None:
            return stack_rows(array)
        if isinstance(array, Parked):  # parked already (a pass the iterations start from again)
            return array
        return Parked(array, self.scratch / f"parked{self.level}")

    def assemble_b(self, u: np.ndarray, op: Operator, *, sample: np.ndarray | None = None,
                   probes: dict[str, np.ndarray] | None = None, other: np.ndarray | None = None) -> Pass:
        """One pass for the nodal field ``u``: ``b``, brightness, gap and voxel counts.

        ``sample`` (uint8, the mesh's element shape): only its non-zero elements take part
        (:meth:`gap`); default: every active element. ``probes``: named nodal fields (each
        (3, nz, ny, nx), voxels of the level) whose gap alone is measured in the same tasks,
        as :meth:`gap` measures it (its sample of elements), from the blocks' reads of this
        pass: ``Pass.probe_gaps`` maps each name to its gap (the brightness is fitted to
        every probe as to ``u``). Their cost is the sums alone: one element in 8 on large
        meshes, an eighth of a pass's arithmetic each and no reads. ``other``: the second
        copies (K, 3) of ``op.crack``'s split nodes (None: ``u`` there).
        """
        t0 = time.perf_counter()
        if not self.f_ready:
            self._f_copy_pass()
        active = op.active if sample is None else sample
        names = list(probes or {})
        probe_active = gap_sample(self.mesh.shape, op.active) if names else None
        if probe_active is None:
            probe_active = op.active
        inputs = self.task_inputs(op)
        whole_other = None if op.crack is None else op.crack.other_field(u, other)

        def args_of(job):
            fields = tuple(_nodes_of(probes[name], job) for name in names)
            return (inputs, job, _nodes_of(u, job), _active_of(active, job), fields, _active_of(probe_active, job),
                    None if whole_other is None else _nodes_of(whole_other, job))

        sums = PassSums(self.mesh, len(names), op.crack)
        for blk, part, probe_parts, other_part in self._map(b_task, (args_of(job) for job in self.jobs), "b pass",
                                                            total=len(self.jobs)):
            sums.add(blk, part, probe_parts, other_part)
        part = None
        return sums.result(self.settings.grey, op, names, t0)


def _active_of(active: np.ndarray | None, job: BlockJob) -> np.ndarray | None:
    """A block's slice of an element activity (None: every element)."""
    if active is None:
        return None
    return np.ascontiguousarray(active[tuple(slice(e0, e1) for e0, e1 in job.block.elements)])


def _nodes_of(u: np.ndarray, job: BlockJob) -> np.ndarray:
    """A block's own slice of the nodal field: what its task receives (kilobytes)."""
    return np.ascontiguousarray(u[(slice(None), *job.block.node_slices)])

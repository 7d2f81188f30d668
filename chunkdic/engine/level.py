"""One pyramid level of a correlation: its blocks, ``M``, prepared ``g`` and ``b`` passes.

A :class:`Level` lives from the ``M`` pass to the end of the level's Gauss–Newton
iterations. It owns the level's scratch data (the haloed copy of ``f``, the B-spline
coefficients of ``g``) and deletes them in :meth:`Level.release`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import warnings
from pathlib import Path

import numpy as np

from .. import config
from ..errors import InputError
from ..io.chunkread import forget_chunks, z_order_key
from ..io.handles import ArrayRef, forget_open_arrays
from ..io.owntree import remove
from ..kernels.blocks import LAGS
from ..mesh import Mesh
from ..solve.cg import PoorTextureWarning, StencilSolver
from ..solve.regularization import Regularizer, plane_wave_unit
from ..solve.stencil import rigid_restriction, stencil_matvec
from .budget import TRIM_SECONDS, release_freed_memory
from .events import emit
from .greylevel import Fit, aligned_block_elements, element_fit, misfit, nodal_rhs, offset_cell
from .haloed import HaloedBlocks
from .masks import MIN_MATERIAL, active_elements
from .noise import correlation_factor
from .prefilter import adopt_prepared, build_prepared, face_margin, reachable_box, record_path
from .settings import Settings
from .stored_matrix import Assembled, StoredMatrix, field_hash
from .tasks import BlockJob, LevelInputs, b_task, f_copy_task, m_task

log = logging.getLogger(__name__)

#: interval of block-count progress events during a long pass over the voxels (seconds)
PROGRESS_SECONDS = 5.0
#: a diagnostic gap (:meth:`Level.gap`) is measured on one element in 8 when the mesh has
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


def prune_adopted(scratch: Path, level: int | None) -> None:
    """Remove from an adopted scratch directory (:func:`chunkdic.io.scratch.adopt_scratch`) the
    level stores no level of this run will adopt: those of levels coarser than ``level`` (the
    level of the interrupted run's checkpoint, done or under way; None: keep every level's),
    a prepared ``g`` left without its completion record or superseded by a later build, and
    the mask's levels (prepared again: :func:`chunkdic.engine.masks.prepare_mask` writes a new
    group)."""
    scratch = Path(scratch)
    latest: dict[int, int] = {}
    for rec in scratch.glob("g-level*-*.prepared.json"):
        name = rec.name[len("g-level"):].split(".")[0]
        try:
            s, k = (int(v) for v in name.split("-"))
        except ValueError:
            continue
        latest[s] = max(latest.get(s, -1), k)
    doomed = [scratch / "mask"]
    for entry in scratch.iterdir():
        name = entry.name
        if not (name.startswith("f-level") or name.startswith("g-level")):
            continue
        try:
            if name.startswith("f-level"):
                s, k = int(name[len("f-level"):].split(".")[0]), None
            else:
                s, k = (int(v) for v in name[len("g-level"):].split(".")[0].split("-"))
        except ValueError:
            doomed.append(entry)
            continue
        if (level is not None and s > level) or (k is not None and k != latest.get(s)):
            doomed.append(entry)
    for path in doomed:
        remove(path)


@dataclasses.dataclass
class Pass:
    """One ``b`` pass over a level for a nodal field.

    Attributes
    ----------
    fit : Fit
        ``b``, ``Σ r²`` and the brightness found (:mod:`chunkdic.engine.greylevel`).
    gap : float
        Matching gap ``rms(r) / (max f - min f)`` over the valid voxels (paper section 5.1).
    n_valid, n_excluded : int
        Voxels used, and voxels whose ``X + u(X)`` left ``g``.
    kappa : float
        How much more misfit a fitted unknown absorbs than with white noise
        (:func:`chunkdic.engine.noise.correlation_factor`).
    probe_gaps : dict
        The gaps of the further fields the pass measured (:meth:`Level.assemble_b`'s ``probes``).
    seconds : float
        Wall time of the pass.
    reported : bool
        An iteration's progress event has shown it (its time is not counted twice).
    """

    fit: Fit
    gap: float
    n_valid: int
    n_excluded: int
    kappa: float = 1.0
    probe_gaps: dict = dataclasses.field(default_factory=dict)
    seconds: float = 0.0
    reported: bool = False

    @property
    def noise_variance(self) -> float:
        """``σ_r²``: the mean squared residual (grey levels²)."""
        return self.fit.ssr / self.fit.weight if self.fit.weight > 0 else float("nan")

    @property
    def b(self) -> np.ndarray:
        return self.fit.b

    @property
    def excluded_fraction(self) -> float:
        total = self.n_valid + self.n_excluded
        return self.n_excluded / total if total else 1.0


class Level:
    """State of one pyramid level: its mesh, data, assembled ``M`` and solver.

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
        Receives events (dicts), see :func:`chunkdic.engine.events.emit`.
    mask : ArrayRef, optional
        The specimen mask at this level.
    start : ndarray, shape (3, nz, ny, nx), float64, keyword-only
        The level's starting field, voxels of the level: the ``M`` pass (run on
        construction) reads the window of ``g`` it reaches.
    """

    def __init__(self, s: int, mesh: Mesh, f_ref: ArrayRef, g_ref: ArrayRef, runner, settings: Settings,
                 scratch: Path, progress=None, mask: ArrayRef | None = None, *, start: np.ndarray,
                 start_to_choose: bool = False, matrix: StoredMatrix | None = None, adopt: bool = False):
        self.s, self.mesh, self.runner, self.settings = s, mesh, runner, settings
        self.scratch = scratch
        self.progress = progress
        self._builds = 0
        self._deferred = None  # a field whose g is prepared by the first pass (prepare_interpolation)
        self.matrix = matrix  # where M is kept for a resumed run (the output), None: not kept
        self.m_reused = False  # M read from the output, not built by a pass (the last _assemble_m)
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
        f_copy, self.f_copy_ready = self._f_copy(f_ref, settings.smoothing, adopt)
        self.inputs = LevelInputs.for_settings(f_ref, g_ref, f_copy, level=s,
                                               interpolation=settings.interpolation, smoothing=settings.smoothing,
                                               grey=settings.grey, mask=mask, grey_cell=cell)
        self.g_adopted = adopt and self._adopt_prepared()
        self.regularization_length = math.nan
        self.regularization_weight = 0.0
        self._unit_weight = (None, None, 0.0)  # (solver, kind, λ of a unit length): regularize
        # the operator is assembled here, so that no method can run before it exists
        # a start still to choose (steps.best_start): the weak-node warning waits for the M it is built with
        self.start_to_choose = start_to_choose
        self.m_start = start  # the field M is built at (a checkpoint keeps it: a resumed level rebuilds this M)
        self._first_pass = None  # (field, pass) summed ahead of the iterations (keep_first_pass)
        self._assemble_m(start)

    @property
    def blocks(self) -> list:
        return [job.block for job in self.jobs]

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
            if now - trimmed >= TRIM_SECONDS:  # freed task buffers back to the system (budget.py)
                release_freed_memory()
                trimmed = now
            if now - last >= PROGRESS_SECONDS and done < total:
                last = now
                rate = done * voxels_per_block / (now - t0)
                emit(self.progress, stage="blocks", level=self.s, label=label, done=done, total=total,
                     rate=rate, eta=(total - done) * voxels_per_block / rate)

    def _f_copy(self, f_ref: ArrayRef, sigma: float, adopt: bool) -> tuple[HaloedBlocks, bool]:
        """The store of the blocks' haloed ``f`` (see :mod:`chunkdic.engine.haloed`): with
        ``adopt``, the complete copy an interrupted run of the same run left in the adopted
        scratch (then ``True``), else an empty store.

        Low-passed blocks are float32; without the low-pass the scan's own dtype (1-2
        bytes per voxel for most scans) keeps the scratch small.
        """
        grid = tuple(max(job.index[a] for job in self.jobs) + 1 for a in range(3))
        regions = [job.haloed_region(f_ref.shape)[0] for job in self.jobs]
        chunk = tuple(max(r[a].stop - r[a].start for r in regions) for a in range(3))
        dtype = "float32" if sigma > 0 else f_ref.dtype
        path = self.scratch / f"f-level{self.s}.zarr"
        if adopt:
            found = HaloedBlocks.adopt(path, grid, chunk, dtype, quantize_from=f_ref.dtype)
            if found is not None:
                return found, True
        return HaloedBlocks.create(path, grid, chunk, dtype, quantize_from=f_ref.dtype), False

    def _adopt_prepared(self) -> bool:
        """Take the prepared ``g`` an interrupted run completed in the adopted scratch
        (:func:`chunkdic.engine.prefilter.adopt_prepared`): whether there was one."""
        if not self.inputs.g_needs_preparing:
            return False
        found = adopt_prepared(self.scratch, self.s, self.inputs.g_grid, local=self.runner.local)
        if found is None:
            return False
        prepared, self._builds = found
        self.inputs = dataclasses.replace(self.inputs, prepared=prepared)
        log.info("level %d: g prepared by the interrupted run over %s reused", self.s, prepared.box)
        return True

    def matrix_key(self, u: np.ndarray) -> dict:
        """What ``M`` depends on beyond the run's fingerprint: the level, its mesh and blocks,
        the 16-bit grid of the haloed ``f`` and the field ``u`` it is built at."""
        mesh, f_copy = self.mesh, self.inputs.f_copy
        return {"level": self.s, "nodes": list(mesh.nodes_shape), "roi": [[r.start, r.stop] for r in mesh.roi],
                "element_size": mesh.element_size, "blocks": self.block_elements,
                "brightness_cell": self.cell,
                "f_grid": [f_copy.offset, f_copy.step, f_copy.dtype], "field": field_hash(u)}

    def _assemble_m(self, u: np.ndarray) -> None:
        """``M`` for the level's starting field ``u``: the stencil, its rigid restriction, the
        solver, the element activity of a mask and the reference's dynamic range.

        Built by a pass over the voxels (:meth:`_m_pass`), or read from the output where an
        interrupted run of the same run kept it (:mod:`chunkdic.engine.stored_matrix`); a pass
        that built it keeps it there."""
        key = None if self.matrix is None else self.matrix_key(u)
        m = None if key is None else self.matrix.load(key)
        self.m_reused = m is not None
        if m is None:
            m = self._m_pass(u)
        # M read and the haloed f not adopted: the first b pass writes it (_f_copy_pass), not
        # here (a finished level resumed for its uncertainty runs none)
        self.sensitivity_lags = m.lags
        self.active = m.active  # element activity of a specimen mask (None: every element)
        if self.active is not None and not self.active.any():
            raise InputError(f"the mask has no element with material in the ROI at level {self.s} "
                             f"(at least {MIN_MATERIAL:.0%} of an element must be material)")
        self.dynamic_range = float(m.fmax - m.fmin)
        if not self.dynamic_range > 0:
            raise InputError(f"the reference is constant over the ROI at level {self.s}: nothing to correlate")
        self.inputs = dataclasses.replace(self.inputs, center=0.5 * float(m.fmin + m.fmax))
        if key is not None and not self.m_reused:
            # for a run that resumes this level after a kill; before the solver, which holds
            # the weak nodes' blocks in place (StencilSolver): M is kept as the pass summed it
            self.matrix.save(key, m)
        S, cells, m = m.stencil, m.cells, None
        # Rigid-body restriction of M: since Σ_a N_a = 1, Σ_voxels ∇f ∇fᵀ = Σ_ij M_ij (minus
        # the brightness cells' share: a cell's W summed over its nodes)
        self.rigid_matrix = rigid_restriction(S)
        if cells is not None:
            rigid = cells.sum(axis=(3, 4, 5), dtype=np.float64).reshape(-1, 3, 4)
            self.rigid_matrix = self.rigid_matrix - np.einsum("cip,cjp->ij", rigid, rigid)
        try:
            self.solver = StencilSolver(S, cells=cells, cell=self.cell)
        except InputError as exc:  # M is empty: name the cause when it is not the reference itself
            raise InputError(self._why_no_gradient(u) or str(exc)) from None
        if not self.start_to_choose:
            self._warn_weak_nodes()

    def _m_pass(self, u: np.ndarray) -> Assembled:
        """The ``M`` pass for the field ``u``: every block's stencil summed, the haloed ``f`` written."""
        mesh = self.mesh
        # float32 and only the symmetric half (solve.HALF_OFFSETS): M only steers the
        # modified Gauss-Newton steps (the converged field solves b = λ R a whatever M),
        # and at 128³ nodes a full float64 stencil alone would be 4 GB. Each block's
        # partial is summed in float64 by its task.
        S = np.zeros(mesh.nodes_shape + (14, 3, 3), dtype=np.float32)
        fmin, fmax = np.inf, -np.inf
        # a generator: each block's slice of u is made as its task is submitted (the embedded
        # runner holds a window of them, not a pass's worth)
        inputs = self.inputs
        args = ((inputs, job, self._nodes_of(u, job)) for job in self.jobs)
        lags = np.zeros((3, LAGS + 1))
        fractions = np.zeros(mesh.shape) if self.inputs.mask is not None else None
        k = self.cell
        cells = (np.zeros(tuple(-(-n // k) for n in mesh.shape) + (k + 1,) * 3 + (3, 4), np.float32)
                 if k > 1 else None)  # the mesh's cells' couplings (kernels.m.cell_couplings)
        inputs.f_copy.unmark()  # rewritten (a start chosen later builds M again): complete once every block is
        for blk, part, lo, hi, block_lags, frac, block_cells in self._map(m_task, args, "M pass",
                                                                          total=len(self.jobs)):
            S[blk.node_slices] += part[..., 13:, :, :]
            if cells is not None:  # blocks hold whole cells from a cell's first element
                first = [e0 // k for e0, _ in blk.elements]
                cells[tuple(slice(c, c + n) for c, n in zip(first, block_cells.shape[:3]))] = block_cells
            fmin, fmax = min(fmin, lo), max(fmax, hi)
            lags += block_lags
            if fractions is not None:
                fractions[tuple(slice(e0, e1) for e0, e1 in blk.elements)] = frac
        inputs.f_copy.mark_complete()
        self.f_copy_ready = True  # written whole by this pass
        self.runner.run_everywhere(forget_chunks)  # the b passes read the haloed copy, not the scan
        active = None if fractions is None else active_elements(fractions)
        return Assembled(S, lags, active, float(fmin), float(fmax), cells)

    def _f_copy_pass(self) -> None:
        """Write the haloed ``f`` alone (``M`` read from the output, the interrupted run's copy
        not adopted): the ``M`` pass's reads and low-pass without its sums
        (:func:`chunkdic.engine.tasks.f_copy_task`); before the first ``b`` pass."""
        t0 = time.perf_counter()
        inputs = self.inputs
        inputs.f_copy.unmark()
        for _ in self._map(f_copy_task, [(inputs, job) for job in self.jobs], "low-pass of f"):
            pass
        inputs.f_copy.mark_complete()
        self.f_copy_ready = True
        self.runner.run_everywhere(forget_chunks)
        emit(self.progress, stage="f-copy", level=self.s, blocks=len(self.jobs), seconds=time.perf_counter() - t0)

    def _why_no_gradient(self, u: np.ndarray) -> str | None:
        """The real cause of an empty ``M`` when it is not the reference's texture (issue 24).

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
            return (f"the start field of level {self.s} maps {outside.mean():.0%} of the ROI's elements outside the "
                    f"deformed scan (mean displacement {shift} voxels of the level): nothing left to correlate; "
                    "check --init (a result of another pair or level?) or the ROI")
        if self.active is not None:
            return (f"the mask keeps no textured voxel of the ROI at level {self.s} ({int(self.active.sum())} of "
                    f"{self.active.size} elements kept, most without a gradient): the textured material lies outside "
                    "the mask; check the mask (inverted? of another scan?)")
        return None

    def settle_start(self, start: np.ndarray, *, rebuild: bool) -> None:
        """The start chosen after the level was opened (:func:`chunkdic.engine.steps.best_start`).

        ``rebuild``: assemble ``M`` again around ``start`` (3, nz, ny, nx), voxels of the
        level, and record it as the field ``M`` is built at. ``M`` sums only the voxels its
        field maps inside ``g``: built around a discarded start 5 voxels off, three corner
        nodes lost their texture and the iterations from the chosen start diverged after
        the regularisation length was chosen (docs/engine.md, "The start"). Then the
        weak-node warning, held back until the ``M`` the level iterates with is known.
        """
        self.start_to_choose = False
        if rebuild:
            self.m_start = start
            self._assemble_m(start)
        else:
            self._warn_weak_nodes()

    def regularize(self, length: float, freed: np.ndarray | None = None) -> None:
        """Solve with ``λ R`` from now on (:mod:`chunkdic.solve.regularization`); ``length``: ``ℓ_reg``, voxels of the level;
        ``freed``: the Tikhonov terms the robust reweighting left out (:attr:`Regularizer.freed`,
        the correlated level only; the weight is the plain penalty's for ``length``).

        Coarser levels only give the finest one its starting field, and their low-passed
        sums may leave elements with too little texture: they are always regularised
        (Tikhonov when the run asks for none). Unregularised, a 128³ foam correlated at
        ℓ = 6 moved by 33-82 voxels on level 1 and ended stalled at σ 0.098 voxel; with the
        coarse levels regularised it converged at σ 0.0048.
        """
        kind = self.settings.regularization
        if kind == "none":
            if self.s == self.settings.level:
                return
            kind = "tikhonov"
        reg = Regularizer(kind, self.mesh.nodes_shape, self.mesh.element_size)
        # λ per length^p, once per M and kind: the correlated level weighs up to three lengths
        # (its start, the choice, the reweighting) against the same M
        if self._unit_weight[:2] != (self.solver, kind):
            unit = plane_wave_unit(reg, lambda v: stencil_matvec(self.solver.matrix, v))
            self._unit_weight = (self.solver, kind, unit)
        weight = self._unit_weight[2] * float(length) ** reg.order
        if freed is not None:
            reg = reg.with_freed(freed)
        self.solver.regularize(reg, weight)
        self.regularization_length, self.regularization_weight = float(length), weight
        log.info("level %d: %s regularisation over %.1f voxels (weight %.3g)", self.s, kind, length, weight)

    def weak_nodes(self) -> np.ndarray:
        """Poorly textured nodes (index triples), those outside a specimen mask left out."""
        weak = self.solver.weak_nodes
        if self.active is not None and len(weak):
            weak = weak[~self.masked_nodes()[tuple(weak.T)]]
        return weak

    def _warn_weak_nodes(self) -> None:
        """Warn of the correlated level's poorly textured nodes (coarser levels: logged only).

        A coarser level only gives the next one its start, and its nodes are regularised
        anyway (:meth:`regularize`): a warning about them, printed by every run on scans
        whose corners lose texture to the sums, told users nothing they could act on.
        """
        weak = self.weak_nodes()
        if len(weak) == 0:
            return
        if self.s != self.settings.level:
            log.info("level %d: %d of %d nodes see little texture (regularised; only a start for level %d)",
                     self.s, len(weak), int(np.prod(self.mesh.nodes_shape)), self.s - 1)
            return
        coords = self.mesh.node_coords()
        where = ", ".join(
            "node (%d, %d, %d) at voxel (%.1f, %.1f, %.1f)" % (*n, *coords[(slice(None), *n)]) for n in weak[:5]
        )
        more = f" and {len(weak) - 5} more" if len(weak) > 5 else ""
        warnings.warn(
            f"level {self.s}: {len(weak)} of {np.prod(self.mesh.nodes_shape)} nodes see too little texture "
            f"to be measured ({where}{more}); they are regularised and their values are unreliable",
            PoorTextureWarning,
            stacklevel=4,
        )

    def prepared_for(self, u: np.ndarray) -> bool:
        """Whether ``u`` (3, nz, ny, nx) reads only the part of ``g`` already prepared (no prefilter pass)."""
        if not self.inputs.g_needs_preparing:
            return True
        needed = reachable_box(self.mesh, u, self.inputs.g.shape, margin=0)
        current = self.inputs.prepared
        return needed is None or (current is not None and current.covers(tuple(slice(a, b) for a, b in needed)))

    def prepare_interpolation(self, u: np.ndarray, *, when_needed: bool = False) -> None:
        """Prepare once the part of ``g`` that ``u`` (± a margin) can reach (low-pass, B-spline);
        ``when_needed``: at the first pass only (a level resumed after its iterations ended may need none)."""
        self._deferred = u if when_needed else None
        if when_needed or self.prepared_for(u):
            return
        g_ref = self.inputs.g
        box = reachable_box(self.mesh, u, g_ref.shape, margin=max(8, self.mesh.element_size))
        self._release_prepared()
        self._builds += 1
        path = self.scratch / f"g-level{self.s}-{self._builds}.zarr"
        t0 = time.perf_counter()
        voxels = int(np.prod([b - a for a, b in box]))
        inp = self.inputs
        prepared = build_prepared(
            g_ref, box, path, lambda fn, args: self._map(fn, args, "prefilter of g", voxels),
            halo=inp.g_halo, local=self.runner.local,
            sigma=inp.sigma, interpolation=inp.interpolation,
        )
        self.inputs = dataclasses.replace(self.inputs, prepared=prepared)
        self.runner.run_everywhere(forget_chunks)  # the b passes read the prepared store, not the scan
        emit(self.progress, stage="prepared", level=self.s, box=[list(b) for b in box], voxels=voxels,
             seconds=time.perf_counter() - t0)

    def _release_prepared(self) -> None:
        if self.inputs.prepared is not None:
            path = Path(self.inputs.prepared.ref.path)
            self.inputs = dataclasses.replace(self.inputs, prepared=None)
            self._delete([record_path(path), path])

    def release(self) -> None:
        """Delete this level's scratch data (prepared ``g``, haloed ``f``) and open handles on them."""
        paths = [Path(self.inputs.f_copy.path)]
        if self.inputs.prepared is not None:
            paths += [record_path(self.inputs.prepared.ref.path), Path(self.inputs.prepared.ref.path)]
        self._delete(paths)

    def _delete(self, paths: list[Path]) -> None:
        self.runner.run_everywhere(forget_open_arrays)
        for path in paths:
            remove(path)

    @staticmethod
    def _active_of(active: np.ndarray | None, job: BlockJob) -> np.ndarray | None:
        """A block's slice of an element activity (None: every element)."""
        if active is None:
            return None
        return np.ascontiguousarray(active[tuple(slice(e0, e1) for e0, e1 in job.block.elements)])

    def masked_nodes(self) -> np.ndarray:
        """Nodes with no active element around them (bool, nodes shape); all False without a mask."""
        if self.active is None:
            return np.zeros(self.mesh.nodes_shape, bool)
        a = np.pad(self.active, 1)
        n = self.mesh.nodes_shape
        around = sum(a[dz:dz + n[0], dy:dy + n[1], dx:dx + n[2]] for dz in (0, 1) for dy in (0, 1) for dx in (0, 1))
        return around == 0

    @staticmethod
    def _nodes_of(u: np.ndarray, job: BlockJob) -> np.ndarray:
        """A block's own slice of the nodal field: what its task receives (kilobytes)."""
        return np.ascontiguousarray(u[(slice(None), *job.block.node_slices)])

    def keep_first_pass(self, u: np.ndarray, p: Pass) -> None:
        """Hold the pass ``p`` measured at ``u`` for the iterations that start from ``u``
        (:func:`chunkdic.engine.steps.measure_start_gaps` sums it with the reported gaps)."""
        self._first_pass = (u, p)

    def take_first_pass(self, u: np.ndarray) -> Pass | None:
        """The pass :meth:`keep_first_pass` holds if it was measured at ``u`` (then released), else None."""
        held, self._first_pass = self._first_pass, None
        if held is None or held[0].shape != u.shape or not np.array_equal(held[0], u):
            return None
        return held[1]

    def gap_sample(self) -> np.ndarray | None:
        """The elements a diagnostic gap is measured on (uint8, the mesh's element shape), or
        None for every active element (:meth:`gap`)."""
        stride = gap_stride(self.mesh.shape)
        if stride == 1:
            return None
        sample = np.zeros(self.mesh.shape, np.uint8)
        sample[::stride, ::stride, ::stride] = 1
        if self.active is not None:
            sample &= self.active.astype(np.uint8)
        return sample if sample.any() else None

    def gap(self, u: np.ndarray) -> float:
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
        return self.assemble_b(u, self.gap_sample()).gap

    def assemble_b(self, u: np.ndarray, sample: np.ndarray | None = None,
                   probes: dict[str, np.ndarray] | None = None) -> Pass:
        """One pass for the nodal field ``u``: ``b``, brightness, gap and voxel counts.

        ``sample`` (uint8, the mesh's element shape): only its non-zero elements take part
        (:meth:`gap`); default: every active element. ``probes``: named nodal fields (each
        (3, nz, ny, nx), voxels of the level) whose gap alone is measured in the same tasks,
        as :meth:`gap` measures it (its sample of elements), from the blocks' reads of this
        pass: ``Pass.probe_gaps`` maps each name to its gap (the brightness is fitted to
        every probe as to ``u``). Their cost is the sums alone: one element in 8 on large
        meshes, an eighth of a pass's arithmetic each and no reads.
        """
        mesh = self.mesh
        t0 = time.perf_counter()
        self.last_pass = None  # not held while the next one is summed (mesh-sized)
        if not self.f_copy_ready:
            self._f_copy_pass()
        if self._deferred is not None:
            self.prepare_interpolation(self._deferred)
        nodal = scalars = None
        elements = None
        n_excluded = 0
        lags = np.zeros((6, LAGS + 1))
        active = self.active if sample is None else sample
        names = list(probes or {})
        probe_active = self.gap_sample() if names else None
        if probe_active is None:
            probe_active = self.active
        probe_scalars = [None] * len(names)
        inputs = self.inputs

        def args_of(job):
            fields = tuple(self._nodes_of(probes[name], job) for name in names)
            return (inputs, job, self._nodes_of(u, job), self._active_of(active, job), fields,
                    self._active_of(probe_active, job))

        args = (args_of(job) for job in self.jobs)
        for blk, part, probe_parts in self._map(b_task, args, "b pass", total=len(self.jobs)):
            if nodal is None:
                nodal = np.zeros((part.nodal.shape[0],) + mesh.nodes_shape + (3,))
                scalars = np.zeros_like(part.scalars)
                elements = np.zeros((part.elements.shape[0],) + tuple(mesh.shape))
            nodal[(slice(None), *blk.node_slices)] += part.nodal
            scalars += part.scalars
            elements[(slice(None), *(slice(e0, e1) for e0, e1 in blk.elements))] = part.elements
            n_excluded += part.n_excluded
            lags += part.lags
            for k, (sc, _) in enumerate(probe_parts):
                probe_scalars[k] = sc.copy() if probe_scalars[k] is None else probe_scalars[k] + sc
        part = None
        # b first, then the nodal rows go (5 per node with the drift model, 240 MB at 128³ nodes)
        # before the element rows are fitted: they never coexist with the fit's arrays
        b = nodal_rhs(self.settings.grey, nodal, scalars)
        nodal = None
        fit = element_fit(self.settings.grey, b, scalars, elements, self.inputs.center, mesh.element_size)
        elements = b = None
        gap = math.sqrt(fit.ssr / fit.weight) / self.dynamic_range if fit.weight > 0 else math.inf
        kappa = correlation_factor(lags, self.sensitivity_lags, float(np.median(fit.gain)),
                                   fit.ssr / fit.weight if fit.weight > 0 else None)
        self.last_pass = Pass(fit, gap, mesh.n_voxels - n_excluded, n_excluded, kappa,
                              {name: self._gap_of_scalars(sc) for name, sc in zip(names, probe_scalars)},
                              time.perf_counter() - t0)
        return self.last_pass

    def _gap_of_scalars(self, scalars: np.ndarray) -> float:
        """The gap of a pass from its summed scalars alone (:func:`chunkdic.engine.greylevel.misfit`)."""
        ssr, weight = misfit(self.settings.grey, scalars)
        return math.sqrt(ssr / weight) / self.dynamic_range if weight > 0 else math.inf

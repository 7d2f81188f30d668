"""One pyramid level of a correlation: its blocks, ``M``, prepared ``g`` and ``b`` passes.

A :class:`Level` lives from the ``M`` pass to the end of the level's Gauss–Newton
iterations. It owns the level's scratch data (the haloed copy of ``f``, the B-spline
coefficients of ``g``) and deletes them in :meth:`Level.release`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from . import config
from .errors import InputError
from .haloed import HaloedBlocks
from .mesh import Mesh
from .prefilter import build_coefficients, reachable_box
from .settings import Settings
from .solve import PoorTextureWarning, StencilSolver
from .tasks import BlockJob, LevelInputs, b_task, m_task
from .volume import ArrayRef, forget_open_arrays

log = logging.getLogger(__name__)

#: interval of block-count progress events during a long pass over the voxels (seconds)
PROGRESS_SECONDS = 5.0


def emit(progress: Callable[[dict], None] | None, **event) -> None:
    """Log an engine event and hand it to the caller's ``progress`` callback."""
    log.info("%s", event)
    if progress is not None:
        progress(event)


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
        Receives events (dicts), see :func:`emit`.
    """

    def __init__(self, s: int, mesh: Mesh, f_ref: ArrayRef, g_ref: ArrayRef, runner, settings: Settings,
                 scratch: Path, progress=None):
        self.s, self.mesh, self.runner, self.settings = s, mesh, runner, settings
        self.scratch = scratch
        self.progress = progress
        self._builds = 0
        m = settings.block_elements or max(1, config.get("block-voxels") // mesh.element_size)
        self.jobs = BlockJob.for_mesh(mesh, m)
        self.inputs = LevelInputs(f_ref, g_ref, self._create_f_copy(f_ref), settings.interpolation,
                                  int(config.get("bspline-halo")))
        self.dynamic_range = math.nan

    @property
    def blocks(self) -> list:
        return [job.block for job in self.jobs]

    def _map(self, fn, args, label: str, voxels: int | None = None):
        """Run one task per argument tuple, yield results as they come, report long passes.

        A pass that lasts more than ``PROGRESS_SECONDS`` emits ``stage="blocks"`` events
        (done/total, voxel rate, ETA) at that interval, for a person at a terminal.
        ``voxels``: what the tasks cover together (default: the mesh's ROI).
        """
        total = len(args)
        voxels_per_block = (self.mesh.n_voxels if voxels is None else voxels) / max(total, 1)
        t0 = last = time.perf_counter()
        for done, result in enumerate(self.runner.map_unordered(fn, args), start=1):
            yield result
            now = time.perf_counter()
            if now - last >= PROGRESS_SECONDS and done < total:
                last = now
                rate = done * voxels_per_block / (now - t0)
                emit(self.progress, stage="blocks", level=self.s, label=label, done=done, total=total,
                     rate=rate, eta=(total - done) * voxels_per_block / rate)

    def _create_f_copy(self, f_ref: ArrayRef) -> HaloedBlocks:
        """Empty store for the blocks' haloed ``f`` (see :mod:`chunkdic.haloed`)."""
        grid = tuple(max(job.index[a] for job in self.jobs) + 1 for a in range(3))
        regions = [job.haloed_region(f_ref.shape)[0] for job in self.jobs]
        chunk = tuple(max(r[a].stop - r[a].start for r in regions) for a in range(3))
        return HaloedBlocks.create(self.scratch / f"f-level{self.s}.zarr", grid, chunk, f_ref.dtype)

    def assemble_m(self) -> None:
        """``M`` pass: assemble the stencil, the rigid restriction and the solver."""
        mesh = self.mesh
        # float32: M only steers the modified Gauss-Newton steps (the converged field solves
        # b = 0 whatever M), and at 128³ nodes a float64 stencil alone would be 4 GB.
        # Each block's partial is summed in float64 by its task.
        S = np.zeros(mesh.nodes_shape + (27, 3, 3), dtype=np.float32)
        fmin, fmax = np.inf, -np.inf
        args = [(self.inputs, job) for job in self.jobs]
        for blk, part, lo, hi in self._map(m_task, args, "M pass"):
            S[blk.node_slices] += part
            fmin, fmax = min(fmin, lo), max(fmax, hi)
        self.dynamic_range = float(fmax - fmin)
        if not self.dynamic_range > 0:
            raise InputError(f"the reference is constant over the ROI at level {self.s}: nothing to correlate")
        # Rigid-body restriction of M: since Σ_a N_a = 1, Σ_voxels ∇f ∇fᵀ = Σ_ij M_ij.
        self.rigid_matrix = S.sum(axis=(0, 1, 2, 3), dtype=np.float64)
        self.solver = StencilSolver(S)
        self._warn_weak_nodes()

    def _warn_weak_nodes(self) -> None:
        weak = self.solver.weak_nodes
        if len(weak) == 0:
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

    def prepare_interpolation(self, u: np.ndarray) -> None:
        """Cubic: prefilter once the part of ``g`` that ``u`` (± a margin) can reach."""
        if self.settings.interpolation != "cubic":
            return
        g_ref = self.inputs.g
        needed = reachable_box(self.mesh, u, g_ref.shape, margin=0)
        current = self.inputs.coefficients
        if needed is None or (current is not None and current.covers(tuple(slice(a, b) for a, b in needed))):
            return
        box = reachable_box(self.mesh, u, g_ref.shape, margin=max(8, self.mesh.element_size))
        self._release_coefficients()
        self._builds += 1
        path = self.scratch / f"bspline-level{self.s}-{self._builds}.zarr"
        t0 = time.perf_counter()
        voxels = int(np.prod([b - a for a, b in box]))
        coefficients = build_coefficients(
            g_ref, box, path, lambda fn, args: self._map(fn, args, "prefilter of g", voxels),
            halo=self.inputs.halo, local=self.runner.local,
        )
        self.inputs = dataclasses.replace(self.inputs, coefficients=coefficients)
        log.info("level %d: g prefiltered over %s in %.1f s", self.s, box, time.perf_counter() - t0)

    def _release_coefficients(self) -> None:
        if self.inputs.coefficients is not None:
            path = Path(self.inputs.coefficients.ref.path)
            self.inputs = dataclasses.replace(self.inputs, coefficients=None)
            self._delete([path])

    def release(self) -> None:
        """Delete this level's scratch data (coefficients, haloed ``f``) and open handles on them."""
        paths = [Path(self.inputs.f_copy.path)]
        if self.inputs.coefficients is not None:
            paths.append(Path(self.inputs.coefficients.ref.path))
        self._delete(paths)

    def _delete(self, paths: list[Path]) -> None:
        self.runner.run_everywhere(forget_open_arrays)
        for path in paths:
            shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)

    def assemble_b(self, u: np.ndarray):
        """``b``, matching gap, valid and excluded voxel counts for the nodal field ``u``."""
        mesh = self.mesh
        b = np.zeros(mesh.nodes_shape + (3,))
        ssr, n_valid, n_excluded = 0.0, 0, 0
        args = [(self.inputs, job, np.ascontiguousarray(u[(slice(None), *job.block.node_slices)]))
                for job in self.jobs]
        for blk, part, r2, nv, ne in self._map(b_task, args, "b pass"):
            b[blk.node_slices] += part
            ssr += r2
            n_valid += nv
            n_excluded += ne
        gap = math.sqrt(ssr / n_valid) / self.dynamic_range if n_valid else math.inf
        return b, gap, n_valid, n_excluded

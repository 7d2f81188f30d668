"""The dense twin of the block passes: the method's protocol on in-memory scans.

:class:`DensePasses` implements :class:`chunkdic.method.protocol.Passes` with no store, no
task and no block: the whole ROI of in-memory NumPy scans is one block, ``f`` is low-passed
once and ``g`` prepared once (the whole volume), and each pass is one call of the kernels,
by default their plain NumPy twins (:mod:`chunkdic.kernels.twins`, ``impl="numpy"``). The
tests run the whole method on it and on the out-of-core passes
(:class:`chunkdic.passes.level.LevelPasses`) and compare the fields: the oracle of the
machinery around the kernels (blocks, tasks, scratch stores and their 16-bit grids, the
client's sums), as dask-image tests its Dask filters against SciPy's. It reads every voxel
at once: for small scans only.

What it shares with the block passes is what defines the values, not how they are got: the
low-pass and prefilter (:mod:`chunkdic.passes.prefilter`), the 16-bit grids of the scratch
stores (:func:`chunkdic.passes.haloed.quantization`,
:func:`chunkdic.passes.prefilter.prepared_grid`), the task-side reduction of a brightness
model (:func:`chunkdic.method.brightness.reduce_block`) and the client's fit of the summed
partials (:class:`chunkdic.passes.reduction.PassSums`). Where the block passes prepare ``g``
over a box smaller than the volume, their values there differ from these by the
prefilter's float32 round-off at the box's faces.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..errors import InputError
from ..kernels.b import b_sums
from ..kernels.m import m_block
from ..kernels.quantize import quantize_u16
from ..mesh import Mesh
from ..method.brightness import offset_cell, reduce_block
from ..method.operator import Assembled, Operator, build_operator
from ..method.protocol import Pass, stack_rows
from ..method.settings import Settings
from .crack_cut import CrackLabels, cut_b_sums, cut_m_sums, fast_active, global_pairs, other_rows, read_cut
from .haloed import quantization
from .level import gap_sample
from .prefilter import (
    check_finite,
    face_margin,
    gaussian_radius,
    on_grid,
    prepare_deformed,
    prepare_reference,
    prepared_grid,
    reachable_box,
)
from .reduction import PassSums
from .tasks import BlockJob, halo_region
from .translation import translation_task

__all__ = ["DensePasses"]


class DensePasses:
    """The passes over one level of in-memory scans (module docstring).

    Parameters
    ----------
    f, g : ndarray, 3-D, grey levels
        Reference and deformed scans at the level (any real dtype; as the level's arrays).
    mesh : Mesh
        The level's mesh.
    settings : Settings
        The correlation's settings (interpolation, low-pass, brightness model).
    level : int
        The pyramid level (for the events and the regularisation of coarse levels).
    active : ndarray, shape (ez, ey, ex), optional
        Elements that take part (non-zero) (a specimen mask's, :func:`chunkdic.passes.masks.active_elements`).
    impl : {"numpy", "numba"}
        The kernels' NumPy twins or the numba kernels themselves.
    crack : ndarray, 3-D, optional
        A known crack surface at the level (non-zero voxels, the scans' shape;
        :mod:`chunkdic.passes.crack_cut`).
    """

    def __init__(self, f: np.ndarray, g: np.ndarray, mesh: Mesh, settings: Settings, *, level: int = 0,
                 active: np.ndarray | None = None, impl: str = "numpy", crack: np.ndarray | None = None):
        self.level, self.mesh, self.settings, self.impl = level, mesh, settings, impl
        self.active = None if active is None else (np.asarray(active) != 0).astype(np.uint8)
        self.cell = offset_cell(settings.grey, mesh.element_size, settings.grey_cell)
        sigma = settings.smoothing
        self.margin = face_margin(sigma)
        (job,) = BlockJob.for_mesh(mesh, max(mesh.shape))
        self.job = job
        labels = None if crack is None else CrackLabels(_InMemory(np.asarray(crack)), mesh.origin, mesh.shape,
                                                        self.margin)
        self.cut = read_cut(labels, job.block.elements, job.ell)
        self.f_raw, self.g_raw = np.asarray(f), np.asarray(g)
        self.f_block, self.lo, self.hi = _haloed_reference(self.f_raw, job, sigma)
        g = self.g_raw
        self.g_shape = g.shape
        check_finite(g, "deformed", tuple(slice(0, n) for n in g.shape))
        if settings.interpolation == "cubic" or sigma > 0:
            grid = prepared_grid(g.dtype, sigma, settings.interpolation)
            self.g = on_grid(prepare_deformed(g, sigma, settings.interpolation), grid)
        else:
            self.g = np.asarray(g, np.float32)
        self.needs_preparing = settings.interpolation == "cubic" or sigma > 0
        #: the box of g the block passes would have prepared (their prefilter's bookkeeping):
        #: what :meth:`covers` answers from, as theirs does
        self.box = None

    def assemble_m(self, u: np.ndarray) -> Operator:
        """``M`` for the field ``u`` (one kernel call over the ROI)."""
        job, s = self.job, self.settings
        stencil, fmin, fmax, lags, *cells = m_block(
            self.f_block, self.lo, self.hi, job.ell, impl=self.impl, grey=s.grey, center=float(self.f_block.mean()),
            u_nodes=u, core_origin=job.start, g_shape=self.g_shape, margin=self.margin, with_lags=True,
            cell=self.cell, active=fast_active(self.active, self.cut, self.mesh.shape))
        crack = None
        if self.cut is not None:
            part, pairs = cut_m_sums(self.cut, self.f_block, self.lo, self.hi, job.ell, u, job.start, self.g_shape,
                                     margin=self.margin, active=self.active)
            stencil = stencil + part
            crack = global_pairs(pairs, self.cut, (0, 0, 0))
        half = np.zeros(self.mesh.nodes_shape + (14, 3, 3), dtype=np.float32)
        half += stencil[..., 13:, :, :]  # the stored half stencil, float32 (solve.HALF_OFFSETS)
        if not float(fmax - fmin) > 0:
            raise InputError(f"the reference is constant over the ROI at level {self.level}: nothing to correlate")
        m = Assembled(half, lags, self.active, float(fmin), float(fmax), cells[0] if cells else None, crack)
        return build_operator(m, u, cell=self.cell)

    def covers(self, u: np.ndarray) -> bool:
        """Whether the block passes would find ``u`` within their prepared ``g``."""
        if not self.needs_preparing:
            return True
        needed = reachable_box(self.mesh, u, self.g_shape, margin=0)
        return needed is None or (self.box is not None and all(a <= c and d <= b for (a, b), (c, d)
                                                                in zip(self.box, needed)))

    def prepare(self, u: np.ndarray) -> None:
        """Mark the box the block passes would prepare for ``u`` (``g`` is prepared whole already)."""
        if not self.covers(u):
            self.box = reachable_box(self.mesh, u, self.g_shape, margin=max(8, self.mesh.element_size))

    def park(self, array) -> np.ndarray:
        """``array`` itself (rows stacked, :func:`~chunkdic.method.protocol.stack_rows`): the mesh
        data of in-memory scans stay in memory."""
        return stack_rows(array)

    def assemble_b(self, u: np.ndarray, op: Operator, *, sample: np.ndarray | None = None,
                   probes: dict[str, np.ndarray] | None = None, other: np.ndarray | None = None) -> Pass:
        """One pass for ``u`` (one kernel call over the ROI per field; ``other``: the second
        copies (K, 3) of ``op.crack``'s split nodes)."""
        t0 = time.perf_counter()
        names = list(probes or {})
        active = op.active if sample is None else sample
        probe_active = gap_sample(self.mesh.shape, op.active) if names else None
        if probe_active is None:
            probe_active = op.active
        grey, cell = self.settings.grey, self.cell
        probe_parts = []
        for name in names:
            part = reduce_block(self._sums(probes[name], op, probe_active)[0], grey, cell)
            probe_parts.append((part.scalars, part.n_excluded))
        sums = PassSums(self.mesh, len(names), op.crack)
        whole_other = None if op.crack is None else op.crack.other_field(u, other)
        main, B1 = self._sums(u, op, active, whole_other)
        rows = None
        if B1 is not None:
            nodal = reduce_block(dataclasses.replace(main, B=B1), grey, cell).nodal
            rows = other_rows(nodal, self.cut, (0, 0, 0))
        sums.add(self.job.block, reduce_block(main, grey, cell), probe_parts, rows)
        return sums.result(grey, op, names, t0)

    def _sums(self, u: np.ndarray, op: Operator, active: np.ndarray | None, other: np.ndarray | None = None):
        """The element sums of ``u`` (and, with a crack, the second copies' ``B``, else None)."""
        job = self.job
        active = None if active is None else np.asarray(active, np.uint8)
        out = b_sums(self.f_block, self.lo, self.hi, job.ell, u, job.start, self.g, (0, 0, 0), self.g_shape,
                     interpolation=self.settings.interpolation, impl=self.impl, prefiltered=True, center=op.center,
                     margin=self.margin, active=fast_active(active, self.cut, self.mesh.shape))
        if self.cut is None:
            return out, None
        B1 = cut_b_sums(out, self.cut, self.f_block, self.lo, self.hi, job.ell, u, u if other is None else other,
                        job.start, self.g, (0, 0, 0), self.g_shape, interpolation=self.settings.interpolation,
                        center=op.center, margin=self.margin, active=active)
        return out, B1

    def gap(self, u: np.ndarray, op: Operator) -> float:
        """The matching gap of ``u`` alone, on the sample of elements the block passes use."""
        return self.assemble_b(u, op, sample=gap_sample(self.mesh.shape, op.active)).gap

    def translation(self) -> np.ndarray:
        """The phase-correlation translation over the ROI (:func:`chunkdic.passes.translation.translation_task`)."""
        return translation_task(_InMemory(self.f_raw), _InMemory(self.g_raw), self.mesh.roi)


class _InMemory:
    """An in-memory array as the readers of :mod:`chunkdic.passes.translation` see a stored one."""

    def __init__(self, a: np.ndarray):
        self.a, self.shape = a, a.shape

    def read(self, region) -> np.ndarray:
        return np.asarray(self.a[region])


def _haloed_reference(f: np.ndarray, job: BlockJob, sigma: float) -> tuple[np.ndarray, tuple, tuple]:
    """The ROI of ``f`` with its one-voxel halo (clipped), low-passed, on the haloed store's
    16-bit grid when the block passes keep it there (:class:`chunkdic.passes.haloed.HaloedBlocks`)."""
    inner, lo, hi = halo_region(job.start, job.shape, f.shape, 1)
    region, _, _ = halo_region(job.start, job.shape, f.shape, 1 + gaussian_radius(sigma))
    raw = f[region]
    check_finite(raw, "reference", region)
    if sigma <= 0:
        return np.asarray(raw, np.float32), lo, hi
    block = prepare_reference(raw, region, inner, sigma)
    offset, step = quantization(f.dtype)
    if step > 0:  # rounded in float64, as HaloedBlocks.write does
        block = quantize_u16(block, offset, step, wide=True)[1]
    return np.asarray(block, np.float32), lo, hi

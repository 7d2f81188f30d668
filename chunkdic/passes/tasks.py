"""Task bodies of the engine: what one worker does for one block of elements.

A task receives a :class:`BlockJob` (which block: a few integers), the level's
:class:`LevelInputs` (paths and small descriptors, never voxels) and, for ``b``, its own
slice of the nodal field; it reads its voxels from the stores and returns mesh-sized
partials (shared/DESIGN.md, "Out-of-core shape").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import config
from ..io.handles import ArrayRef
from ..kernels.b import b_sums
from ..kernels.blocks import ElementSums
from ..kernels.m import m_block
from ..kernels.window import g_window
from ..mesh import Block, Mesh
from ..method.brightness import Partials, reduce_block
from .haloed import HaloedBlocks
from .masks import active_elements, element_fractions
from .prefilter import (
    PreparedImage,
    check_finite,
    face_margin,
    gaussian_radius,
    on_grid,
    prepare_deformed,
    prepare_reference,
    prepared_grid,
    prepared_halo,
)


@dataclass(frozen=True)
class BlockJob:
    """One block of whole elements of a level's mesh.

    Attributes
    ----------
    block : Block
        Element ranges.
    ell : int
        Element edge, voxels of the level.
    start, shape : tuple of 3 int
        Absolute first voxel and shape of the block's core, voxels of the level.
    index : tuple of 3 int
        Position of the block in the block grid (its chunk of the haloed ``f`` copy).
    """

    block: Block
    ell: int
    start: tuple[int, int, int]
    shape: tuple[int, int, int]
    index: tuple[int, int, int]

    @classmethod
    def for_mesh(cls, mesh: Mesh, elements_per_block: int) -> list["BlockJob"]:
        """Every block of ``mesh``, at most ``elements_per_block`` elements per side."""
        m = max(1, int(elements_per_block))
        jobs = []
        for blk in mesh.blocks(m):
            start, shape = mesh.block_core(blk)
            index = tuple(e0 // m for e0, _ in blk.elements)
            jobs.append(cls(blk, mesh.element_size, start, shape, index))
        return jobs

    def haloed_region(self, volume_shape) -> tuple[tuple[slice, ...], tuple[int, ...], tuple[int, ...]]:
        """The core grown by one voxel (clipped to the volume) and the halo obtained per side."""
        return halo_region(self.start, self.shape, volume_shape)


@dataclass(frozen=True)
class LevelInputs:
    """What every task of one level reads: stores and the level's image settings.

    Attributes
    ----------
    f, g : ArrayRef
        Reference and deformed scans at the level.
    f_copy : HaloedBlocks
        Each block's prepared, haloed ``f``, written by the ``M`` pass, read by the ``b`` passes.
    interpolation : {"cubic", "linear"}
    sigma : float
        Gaussian low-pass of both scans, voxels of the level (0: none).
    grey : str
        Brightness model (:mod:`chunkdic.method.brightness`).
    bspline_halo : int
        Extra voxels around a ``g`` window prefiltered by the task itself (cubic).
    g_margin : int
        Voxels ``X + u(X)`` falling within this distance of a face of ``g`` are excluded:
        there the low-pass of ``g`` sees the mirror extension instead of the specimen's
        continuation (:func:`chunkdic.passes.prefilter.face_margin`).
    center : float
        Centring constant of the brightness sums (the level's mid grey level, set by the
        ``M`` pass).
    prepared : PreparedImage or None
        The level's prepared ``g``, when built.
    level : int
        The pyramid level.
    mask : ArrayRef or None
        The binary specimen mask's sums at this level (:mod:`chunkdic.passes.masks`).
    g_grid : (float, float)
        ``(offset, step)`` of the grid the prepared ``g`` is kept on
        (:func:`chunkdic.passes.prefilter.prepared_grid`, chosen on the client for the run's
        scratch layout); a task that prepares its own window rounds it to the same grid.
    grey_cell : int
        Elements per side of the cells sharing one brightness offset
        (:func:`chunkdic.method.brightness.offset_cell`; blocks hold whole cells).
    """

    f: ArrayRef
    g: ArrayRef
    f_copy: HaloedBlocks
    interpolation: str
    sigma: float
    grey: str
    bspline_halo: int
    g_margin: int = 0
    center: float = 0.0
    prepared: PreparedImage | None = None
    level: int = 0
    mask: ArrayRef | None = None
    g_grid: tuple[float, float] = (0.0, 0.0)
    grey_cell: int = 1

    @classmethod
    def for_settings(cls, f: ArrayRef, g: ArrayRef, f_copy: HaloedBlocks | None, *, level: int,
                     interpolation: str, smoothing: float, grey: str, mask: ArrayRef | None = None,
                     grey_cell: int = 1) -> "LevelInputs":
        """The one way to make a level's inputs from a run's settings: the B-spline halo from
        ``chunkdic.bspline-halo`` and the margin near the faces of ``g`` from the low-pass
        (:func:`chunkdic.passes.prefilter.face_margin`) are derived here, once."""
        return cls(f, g, f_copy, interpolation, float(smoothing), grey, int(config.get("bspline-halo")),
                   face_margin(smoothing), level=int(level), mask=mask,
                   g_grid=prepared_grid(g.dtype, smoothing, interpolation), grey_cell=int(grey_cell))

    @property
    def g_needs_preparing(self) -> bool:
        return self.interpolation == "cubic" or self.sigma > 0

    @property
    def g_halo(self) -> int:
        """Halo (voxels) a window of raw ``g`` needs to be prepared exactly on its crop."""
        return prepared_halo(self.sigma, self.interpolation, self.bspline_halo)


def halo_region(start, shape, full_shape, halo: int = 1):
    """Core box grown by ``halo`` voxels, clipped to the volume; and the halos obtained."""
    region, lo, hi = [], [], []
    for a, n, N in zip(start, shape, full_shape):
        r0, r1 = max(a - halo, 0), min(a + n + halo, N)
        region.append(slice(r0, r1))
        lo.append(a - r0)
        hi.append(r1 - (a + n))
    return tuple(region), tuple(lo), tuple(hi)


def read_prepared_reference(inputs: LevelInputs, start, shape, halo: int = 1):
    """The reference over a block core grown by ``halo`` voxels (clipped), checked and low-passed.

    Returns ``(f, lo, hi)``: the block (float32 when low-passed, else the scan's dtype) and
    the halo obtained on each side (:func:`halo_region`).
    """
    inner, lo, hi = halo_region(start, shape, inputs.f.shape, halo)
    region, _, _ = halo_region(start, shape, inputs.f.shape, halo + gaussian_radius(inputs.sigma))
    raw = inputs.f.read(region)
    check_finite(raw, "reference", region)
    f = prepare_reference(raw, region, inner, inputs.sigma) if inputs.sigma > 0 else raw
    return f, lo, hi


def m_task(inputs: LevelInputs, job: BlockJob, u_block: np.ndarray):
    """Task: this block's share of ``M`` (a nodal stencil), the min/max of the prepared ``f``
    and, with brightness cells, their offsets' Schur complement (:func:`~chunkdic.kernels.m.cell_couplings`,
    None without cells).

    Reads the block with the halo its low-pass needs, checks it, low-passes it and keeps
    the prepared block with its one-voxel halo as its chunk of ``inputs.f_copy`` for the
    ``b`` passes. ``u_block``: the level's starting field on the block's nodes; voxels it
    maps outside ``g`` are left out of ``M`` as the ``b`` passes leave them out.
    """
    f, lo, hi = read_prepared_reference(inputs, job.start, job.shape, halo=1)
    f = np.asarray(inputs.f_copy.write(job.index, f), dtype=np.float32)  # as the b passes will read it
    fractions = None
    if inputs.mask is not None:
        fractions = element_fractions(inputs.mask, inputs.level, job.start, job.shape, job.ell)
    # the brightness condensation is invariant to the centring constant: the block's mean
    # keeps its sums small
    stencil, fmin, fmax, lags, *cells = m_block(f, lo, hi, job.ell, grey=inputs.grey, center=float(f.mean()),
                                                u_nodes=u_block, core_origin=job.start, g_shape=inputs.g.shape,
                                                margin=inputs.g_margin, with_lags=True, cell=inputs.grey_cell,
                                                active=None if fractions is None else active_elements(fractions))
    return job.block, stencil, fmin, fmax, lags, fractions, (cells[0] if cells else None)


def f_copy_task(inputs: LevelInputs, job: BlockJob) -> Block:
    """Task: this block's haloed, low-passed ``f`` into ``inputs.f_copy``, as :func:`m_task`
    writes it, without the sums of ``M`` (a resumed level that read ``M`` from the output,
    :mod:`chunkdic.passes.stored_matrix`)."""
    f, _, _ = read_prepared_reference(inputs, job.start, job.shape, halo=1)
    inputs.f_copy.write(job.index, f)
    return job.block


def b_task(inputs: LevelInputs, job: BlockJob, u_block: np.ndarray,
           active: np.ndarray | None = None, probes: tuple = (),
           probe_active: np.ndarray | None = None) -> tuple[Block, Partials, list]:
    """Task: this block's share of one Gauss–Newton pass (:class:`chunkdic.method.brightness.Partials`).

    ``f`` (with its halo) comes from the level's haloed copy written by the ``M`` pass;
    the window of ``g`` from the level's prepared store when it covers it, else it is read
    raw with a halo and prepared here (same result to float32 precision). ``active``: the
    block's element activity (a specimen mask), default all.

    ``probes``: further nodal fields over the block's nodes (each (3, ez+1, ey+1, ex+1))
    whose misfit alone is wanted (the reported gaps of no motion and of the rigid
    translation): summed over the elements ``probe_active`` keeps, from the same reads of
    ``f`` and ``g`` (one window covering every field). Returns ``(block, partials, probe_parts)``,
    ``probe_parts`` one ``(scalars, n_excluded)`` per probe (the misfit's scalars of
    :class:`Partials`: a few numbers, no nodal rows).
    """
    region, lo, hi = job.haloed_region(inputs.f.shape)
    f = inputs.f_copy.read(job.index, tuple(r.stop - r.start for r in region))
    g, g_origin = read_g_window(inputs, job, u_block, *probes)

    def sums(u, act):
        if g is None:
            # no voxel of the block maps inside g: every active voxel is excluded
            n_off = 0 if act is None else int(np.sum(act == 0)) * job.ell**3
            return ElementSums(np.zeros(job.block.n_elements + (6, 8, 3)),
                               np.zeros(job.block.n_elements + (6, 6)), int(np.prod(job.shape)) - n_off)
        return b_sums(f, lo, hi, job.ell, u, job.start, g, g_origin, inputs.g.shape,
                      interpolation=inputs.interpolation, prefiltered=True, center=inputs.center,
                      margin=inputs.g_margin, active=act)

    probe_parts = []
    for u in probes:
        part = reduce_block(sums(u, probe_active), inputs.grey, inputs.grey_cell)
        probe_parts.append((part.scalars, part.n_excluded))
    return job.block, reduce_block(sums(u_block, active), inputs.grey, inputs.grey_cell), probe_parts


def read_g_window(inputs: LevelInputs, job: BlockJob, u_block: np.ndarray, *more: np.ndarray):
    """The prepared window of ``g`` a block needs for the field ``u_block`` (and the fields ``more``).

    Returns ``(window, origin)``: float32 samples (linear) or B-spline coefficients (cubic)
    of the low-passed ``g``; ``(None, None)`` when no voxel of the block can map inside ``g``
    for any of the fields. With ``more``, one window covers every field's.
    """
    interp = inputs.interpolation

    def window_for(halo: int = 0):
        boxes = [g_window(job.start, job.shape, u, inputs.g.shape, interpolation=interp, halo=halo,
                          margin=inputs.g_margin) for u in (u_block, *more)]
        boxes = [b for b in boxes if all(s.stop > s.start for s in b)]
        if not boxes:
            return None
        return tuple(slice(min(b[a].start for b in boxes), max(b[a].stop for b in boxes)) for a in range(3))

    window = window_for()
    if window is None:
        return None, None
    if inputs.prepared is not None and inputs.prepared.covers(window):
        return inputs.prepared.read(window), tuple(s.start for s in window)
    if not inputs.g_needs_preparing:
        return np.asarray(inputs.g.read(window), dtype=np.float32), tuple(s.start for s in window)
    window = window_for(prepared_halo(inputs.sigma, interp, inputs.bspline_halo))
    raw = inputs.g.read(window)
    check_finite(raw, "deformed", window)
    # on the prepared store's grid (chosen on the client: the layout is the run's), so that a
    # result never depends on the store's box
    grid = inputs.g_grid
    prepared = on_grid(prepare_deformed(raw, inputs.sigma, interp), grid)
    return prepared, tuple(s.start for s in window)

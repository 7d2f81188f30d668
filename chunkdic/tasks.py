"""Task bodies of the engine: what one worker does for one block of elements.

A task receives a :class:`BlockJob` (which block: a few integers), the level's
:class:`LevelInputs` (paths and small descriptors, never voxels) and, for ``b``, its own
slice of the nodal field; it reads its voxels from the stores and returns mesh-sized
partials (shared/DESIGN.md, "Out-of-core shape").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels
from .haloed import HaloedBlocks
from .mesh import Block, Mesh
from .prefilter import Coefficients
from .volume import ArrayRef


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
    """What every task of one level reads: stores and interpolation settings.

    Attributes
    ----------
    f, g : ArrayRef
        Reference and deformed scans at the level.
    f_copy : HaloedBlocks
        Each block's haloed ``f``, written by the ``M`` pass, read by the ``b`` passes.
    interpolation : {"cubic", "linear"}
    halo : int
        Extra voxels around a ``g`` window prefiltered by the task itself (cubic).
    coefficients : Coefficients or None
        The level's prefiltered ``g`` (cubic), when built.
    """

    f: ArrayRef
    g: ArrayRef
    f_copy: HaloedBlocks
    interpolation: str
    halo: int
    coefficients: Coefficients | None = None


def halo_region(start, shape, full_shape, halo: int = 1):
    """Core box grown by ``halo`` voxels, clipped to the volume; and the halos obtained."""
    region, lo, hi = [], [], []
    for a, n, N in zip(start, shape, full_shape):
        r0, r1 = max(a - halo, 0), min(a + n + halo, N)
        region.append(slice(r0, r1))
        lo.append(a - r0)
        hi.append(r1 - (a + n))
    return tuple(region), tuple(lo), tuple(hi)


def m_task(inputs: LevelInputs, job: BlockJob):
    """Task: this block's share of ``M`` (a nodal stencil) and the min/max of ``f``.

    Also keeps the block's haloed ``f`` as its chunk of ``inputs.f_copy`` for the ``b`` passes.
    """
    region, lo, hi = job.haloed_region(inputs.f.shape)
    raw = inputs.f.read(region)
    inputs.f_copy.write(job.index, raw)
    stencil, fmin, fmax = kernels.m_block(raw.astype(np.float32, copy=False), lo, hi, job.ell)
    return job.block, stencil, fmin, fmax


def b_task(inputs: LevelInputs, job: BlockJob, u_block: np.ndarray):
    """Task: this block's share of ``b``, ``Σ r²`` and the valid/excluded voxel counts.

    ``f`` (with its halo) comes from the level's haloed copy written by the ``M`` pass.
    With cubic interpolation the window of ``g`` comes from the level's prefiltered
    coefficients when they cover it, else it is read raw with a halo and prefiltered
    here (same result to float32 precision, see :mod:`chunkdic.prefilter`).
    """
    region, lo, hi = job.haloed_region(inputs.f.shape)
    f = inputs.f_copy.read(job.index, tuple(r.stop - r.start for r in region)).astype(np.float32, copy=False)
    g, g_origin, prefiltered = read_g_window(inputs, job, u_block)
    if g is None:
        b = np.zeros(u_block.shape[1:] + (3,))
        return job.block, b, 0.0, 0, int(np.prod(job.shape))
    b, ssr, n_valid, n_excluded = kernels.b_block(
        f, lo, hi, job.ell, u_block, job.start, g, g_origin, inputs.g.shape,
        interpolation=inputs.interpolation, prefiltered=prefiltered,
    )
    return job.block, b, ssr, n_valid, n_excluded


def read_g_window(inputs: LevelInputs, job: BlockJob, u_block: np.ndarray):
    """The window of ``g`` a block needs for the field ``u_block``.

    Returns ``(window data, window origin, prefiltered)``, or ``(None, None, False)`` when
    no voxel of the block can map inside ``g``.
    """
    interp = inputs.interpolation
    window = kernels.g_window(job.start, job.shape, u_block, inputs.g.shape, interpolation=interp)
    if any(s.stop <= s.start for s in window):
        return None, None, False
    coefficients = inputs.coefficients
    if coefficients is not None and coefficients.covers(window):
        return coefficients.read(window), tuple(s.start for s in window), True
    if interp == "cubic":
        window = kernels.g_window(job.start, job.shape, u_block, inputs.g.shape, interpolation=interp,
                                  halo=inputs.halo)
    return inputs.g.read(window), tuple(s.start for s in window), False

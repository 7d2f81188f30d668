"""Voxel-wise fields of a result for viewers: one OME-NGFF 0.5 image on the scan's grid.

One idea: :func:`write_fields` turns a result (a nodal field on a mesh of some pyramid
level) into volumes a viewer lays over the scan with no code: ``Uz, Uy, Ux``, ``|U|``,
``eps_zz``, the equivalent (von Mises) strain and the residual, as the channels of one
multiscale OME-NGFF 0.5 image (axes ``c, z, y, x``) on the reference scan's **full level-0
grid**, or on its level-``S`` grid (``grid_level=S``, ``export --fields-level S``: ``8^-S``
of the size, for whole specimens), with its scale, unit and origin, NaN outside the ROI (and
outside a specimen mask). napari (napari-ome-zarr) opens it as one layer per channel, named,
with its contrast window; neuroglancer opens it as one layer with a channel dimension.

Everything voxel-sized is made by tasks, one per output chunk (shared/DESIGN.md,
"Out-of-core shape"): a task receives the nodes, element values and brightness of the
elements its chunk touches (kilobytes) and writes its chunk of every channel; the
pyramid levels ``1..k`` are 2×2×2 means (NaN-aware) made by tasks from the level below;
the contrast windows come from a bounded sample of the coarsest level, read by tasks
(:func:`chunkdic.export.images.write_image`, the writer shared with the corrected image).
Before anything is written, the image's size (every chunk stored whole, uncompressed: an
upper bound) is compared with the free disk of where it goes (:func:`plan_fields`).

- Grid: level-``S`` voxel ``j`` has its centre at level-0 coordinate ``2^S j + (2^S - 1)/2``
  (shared/DESIGN.md); the image's level 0 carries the scan's level-``S`` scale and
  translation (:func:`chunkdic.io.ngff.level_frame`). A voxel is in the ROI when its centre
  lies in the mesh's box (:func:`roi_on_grid`).
- Displacement: the C8 field (trilinear shape functions) sampled at those centres. A
  level-``S`` centre lies at level-``s`` position ``(2^S (j + 1/2)) / 2^s - 1/2``
  (:func:`chunkdic.mesh.level_to_level`) and the displacement in level-0 voxels is
  ``2^s`` times the level-``s`` value (physical units: times the voxel size per axis),
  whatever ``S``.
- Strain: per element, constant over the element, the value of :mod:`chunkdic.results.strain`
  (the C8 gradient at the element centre = its average; paper section 5.4), as the
  result's ``strain`` array and ``chunkdic strain`` use; a voxel takes the element holding
  its centre. The equivalent strain is ``sqrt(2/3 e:e)`` with ``e`` the deviatoric part.
- Residual: ``f̃(X) - corrected g(X + u(X))`` of :mod:`chunkdic.export.correction` (what the
  engine compared), in grey levels of the result's level, computed per task at that level.
  On a grid at least as fine as the result's (``S <= s``): the residual of the level-``s``
  voxel holding the centre, repeated (nearest). On a coarser grid (``S > s``): the mean of
  ``|r|`` over the level-``s`` voxels each level-``S`` voxel holds (:func:`mean_abs_residual`;
  a signed mean would cancel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mesh import Block, Mesh, level_to_level
from ..results.result import Result
from ..results.strain import element_strain
from .correction import brightness_fields, correct_block, element_slice

__all__ = ["CHANNELS", "FieldsJob", "fields_values", "fields_task"]

#: channel labels of the image, in order (``|U|`` is the displacement's norm)
CHANNELS = ("Uz", "Uy", "Ux", "|U|", "eps_zz", "eps_eq", "residual")


@dataclass(frozen=True)
class FieldsJob:
    """What every task of :func:`write_fields` shares: the mesh, grids, units, stores.

    Attributes
    ----------
    mesh : Mesh
        The result's mesh (voxels of its level ``level``).
    level : int
        The result's pyramid level ``s``.
    shape0 : tuple of 3 int
        The image grid's shape: the reference scan's level-``grid_level`` shape.
    factor : tuple of 3 float
        Output displacement per level-``s`` voxel of displacement, per component ``(z, y, x)``:
        ``2^s`` (level-0 voxels) or ``2^s * voxel_size`` (physical units).
    out : str
        The image group being written (its level arrays ``"0"``, ``"1"``, …).
    correction : Correction or None
        How to compute the residual (None: the residual channel stays NaN).
    strain : str
        Strain measure of ``eps_zz`` and ``eps_eq`` (:mod:`chunkdic.results.strain`).
    grid_level : int
        The scan's pyramid level ``S`` whose grid the image's level 0 lies on (0: the
        scan's full grid).
    """

    mesh: Mesh
    level: int
    shape0: tuple[int, int, int]
    factor: tuple[float, float, float]
    out: str
    correction: object | None
    strain: str = "small"
    grid_level: int = 0


def roi_level0(mesh: Mesh, level: int) -> tuple[tuple[int, int], ...]:
    """Level-0 voxels ``[a, b)`` per axis whose centres lie in the mesh's elements: those
    summed into the ROI's level-``s`` voxels, ``[2^s o, 2^s (o + n ell))``."""
    return roi_on_grid(mesh, level, 0)


def roi_on_grid(mesh: Mesh, level: int, grid_level: int) -> tuple[tuple[int, int], ...]:
    """Voxels ``[a, b)`` per axis of the scan's level-``S`` grid whose centres lie in the
    mesh's box (the ROI of a level-``s`` mesh seen on the level-``S`` grid).

    In level-0 units the mesh spans ``[A - 1/2, B - 1/2]`` (first node to last node) with
    ``A = 2^s o``, ``B = 2^s (o + n ell)``, and level-``S`` voxel ``j`` has its centre at
    ``2^S (j + 1/2) - 1/2`` (shared/DESIGN.md), so ``j`` is inside when
    ``A <= 2^S (j + 1/2) <= B``; exact integer arithmetic below. ``S = 0``:
    ``[2^s o, 2^s (o + n ell))`` (centres never fall on the box's faces). A coarse voxel
    whose centre falls on a face (half of it in the ROI) counts as inside, at both ends.

    Examples
    --------
    >>> m = Mesh((6, 6, 6), 12, (3, 3, 3))  # level 0, voxels [6, 42), box [5.5, 41.5]
    >>> roi_on_grid(m, 0, 0)[0], roi_on_grid(m, 0, 2)[0]  # level-2 centres 4 j + 1.5
    ((6, 42), (1, 11))
    """
    out = []
    for o, n in zip(mesh.origin, mesh.shape):
        a, b = 2**level * o, 2**level * (o + n * mesh.element_size)
        # 2^(S+1) j + 2^S >= 2a (the smallest such j) and <= 2b (one past the largest)
        first = -((2**grid_level - 2 * a) // 2 ** (grid_level + 1))
        end = (2 * b - 2**grid_level) // 2 ** (grid_level + 1) + 1
        out.append((int(first), int(end)))
    return tuple(out)


def _chunk_elements(job: FieldsJob, region) -> tuple | None:
    """The in-ROI grid range of a chunk and the element range it touches, per axis
    (None if the chunk misses the ROI)."""
    inside, elements = [], []
    for axis, (r, (a, b)) in enumerate(zip(region, roi_on_grid(job.mesh, job.level, job.grid_level))):
        lo, hi = max(r.start, a), min(r.stop, b)
        if lo >= hi:
            return None
        if job.grid_level > job.level:  # every level-s voxel the coarse voxels hold (their mean |r|)
            f = 2 ** (job.grid_level - job.level)
            ends = np.array([lo * f, hi * f - 1], np.float64)
        else:  # the voxel centres
            ends = _level_positions(np.array([lo, hi - 1]), job.grid_level, job.level)
        k, _ = job.mesh.element_index(axis, ends)
        inside.append((lo, hi))
        elements.append((int(k[0]), int(k[1]) + 1))
    return tuple(inside), tuple(elements)


def _level_positions(x: np.ndarray, grid_level: int, level: int) -> np.ndarray:
    """Level-``s`` position of the centres of level-``S`` voxels ``x`` (DESIGN.md half-voxel offset)."""
    return level_to_level(np.asarray(x, np.float64), grid_level, level)


def chunk_tasks(job: FieldsJob, result: Result, chunks: tuple[int, int, int]) -> list[tuple]:
    """Arguments of :func:`fields_task`, one per chunk of the image grid that meets the ROI.

    Each carries only its own elements' nodes, brightness and activity (mesh-sized slices).
    """

    u = result.displacement
    brightness = brightness_fields(result)  # per element, made once (mesh-sized)
    args = []
    grid = [range(0, n, c) for n, c in zip(job.shape0, chunks)]
    for z in grid[0]:
        for y in grid[1]:
            for x in grid[2]:
                region = tuple(slice(a, min(a + c, n)) for a, c, n in zip((z, y, x), chunks, job.shape0))
                found = _chunk_elements(job, region)
                if found is None:
                    continue  # the fill value (NaN) stands for it
                _, elements = found
                block = Block(elements)
                active = None if result.active is None else np.ascontiguousarray(
                    result.active[tuple(slice(e0, e1) for e0, e1 in elements)])
                args.append((job, tuple((r.start, r.stop) for r in region), block,
                             np.ascontiguousarray(u[(slice(None), *block.node_slices)]),
                             element_slice(brightness, block), active))
    return args


def equivalent_strain(eps: np.ndarray) -> np.ndarray:
    """Von Mises equivalent strain ``sqrt(2/3 e:e)``, ``e = eps - tr(eps)/3 I``.

    Parameters
    ----------
    eps : ndarray, shape (3, 3, ...), float64, dimensionless

    Returns
    -------
    ndarray, shape (...), float64

    Examples
    --------
    >>> eps = np.diag([0.01, -0.005, -0.005])[:, :, None]  # incompressible uniaxial strain
    >>> round(float(equivalent_strain(eps)[0]), 12)
    0.01
    """
    dev = eps - np.trace(eps)[None, None] / 3.0 * np.eye(3).reshape(3, 3, *([1] * (eps.ndim - 2)))
    return np.sqrt(2.0 / 3.0 * (dev**2).sum(axis=(0, 1)))


def fields_values(job: FieldsJob, region, block: Block, u_block: np.ndarray, brightness, active) -> np.ndarray:
    """Every channel over one region of the image grid (the body of :func:`fields_task`).

    Parameters
    ----------
    job : FieldsJob
    region : tuple of 3 (start, stop)
        Voxels of the image grid (the scan's level ``job.grid_level``) of the chunk.
    block : Block
        The result's elements the region's in-ROI voxels fall in.
    u_block : ndarray, shape (3, ez+1, ey+1, ex+1), float64, voxels of the result's level
        The result's field on the block's nodes.
    brightness : ndarray, shape (2 or 5, ez, ey, ex), or None
        :func:`chunkdic.export.correction.brightness_fields`, the block's elements.
    active : ndarray, shape (ez, ey, ex), or None
        Elements inside the specimen mask (others give NaN).

    Returns
    -------
    ndarray, shape (len(CHANNELS), nz, ny, nx), float32
        NaN outside the ROI (and in inactive elements); see the module docstring for units.
    """

    mesh, s, grid = job.mesh, job.level, job.grid_level
    ell = mesh.element_size
    shape = tuple(b - a for a, b in region)
    out = np.full((len(CHANNELS),) + shape, np.nan, np.float32)
    found = _chunk_elements(job, tuple(slice(a, b) for a, b in region))
    if found is None:
        return out
    inside, _ = found
    at = (slice(None),) + tuple(slice(lo - a, hi - a) for (lo, hi), (a, _) in zip(inside, region))
    # the block's own mesh: the same elements, numbered from the block's first one
    sub = Mesh(tuple(o + e0 * ell for o, (e0, _) in zip(mesh.origin, block.elements)), ell, block.n_elements)
    x0 = [np.arange(lo, hi) for lo, hi in inside]
    pos = [_level_positions(v, grid, s) for v in x0]
    u = sub.evaluate_grid(u_block, pos) * np.asarray(job.factor).reshape(3, 1, 1, 1)
    k = [sub.element_index(axis, p)[0] for axis, p in enumerate(pos)]
    eps = element_strain(u_block, ell, job.strain)
    per_voxel = np.ix_(*k)
    values = out[at]  # a view: the channels are computed in place
    values[0:3] = u
    values[3] = np.sqrt((u**2).sum(axis=0))
    values[4] = eps[0, 0][per_voxel]
    values[5] = equivalent_strain(eps)[per_voxel]
    if job.correction is not None and grid <= s:
        f, corrected, valid = correct_block(job.correction, block, u_block, brightness, active)
        residual = np.where(valid, f - corrected, np.nan)
        start, _ = mesh.block_core(block)
        # the level-s voxel j holding a level-S voxel v (S <= s) is v // 2^(s-S): repeat it over them
        j = [v // 2 ** (s - grid) - s0 for v, s0 in zip(x0, start)]
        values[6] = residual[np.ix_(*j)]
    elif job.correction is not None:
        values[6] = mean_abs_residual(job, block, u_block, brightness, active, inside)
    if active is not None:
        values[:, ~(active[per_voxel] > 0)] = np.nan
    return out


#: edge (voxels of the result's level) of the pieces a task corrects at a time when the image
#: grid is coarser than the result's: bounds its memory, whatever the chunk and level
RESIDUAL_PIECE = 128


def mean_abs_residual(job: FieldsJob, block: Block, u_block: np.ndarray, brightness, active, inside) -> np.ndarray:
    """Mean ``|r|`` over each coarse voxel of an image grid coarser than the result (``S > s``).

    A level-``S`` voxel ``j`` holds the level-``s`` voxels ``2^(S-s) j … 2^(S-s) (j + 1) - 1``
    per axis; its value is the mean of ``|r|`` over those of them that are in the ROI and
    valid (:func:`chunkdic.export.correction.correct_block`), NaN when none is. The absolute
    value, because a signed mean cancels (``r`` is centred on 0 wherever the match is good);
    a mean, because the image's own pyramid levels are means: level ``t`` of a level-``S``
    image then holds the mean ``|r|`` over ``2^(S+t-s)`` voxels per axis, as a level-``S+t``
    image would.

    The block's elements are corrected in pieces of at most :data:`RESIDUAL_PIECE` voxels
    per axis (whole elements), whose sums are binned separably (``np.add.reduceat``).

    Parameters
    ----------
    job : FieldsJob
    block, u_block, brightness, active
        As in :func:`fields_values`.
    inside : tuple of 3 (lo, hi)
        The level-``S`` voxels wanted, per axis.

    Returns
    -------
    ndarray, shape (hi - lo per axis), float32, grey levels of the result's level
    """
    ell, factor = job.mesh.element_size, 2 ** (job.grid_level - job.level)
    shape = tuple(hi - lo for lo, hi in inside)
    total, count = np.zeros(shape), np.zeros(shape)
    step = max(1, RESIDUAL_PIECE // ell)
    ranges = [[(a, min(a + step, n)) for a in range(0, n, step)] for n in block.n_elements]
    for rz in ranges[0]:
        for ry in ranges[1]:
            for rx in ranges[2]:
                rel = (rz, ry, rx)
                piece = Block(tuple((e0 + a, e0 + b) for (e0, _), (a, b) in zip(block.elements, rel)))
                cells = tuple(slice(a, b) for a, b in rel)
                nodes = tuple(slice(a, b + 1) for a, b in rel)
                f, corrected, valid = correct_block(
                    job.correction, piece, u_block[(slice(None), *nodes)],
                    None if brightness is None else brightness[(slice(None), *cells)],
                    None if active is None else active[cells])
                start, _ = job.mesh.block_core(piece)
                bins = [_bins(s0, n, factor, lo, hi) for s0, n, (lo, hi) in zip(start, f.shape, inside)]
                if any(b is None for b in bins):
                    continue
                take = tuple(b[0] for b in bins)
                r = np.where(valid[take], np.abs(f[take].astype(np.float64) - corrected[take]), 0.0)
                n = valid[take].astype(np.float64)
                for axis, (_, cuts, _) in enumerate(bins):
                    r = np.add.reduceat(r, cuts, axis=axis)
                    n = np.add.reduceat(n, cuts, axis=axis)
                where = np.ix_(*(b[2] for b in bins))
                total[where] += r
                count[where] += n
    with np.errstate(invalid="ignore", divide="ignore"):
        return (total / count).astype(np.float32)  # 0 / 0: no valid voxel, NaN


def _bins(start: int, n: int, factor: int, lo: int, hi: int):
    """How ``n`` fine voxels from ``start`` fall into coarse voxels ``v // factor`` of ``[lo, hi)``:
    ``(slice of the fine voxels kept, first index of each coarse voxel in it, coarse
    voxels - lo)``, or None when none falls in."""
    b = (start + np.arange(n)) // factor
    kept = np.flatnonzero((b >= lo) & (b < hi))
    if kept.size == 0:
        return None
    b = b[kept[0]:kept[-1] + 1]
    cuts = np.flatnonzero(np.r_[True, b[1:] != b[:-1]])
    return slice(int(kept[0]), int(kept[-1]) + 1), cuts, b[cuts] - lo


def fields_task(job: FieldsJob, region, block: Block, u_block, brightness, active) -> int:
    """Task: compute every channel over one chunk of the image grid and write it (the task
    owns that chunk of every channel). Returns the number of in-ROI voxels written."""
    import zarr

    data = fields_values(job, region, block, u_block, brightness, active)
    arr = zarr.open_array(store=job.out, path="0", mode="r+")
    arr[(slice(None), *(slice(a, b) for a, b in region))] = data
    return int(np.isfinite(data[0]).sum())

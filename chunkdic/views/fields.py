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
(:func:`chunkdic.views.images.write_image`, the writer shared with the corrected image).
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
- Residual: ``f̃(X) - corrected g(X + u(X))`` of :mod:`chunkdic.views.correction` (what the
  engine compared), in grey levels of the result's level, computed per task at that level.
  On a grid at least as fine as the result's (``S <= s``): the residual of the level-``s``
  voxel holding the centre, repeated (nearest). On a coarser grid (``S > s``): the mean of
  ``|r|`` over the level-``s`` voxels each level-``S`` voxel holds (:func:`mean_abs_residual`;
  a signed mean would cancel).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import config
from ..errors import InputError
from ..io import diskspace
from ..io.ngff import level_frame
from ..io.outputs import Outputs
from ..mesh import Block, Mesh, level_to_level
from ..results.result import Result
from ..results.scans import (
    as_result,
    input_paths,
    input_scan,
    input_scans,
    interpolation_of,
    level_refs,
)
from ..results.strain import DEFAULT_MEASURE, check_measure, element_strain
from ..scheduler import open_runner
from .correction import Correction, brightness_fields, correct_block, element_slice
from .images import field_levels, image_bytes, scan_frame, write_image

log = logging.getLogger(__name__)

__all__ = ["CHANNELS", "write_fields", "plan_fields", "open_fields", "open_levels", "field_levels"]

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
        :func:`chunkdic.views.correction.brightness_fields`, the block's elements.
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
    valid (:func:`chunkdic.views.correction.correct_block`), NaN when none is. The absolute
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


# --------------------------------------------------------------------------- writer


def write_fields(result, out, *, ref=None, deformed=None, residual: bool = True, units: str = "voxels",
                 levels: int | None = None, grid_level: int = 0, scheduler=None, overwrite: bool = False,
                 progress: Callable[[str, float], None] | None = None, strain: str = DEFAULT_MEASURE) -> dict:
    """Write the voxel-wise fields of a result as one OME-NGFF 0.5 image on the scan's grid.

    Parameters
    ----------
    result : Result or path
        A correlation result (any pyramid level).
    out : path
        Zarr v3 group to create: a multiscale image, arrays ``"0"`` … ``"k"``, shape
        ``(7, nz, ny, nx)`` at level 0 (the reference scan's level-``grid_level`` shape),
        float32, channels :data:`CHANNELS`; NaN outside the ROI. Level ``t`` is the 2^t mean.
    ref, deformed : path, optional
        The scans (default: the paths recorded in the result). The reference gives the
        grid (shape, scale, unit, origin); both are needed for the residual.
    residual : bool, keyword-only
        Compute the residual channel (False: it stays NaN, and the scans are only needed
        for the grid: without them the result's recorded shape and voxel size are used).
    units : {"voxels", "physical"}, keyword-only
        Displacement in level-0 voxels (default) or in the scan's unit (needs a voxel size),
        whatever ``grid_level``.
    levels : int, optional
        Pyramid levels above 0 (default: down to an edge of :data:`MIN_COARSE_EDGE`).
    grid_level : int, keyword-only
        The scan's pyramid level ``S`` whose grid the image's level 0 lies on (default 0,
        the full grid; ``S``: ``8^-S`` of its size): the fields sampled at the centres of
        the level-``S`` voxels, placed by the scan's level-``S`` scale and translation.
        The residual channel: the level-``s`` voxel's residual when ``S <= s`` (the
        result's level), the mean ``|r|`` over the voxel when ``S > s``
        (:func:`mean_abs_residual`). ``--fields-level`` of ``chunkdic export``.
    scheduler
        As in :func:`chunkdic.correlate`.
    overwrite : bool
        Replace a fields image an earlier export wrote (nothing else).
    progress : callable(str, float), optional
        ``(stage, fraction)``: ``"fields"`` then ``"level t"``.
    strain : {"green-lagrange", "small"}, keyword-only
        Measure of the ``eps_zz`` and ``eps_eq`` channels (default Green–Lagrange: zero for a
        rigid rotation); recorded in the image's ``chunkdic`` attributes (``strain_measure``).

    Returns
    -------
    dict
        ``path``, ``levels`` (shapes), ``voxels`` (in-ROI voxels of the image's level 0),
        ``windows`` (per channel label: 1st/99th percentile, min, max of the coarsest level),
        ``seconds``, ``bytes`` (the upper bound checked against the free disk, :func:`plan_fields`).

    Raises
    ------
    DiskSpaceError
        The image cannot fit the free disk (one line naming the finest ``grid_level`` that
        fits), before anything is written.

    Examples
    --------
    >>> chunkdic.write_fields("result.zarr", "fields.zarr")  # doctest: +SKIP
    >>> chunkdic.write_fields("result.zarr", "fields-4.zarr", grid_level=2)  # doctest: +SKIP
    """

    result = as_result(result)
    result.check_displacement()
    check_measure(strain)
    if units not in ("voxels", "physical"):
        raise InputError(f"units must be voxels or physical, got {units!r}")
    if levels is not None and (int(levels) != levels or levels < 0):
        raise InputError(f"levels must be a whole number >= 0, got {levels!r}")
    scans = _scans(result, ref, deformed, residual)
    f_scan = scans[0]
    shape0 = _scan_shape(result, f_scan)
    room = plan_fields(shape0, out, grid_level=grid_level, levels=levels)
    scale0, shift0, unit = scan_frame(f_scan, result.info)
    s = result.level
    if units == "physical":
        vs = result.info.get("voxel_size") or (f_scan.voxel_size if f_scan is not None else None)
        if not vs:
            raise InputError("this result has no voxel size: export fields in voxels, or give the scans a voxel size")
        factor, disp_unit = tuple(2.0**s * float(v) for v in vs), str(result.info.get("unit") or unit or "unit")
    else:
        factor, disp_unit = (2.0**s,) * 3, "level-0 voxels"
    plan = Outputs(inputs=input_paths(result, ref, deformed), overwrite=overwrite)
    entry = plan.add(out, "fields")
    frame = (*level_frame(scale0, shift0, grid_level), unit)  # the image's level 0 is the scan's level S
    with plan:
        done = _write(result, entry.work, Path(out), scans if residual else None, room["shape"], frame,
                      factor, disp_unit, room["shapes"], scheduler, progress, strain, grid_level)
    return {**done, "bytes": room["bytes"]}


def _x(shape) -> str:
    return "x".join(map(str, shape))


def _coarser_hint(shape0, grid_level: int, need: Callable, room: float) -> str:
    """The end of a refusal: the finest coarser grid whose image fits ``room`` bytes."""
    level = grid_level + 1
    while min(int(n) >> level for n in shape0) >= 1:
        shape, _, size = need(level)
        if size * diskspace.DISK_MARGIN <= room:
            return (f"--fields-level {level} (grid_level={level}, {_x(shape)} voxels) needs up to "
                    f"{diskspace.format_bytes(size)}")
        level += 1
    return "free some disk or write it to a larger one"


def _scan_shape(result: Result, f_scan) -> tuple[int, int, int]:
    """The reference scan's level-0 shape (the result's record when the scan is not at hand)."""
    return tuple(int(n) for n in (f_scan.shape(0) if f_scan is not None
                                  else result.info["input_shapes"]["reference"]))


def fields_grid(shape0, grid_level: int) -> tuple[int, int, int]:
    """The scan's level-``S`` shape (each level halves, odd voxels trimmed, as its pyramid).

    Examples
    --------
    >>> fields_grid((2048, 2048, 2000), 2)
    (512, 512, 500)
    """
    if isinstance(grid_level, bool) or int(grid_level) != grid_level or grid_level < 0:
        raise InputError(f"the fields level must be a whole number >= 0, got {grid_level!r}")
    shape = tuple(int(n) >> int(grid_level) for n in shape0)
    if min(shape) < 1:
        raise InputError(f"the fields level {grid_level} is coarser than the scan ({'x'.join(map(str, shape0))} "
                         "voxels): choose a finer one")
    return shape


def plan_fields(shape0, out, *, grid_level: int = 0, levels: int | None = None, also: int = 0) -> dict:
    """The size of a fields image and the free disk for it, refused when it cannot fit.

    Parameters
    ----------
    shape0 : tuple of 3 int
        The reference scan's level-0 shape.
    out : path
        Where the image goes (its file system's free space counts).
    grid_level, levels
        As in :func:`write_fields`.
    also : int
        Bytes that other outputs of the same command put on that file system first.

    Returns
    -------
    dict
        ``shape`` (the image's level-0 shape), ``shapes`` (every level), ``bytes`` (upper
        bound, :func:`chunkdic.views.images.image_bytes`), ``free`` (bytes), ``line`` (the
        estimate for a person).

    Raises
    ------
    DiskSpaceError
        ``bytes + also`` (with a 5 % margin) exceed the free disk: one line naming the need,
        the free space and the finest ``grid_level`` (``--fields-level``) that fits.
    """
    chunk = int(config.get("chunk-size"))

    def need(level: int) -> tuple:
        shape = fields_grid(shape0, level)
        shapes = field_levels(shape, levels)
        return shape, shapes, image_bytes(shapes, len(CHANNELS), chunk)

    shape, shapes, size = need(grid_level)
    room = diskspace.free_bytes(out)
    if (size + also) * diskspace.DISK_MARGIN > room:
        diskspace.check_disk(size + also, out, f"the fields image on the scan's level-{grid_level} grid "
                                               f"({_x(shape)} voxels x {len(CHANNELS)} channels)",
                             _coarser_hint(shape0, grid_level, need, room - also * diskspace.DISK_MARGIN))
    line = (f"{len(CHANNELS)} channels on the scan's level-{grid_level} grid ({_x(shape)} voxels, {len(shapes)} "
            f"levels): up to {diskspace.format_bytes(size)} (uncompressed), {diskspace.format_bytes(room)} free")
    return {"shape": shape, "shapes": shapes, "bytes": size, "free": room, "line": line}


def _scans(result: Result, ref, deformed, residual: bool) -> tuple:
    """The scans, opened and checked once: both when the residual needs them, else the
    reference alone, or None when it is not on disk but the result recorded its shape."""

    if residual:
        return input_scans(result, ref, deformed)
    known = (result.info.get("input_shapes") or {}).get("reference") is not None
    return input_scan(result, "reference", ref, optional=known), None


def _write(result: Result, work: Path, out: Path, scans, shape0, frame, factor, disp_unit: str, shapes,
           scheduler, progress, strain: str = DEFAULT_MEASURE, grid_level: int = 0) -> dict:
    """:func:`write_fields` into ``work`` (renamed to ``out`` by the caller); ``scans``:
    the result's scans for the residual (None: no residual)."""
    import contextlib

    t0 = time.perf_counter()
    c = int(config.get("chunk-size"))
    mesh, s = result.mesh, result.level
    meta = {"kind": "fields", "complete": False, "result": result.path, "level": s,
            "element_size": mesh.element_size, "roi_level0": [list(r) for r in roi_level0(mesh, s)],
            "channels": list(CHANNELS), "displacement_unit": disp_unit, "residual": scans is not None,
            "strain": "per element (C8 gradient at the element centre), constant over the element",
            "strain_measure": strain, "grid_level": grid_level,
            "roi": [list(r) for r in roi_on_grid(mesh, s, grid_level)],
            "residual_statistic": "mean |r| over the voxel" if grid_level > s else "r of the voxel"}
    description = (
        f"channels {', '.join(CHANNELS)}: displacement ({disp_unit}), its norm, eps_zz and the von Mises "
        f"equivalent strain ({strain} strain, per element, dimensionless), residual f - corrected g (grey levels of the "
        f"result's level; {'the mean |r| over each voxel' if grid_level > s else 'signed'}); NaN outside the ROI. "
        f"Level 0 lies on the reference scan's level-{grid_level} grid, level t is the NaN-aware mean over 2^t "
        "voxels per axis of level 0")
    with contextlib.ExitStack() as stack:
        runner = stack.enter_context(open_runner(scheduler))
        corr = None
        if scans is not None:
            f_ref, g_ref = stack.enter_context(level_refs(result, scans=scans))
            corr = Correction.of_result(result, f_ref, g_ref, interpolation_of(result))
        job = FieldsJob(mesh, s, shape0, factor, str(work), corr, strain, grid_level)
        counts, windows = write_image(
            runner, work, fields_task, chunk_tasks(job, result, tuple(min(c, n) for n in shape0)), meta=meta,
            channels=CHANNELS, shapes=shapes, chunk=c, frame=frame, description=description,
            summarize=lambda counts: {"voxels": sum(counts)}, progress=progress, stage="fields")
    seconds = time.perf_counter() - t0
    log.info("fields written to %s (%d levels, %.1f s)", out, len(shapes), seconds)
    return {"path": str(out), "levels": shapes, "voxels": sum(counts),
            "windows": dict(zip(CHANNELS, windows)), "seconds": seconds}


def open_levels(path):
    """Open an image written by :func:`write_fields`: ``(levels, attrs)``, the level arrays
    (lazily read Zarr arrays, ``(7, nz, ny, nx)``) and the group's attributes; an
    incomplete one is refused. :func:`open_fields` gives one level as an xarray Dataset."""
    import zarr

    try:
        g = zarr.open_group(str(path), mode="r")
        attrs = g.attrs.asdict()
        meta = attrs["chunkdic"]
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{path} is not a fields image ({exc.__class__.__name__})") from None
    if meta.get("kind") != "fields" or not meta.get("complete"):
        raise InputError(f"{path} is not a complete fields image")
    datasets = attrs["ome"]["multiscales"][0]["datasets"]
    return [g[d["path"]] for d in datasets], attrs


def open_fields(path, level: int = 0):
    """One level of a fields image (:func:`write_fields`) as an :class:`xarray.Dataset`.

    ``xarray.open_zarr`` cannot read the image group itself: its levels share the dimension
    names ``c, z, y, x`` with different sizes (an OME-NGFF pyramid, "conflicting sizes for
    dimension 'z'"); this opens one level, lazily (Dask, the image's chunks).

    Parameters
    ----------
    path : path
        The image (``chunkdic export RESULT --fields fields.zarr``).
    level : int
        Pyramid level of the image (0: its finest, on the scan's level-``grid_level`` grid, see
        ``attrs["chunkdic"]["grid_level"]``; ``t``: the 2^t mean).

    Returns
    -------
    xarray.Dataset
        One variable per channel (:data:`CHANNELS`: ``Uz``, ``Uy``, ``Ux``, ``|U|``, ``eps_zz``,
        ``eps_eq``, ``residual``), float32 on ``(z, y, x)``, NaN outside the ROI; coordinates
        ``z, y, x`` are the voxel centres in the scan's physical unit (OME-NGFF scale and
        translation of that level; voxels without a voxel size), ``units`` in their attributes;
        the Dataset's attributes hold the image's ``chunkdic`` metadata (result, element size,
        displacement unit, strain measure).

    Examples
    --------
    >>> ds = chunkdic.open_fields("fields.zarr")  # doctest: +SKIP
    >>> ds["eps_zz"].sel(z=500.0, method="nearest").plot()  # doctest: +SKIP
    """
    try:
        import xarray as xr
    except ImportError:
        raise ImportError("open_fields needs xarray: pip install xarray") from None
    import dask.array as da

    levels, attrs = open_levels(path)
    if int(level) != level or not 0 <= level < len(levels):
        raise InputError(f"{path} has levels 0 to {len(levels) - 1}, not {level!r}")
    level = int(level)
    ms = attrs["ome"]["multiscales"][0]
    scale, shift = [1.0] * 4, [0.0] * 4
    for t in ms["datasets"][level].get("coordinateTransformations", []):
        if t.get("type") == "scale":
            scale = [float(v) for v in t["scale"]]
        elif t.get("type") == "translation":
            shift = [float(v) for v in t["translation"]]
    axes = {a["name"]: a for a in ms.get("axes", []) if isinstance(a, dict)}
    arr = levels[level]
    data = da.from_zarr(arr)
    meta = attrs.get("chunkdic", {})
    coords = {}
    for i, name in enumerate("zyx", start=1):
        unit = axes.get(name, {}).get("unit") or "voxel"
        coords[name] = (name, shift[i] + scale[i] * np.arange(arr.shape[i]), {"units": unit})
    names = meta.get("channels") or list(CHANNELS)
    units = {"Uz": meta.get("displacement_unit"), "Uy": meta.get("displacement_unit"),
             "Ux": meta.get("displacement_unit"), "|U|": meta.get("displacement_unit"), "eps_zz": "1",
             "eps_eq": "1", "residual": "grey level"}
    data_vars = {name: (("z", "y", "x"), data[k], {"units": units.get(name) or "1"}) for k, name in enumerate(names)}
    return xr.Dataset(data_vars, coords=coords, attrs={**{k: v for k, v in meta.items() if v is not None and
                                                          isinstance(v, (str, int, float, bool))},
                                                       "level": level, "path": str(path)})


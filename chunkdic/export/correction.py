"""The corrected deformed image: what the engine compared with the reference, voxel by voxel.

A result's residual is ``r = f̃(X) - (λ g̃(X + u(X)) + μ(X))`` (paper section 3, with the
image preparation and brightness model of docs/engine.md): ``f̃``, ``g̃`` are the scans
low-passed as the engine did (:mod:`chunkdic.passes.prefilter`), ``g̃`` interpolated as the engine
did (same window reads, same kernel: :func:`chunkdic.kernels.warp.warp_block`), and ``λ``, ``μ``
the brightness the engine found (:mod:`chunkdic.method.brightness`: a gain and an offset per
element, plus a linear drift, or with ``grey_cell`` an affine offset per cell of elements,
whose slopes :func:`brightness_fields` reads back from the offsets at the element centres).
This module computes it for one block of whole elements, in a task, and is the one place
that knows how: the corrected volume of
:func:`chunkdic.export.corrected_image.write_corrected`, the cuts of :mod:`chunkdic.plot.report` and anything
else that shows ``g(X + u(X))`` go through :func:`correct_block`. The client never reads
voxels: a plane of the corrected image is assembled from the planes the tasks return.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import config
from ..method.brightness import offset_cell
from ..passes.tasks import BlockJob, LevelInputs, read_g_window, read_prepared_reference
from ..io.handles import ArrayRef
from ..kernels.blocks import voxel_xi
from ..kernels.warp import warp_block
from ..mesh import Block, Mesh
from ..results.result import Result

__all__ = ["Correction", "brightness_fields", "cell_slopes", "correct_block", "element_slice", "plane_jobs", "plane_task", "active_slice", "fill_missing_nodes", "assemble_plane", "planes"]


@dataclass(frozen=True)
class Correction:
    """Everything a task needs to correct ``g`` by a result: stores and settings, no voxels.

    Attributes
    ----------
    inputs : LevelInputs
        The scans at the result's level and the engine's image settings.
    mesh : Mesh
        The result's mesh (its level).
    drift : tuple of 3 float
        Brightness drift of the ``drift`` model, grey levels per voxel of the level along
        ``(z, y, x)`` (zeros for the other models).
    """

    inputs: LevelInputs
    mesh: Mesh
    drift: tuple[float, float, float]

    @classmethod
    def of_result(cls, result: Result, f_ref: ArrayRef, g_ref: ArrayRef, interpolation: str | None = None
                  ) -> "Correction":
        """The correction of ``result`` for the scans ``f_ref``, ``g_ref`` at its level."""
        settings = result.info.get("settings") or {}
        sigma = float(settings.get("smoothing", 0.0) or 0.0)
        grey = (result.info.get("grey_level") or {}).get("model", settings.get("grey", "none"))
        interp = interpolation or str(settings.get("interpolation", "cubic"))
        inputs = LevelInputs.for_settings(f_ref, g_ref, None, level=result.level, interpolation=interp,
                                          smoothing=sigma, grey=grey)
        drift = (result.info.get("grey_level") or {}).get("drift") or (0.0, 0.0, 0.0)
        return cls(inputs, result.mesh, tuple(float(v) for v in drift))


def fill_missing_nodes(u_block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nodes not measured (NaN: outside a specimen mask, no data) given the mean of the
    measured nodes of the block, so that the window of ``g`` and the warp stay finite.

    Returns the filled field ``(3, nz, ny, nx)`` and the per-element usability
    ``(ez, ey, ex)`` bool: an element is usable when its eight nodes were measured. The
    voxels of other elements are invalid whatever the filled values give.
    """
    known = np.isfinite(u_block).all(axis=0)
    k = known.astype(np.int8)
    usable = np.ones(tuple(n - 1 for n in known.shape), bool)
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                usable &= k[dz:dz + usable.shape[0], dy:dy + usable.shape[1], dx:dx + usable.shape[2]] > 0
    if known.all():
        return u_block, usable
    fill = u_block[:, known].mean(axis=1) if known.any() else np.zeros(3)
    return np.where(known[None], u_block, fill[:, None, None, None]), usable


def _per_voxel(per_element: np.ndarray, ell: int) -> np.ndarray:
    return np.repeat(np.repeat(np.repeat(per_element, ell, 0), ell, 1), ell, 2)


def brightness_cell(result: Result) -> int:
    """Elements per side of the cells that shared one affine brightness offset in ``result``
    (:func:`chunkdic.method.brightness.offset_cell` of its settings; 1: one offset per element)."""
    settings = result.info.get("settings") or {}
    model = (result.info.get("grey_level") or {}).get("model", settings.get("grey", "none"))
    return offset_cell(str(model), int(result.mesh.element_size), float(settings.get("grey_cell", 0) or 0))


def cell_slopes(offset: np.ndarray, cell: int, element_size: int, drift) -> np.ndarray:
    """Each element's brightness slope, read back from the offsets at the element centres.

    With affine offsets per cell of ``cell³`` elements (the ``drift`` model with
    ``grey_cell``, :func:`chunkdic.method.brightness._reduce_cells`) the offset at an element's
    centre is ``a_c + b_c · (X_e - X_c)``: two neighbours of one cell along an axis differ by
    exactly ``b_c`` times ``element_size`` there, so the cell's slope along that axis is that
    difference (the mean of every such pair, equal to round-off). Cells start at multiples of
    ``cell`` from the mesh's first element (blocks hold whole cells). A cell one element thick
    along an axis (the mesh's last, when its element count leaves one; every cell when
    ``cell`` is 1) has no pair there: its slope along that axis is ``drift``'s (the cells'
    mean slope the result reports), the one figure left.

    Parameters
    ----------
    offset : ndarray, shape (ez, ey, ex), float, grey levels
        Offset at each element's centre (``Result.brightness[1]``); non-finite values are
        left out.
    cell : int
        Elements per side of a cell (:func:`brightness_cell`).
    element_size : int
        Element edge, voxels of the result's level.
    drift : sequence of 3 float
        Mean slope (grey levels per voxel, z, y, x): where a cell has no pair.

    Returns
    -------
    ndarray, shape (3, ez, ey, ex), float64, grey levels per voxel of the level
    """
    offset = np.asarray(offset, np.float64)
    shape = offset.shape
    k = max(1, int(cell))
    n_cells = tuple(-(-n // k) for n in shape)
    index = np.ix_(*(np.arange(n) // k for n in shape))  # each element's cell
    out = np.empty((3,) + shape)
    for axis, n in enumerate(shape):
        first = [slice(None)] * 3
        second = [slice(None)] * 3
        first[axis], second[axis] = slice(0, n - 1), slice(1, n)
        diff = (offset[tuple(second)] - offset[tuple(first)]) / float(element_size)
        same = (np.arange(1, n) % k) != 0  # both elements of the pair in one cell
        ok = np.isfinite(diff) & same.reshape([-1 if a == axis else 1 for a in range(3)])
        pair_cell = [np.arange(m) // k for m in diff.shape]  # the pair's first element's cell
        linear = np.ravel_multi_index(np.ix_(*pair_cell), n_cells)
        linear = np.broadcast_to(linear, diff.shape)
        total = np.bincount(linear[ok], weights=diff[ok], minlength=int(np.prod(n_cells)))
        count = np.bincount(linear[ok], minlength=int(np.prod(n_cells)))
        per_cell = np.where(count > 0, total / np.maximum(count, 1), float(drift[axis])).reshape(n_cells)
        out[axis] = per_cell[index]
    return out


def brightness_fields(result: Result) -> np.ndarray | None:
    """The per-element brightness that :func:`correct_block` rebuilds ``μ(X)`` from.

    ``Result.brightness`` (gain, offset at the element centre) as it is for one offset per
    element (the ramp inside an element is then the result's one drift); with affine offsets
    per cell, those rows and each element's slope along z, y, x (:func:`cell_slopes`), so
    that the corrected image is the engine's model exactly, not the offsets with the cells'
    mean slope. Mesh-sized (5 float64 per element), made once on the client; tasks receive
    their elements' slice (:func:`element_slice`).

    Returns
    -------
    ndarray, shape (2, ez, ey, ex) or (5, ez, ey, ex), float64, or None (no brightness)
    """
    b = result.brightness
    cell = brightness_cell(result)
    if b is None or cell <= 1:
        return b
    drift = (result.info.get("grey_level") or {}).get("drift") or (0.0, 0.0, 0.0)
    return np.concatenate([np.asarray(b, np.float64),
                           cell_slopes(b[1], cell, result.mesh.element_size, drift)])


def correct_block(c: Correction, block: Block, u_block: np.ndarray, brightness: np.ndarray | None,
                  active: np.ndarray | None = None):
    """The prepared reference, the corrected deformed image and their validity over one block.

    Parameters
    ----------
    c : Correction
    block : Block
        Whole elements of ``c.mesh``.
    u_block : ndarray, shape (3, ez+1, ey+1, ex+1), float64, voxels
        The result's field on the block's nodes.
    brightness : ndarray, shape (2, ez, ey, ex) or (5, ez, ey, ex), float64, or None
        Gain and offset (at the element centre) per element, then (5 rows) the offset's
        slope per element along z, y, x (grey levels per voxel), else ``c.drift`` for every
        element: :func:`brightness_fields`. None: gain 1, offset 0.
    active : ndarray, shape (ez, ey, ex), or None
        The elements that took part (``Result.active``, a specimen mask): the voxels of the
        others are invalid, as are those of elements with a node not measured (NaN).

    Returns
    -------
    f : ndarray, block core shape, float32, grey levels
        The reference as the engine saw it (low-passed).
    corrected : ndarray, block core shape, float32, grey levels
        ``λ g̃(X + u(X)) + μ(X)``; NaN where ``X + u(X)`` leaves the usable part of ``g``.
    valid : ndarray, block core shape, bool
        Inside ``g``, in an element whose nodes were measured and (with ``active``) that
        took part.
    """
    ell = c.mesh.element_size
    start, shape = c.mesh.block_core(block)
    job = BlockJob(block, ell, start, shape, (0, 0, 0))
    f, _, _ = read_prepared_reference(c.inputs, start, shape, halo=0)
    u_block, usable = fill_missing_nodes(np.asarray(u_block, np.float64))
    if active is not None:
        usable &= np.asarray(active) > 0
    if not usable.any():
        return np.asarray(f, np.float32), np.full(shape, np.nan, np.float32), np.zeros(shape, bool)
    g, g_origin = read_g_window(c.inputs, job, u_block)
    if g is None:
        return np.asarray(f, np.float32), np.full(shape, np.nan, np.float32), np.zeros(shape, bool)
    warped, valid = warp_block(ell, u_block, start, shape, g, g_origin, c.inputs.g.shape,
                               interpolation=c.inputs.interpolation, prefiltered=True,
                               margin=c.inputs.g_margin)
    if not usable.all():
        valid = valid & _per_voxel(usable, ell)
    if brightness is not None:
        # per voxel: the element's gain and centre offset, plus slope · (X - X_e), the slope
        # the element's own (affine offsets per cell) or the result's one drift
        rows = [np.where(np.isfinite(b), b, 0.0) for b in brightness]
        warped = _per_voxel(rows[0], ell) * warped + _per_voxel(rows[1], ell)
        local = (voxel_xi(ell) - 0.5) * ell  # X - X_e inside an element, voxels
        for axis, n in enumerate(block.n_elements):
            along = np.tile(local, n).reshape([-1 if a == axis else 1 for a in range(3)])
            if len(rows) > 2:
                warped += _per_voxel(rows[2 + axis], ell) * along
            elif c.drift[axis]:
                warped += c.drift[axis] * along
    warped = np.where(valid, warped, np.nan)
    return np.asarray(f, np.float32), np.asarray(warped, np.float32), valid


def element_slice(per_element: np.ndarray | None, block: Block) -> np.ndarray | None:
    """The block's elements of a per-element array ``(k, ez, ey, ex)`` (None stays None)."""
    if per_element is None:
        return None
    return np.ascontiguousarray(per_element[(slice(None), *(slice(e0, e1) for e0, e1 in block.elements))])


def active_slice(result: Result, block: Block) -> np.ndarray | None:
    """The block's elements of ``result.active`` (the specimen mask's elements; None without a mask)."""
    if result.active is None:
        return None
    return np.ascontiguousarray(result.active[tuple(slice(e0, e1) for e0, e1 in block.elements)])


# --------------------------------------------------------------------------- planes


def plane_jobs(mesh: Mesh, normal: int, index: int, elements_per_block: int) -> list[Block]:
    """Blocks one element thick along ``normal`` that hold the plane ``index`` (level voxels)."""
    e = (index - mesh.origin[normal]) // mesh.element_size
    if not 0 <= e < mesh.shape[normal]:
        raise ValueError(f"plane {index} is outside the ROI along axis {normal}")
    out = []
    for blk in mesh.blocks(elements_per_block):
        if blk.elements[normal][0] <= e < blk.elements[normal][1]:
            els = list(blk.elements)
            els[normal] = (e, e + 1)
            out.append(Block(tuple(els)))
    return out


def plane_task(c: Correction, block: Block, u_block: np.ndarray, brightness: np.ndarray | None,
               normal: int, index: int, active: np.ndarray | None = None) -> tuple[Block, dict[str, np.ndarray]]:
    """Task: one block's share of a plane: ``f`` raw and prepared, ``g`` raw, corrected ``g``.

    Returns the block and 2-D float32 arrays (the block's extent along the two other axes).
    """
    start, shape = c.mesh.block_core(block)
    f_prep, corrected, valid = correct_block(c, block, u_block, brightness, active)
    k = index - start[normal]
    take = tuple(k if a == normal else slice(None) for a in range(3))
    region = tuple(slice(index, index + 1) if a == normal else slice(s, s + n)
                   for a, (s, n) in enumerate(zip(start, shape)))
    planes = {"reference": c.inputs.f.read(region).astype(np.float32).squeeze(normal),
              "prepared": f_prep[take], "corrected": np.where(valid[take], corrected[take], np.nan)}
    g_region = tuple(slice(max(r.start, 0), min(r.stop, n)) for r, n in zip(region, c.inputs.g.shape))
    g_plane = np.full([r.stop - r.start for r in region], np.nan, np.float32)
    if all(r.stop > r.start for r in g_region):
        dst = tuple(slice(r.start - q.start, r.stop - q.start) for r, q in zip(g_region, region))
        g_plane[dst] = c.inputs.g.read(g_region)
    planes["deformed"] = g_plane.squeeze(normal)
    return block, planes


def assemble_plane(c: Correction, normal: int, parts) -> dict[str, np.ndarray]:
    """The ROI plane from the ``(block, planes)`` of :func:`plane_task` (any order)."""
    others = [a for a in range(3) if a != normal]
    ell = c.mesh.element_size
    full = tuple(c.mesh.shape[a] * ell for a in others)
    out: dict[str, np.ndarray] = {}
    for block, planes in parts:
        at = tuple(slice(block.elements[a][0] * ell, block.elements[a][1] * ell) for a in others)
        for name, img in planes.items():
            out.setdefault(name, np.full(full, np.nan, np.float32))[at] = img
    return out


def planes(result: Result, f_ref: ArrayRef, g_ref: ArrayRef, normal: int, index: int, runner, *,
           interpolation: str | None = None) -> dict[str, np.ndarray]:
    """One ROI plane of the reference, the deformed scan and the corrected image, from tasks.

    Parameters
    ----------
    result : Result
    f_ref, g_ref : ArrayRef
        The scans at the result's level.
    normal : int
        Axis normal to the plane (0 = z, 1 = y, 2 = x).
    index : int
        Plane index along ``normal``, voxels of the level, inside the ROI.
    runner
        Where the tasks run (:func:`chunkdic.scheduler.open_runner`).

    Returns
    -------
    dict of str to ndarray, 2-D (the two other axes over the ROI), float32, grey levels
        ``reference`` and ``deformed`` (raw, NaN where the plane leaves ``g``), ``prepared``
        (the reference as the engine saw it), ``corrected`` (NaN where invalid); the residual
        is ``prepared - corrected``.
    """
    c = Correction.of_result(result, f_ref, g_ref, interpolation)
    m = max(1, int(config.get("chunk-size")) // c.mesh.element_size)
    u = result.displacement
    brightness = brightness_fields(result)
    args = [(c, blk, np.ascontiguousarray(u[(slice(None), *blk.node_slices)]),
             element_slice(brightness, blk), normal, index, active_slice(result, blk))
            for blk in plane_jobs(c.mesh, normal, index, m)]
    return assemble_plane(c, normal, runner.map_unordered(plane_task, args))

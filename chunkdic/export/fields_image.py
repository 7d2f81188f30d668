"""Writing the voxel-wise fields of a result: one OME-NGFF 0.5 image on the scan's grid.

:func:`write_fields` turns a result (a nodal field on a mesh of some pyramid level) into
volumes a viewer lays over the scan with no code: the channels of
:data:`~chunkdic.export.voxel_values.CHANNELS` as one multiscale OME-NGFF 0.5 image (axes
``c, z, y, x``) on the reference scan's full level-0 grid, or on its level-``S`` grid
(``grid_level=S``, ``export --fields-level S``), with its scale, unit and origin. Before
anything is written, the image's size (every chunk stored whole, uncompressed: an upper
bound) is compared with the free disk of where it goes (:func:`plan_fields`); the chunks
are written by tasks (:func:`chunkdic.export.voxel_values.fields_task`) through the image
writer shared with the corrected image (:func:`chunkdic.export.images.write_image`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path


from .. import config
from ..errors import InputError
from ..io import diskspace
from ..io.ngff import level_frame
from ..io.outputs import Outputs
from ..results.result import Result
from ..results.scans import (
    as_result,
    input_paths,
    input_scan,
    input_scans,
    interpolation_of,
    level_refs,
)
from ..results.strain import DEFAULT_MEASURE, check_measure
from ..scheduler import open_runner
from .correction import Correction
from .images import field_levels, image_bytes, scan_frame, write_image
from .voxel_values import CHANNELS, FieldsJob, chunk_tasks, fields_task, roi_level0, roi_on_grid

log = logging.getLogger(__name__)

__all__ = ["write_fields", "plan_fields"]


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
        bound, :func:`chunkdic.export.images.image_bytes`), ``free`` (bytes), ``line`` (the
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

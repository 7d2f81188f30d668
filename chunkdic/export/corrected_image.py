"""The corrected deformed image and the residual of a result, as an OME-NGFF image on the scan's grid.

One idea: :func:`write_corrected` writes the deformed scan corrected by the measured field,
``g(X + u(X))``, and the residual ``r = f(X) - g(X + u(X))`` as the two channels
(``corrected``, ``residual``) of one OME-NGFF 0.5 multiscale image (axes ``c, z, y, x``)
on the reference scan's grid **at the result's level** ``s``: level 0 of the image has the
shape of the scan's level ``s``, its scale ``voxel_size * 2^s`` and translation
``origin + voxel_size (2^s - 1) / 2`` (the scan's own metadata for that level), so a
viewer lays it exactly over the scan; NaN outside the ROI. Writing at level ``s`` rather
than repeating onto level 0 (as the fields image does) keeps what was computed, in the
grey levels the engine compared (level-``s`` sums), at ``8^-s`` of the storage.

Chunk by chunk: one task per chunk of the level-``s`` grid that meets the ROI; it corrects
the elements its chunk touches and writes that chunk of both channels (it owns it). The
pyramid levels ``1..k`` are NaN-aware 2×2×2 means by tasks, the contrast windows come
from a bounded sample read by tasks (:func:`chunkdic.export.images.write_image`, the writer
shared with the fields image); arrays created first, marked complete last (shared/DESIGN.md, "Out-of-core shape"; paper section 5.3, Figs. 6-8).
:func:`open_corrected` reads the ROI back.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .. import config
from ..errors import InputError
from ..io import diskspace
from ..io.ngff import level_frame
from ..io.outputs import Outputs
from ..mesh import Block, Mesh
from ..results.result import Result
from ..results.scans import (
    as_result,
    input_paths,
    input_scans,
    interpolation_of,
    level_refs,
)
from ..scheduler import open_runner
from .correction import (
    Correction,
    active_slice,
    brightness_fields,
    correct_block,
    element_slice,
)
from .images import field_levels, image_bytes, scan_frame, write_image

log = logging.getLogger(__name__)

__all__ = ["CORRECTED_CHANNELS", "write_corrected", "plan_corrected", "open_corrected", "corrected_task"]

#: channel labels of the corrected image, in order
CORRECTED_CHANNELS = ("corrected", "residual")


def chunk_block(mesh: Mesh, region) -> Block | None:
    """The elements a level-``s`` chunk's in-ROI voxels fall in (None: the chunk misses the ROI).

    Parameters
    ----------
    mesh : Mesh
        The result's mesh (voxels of its level).
    region : tuple of 3 (start, stop)
        The chunk, voxels of the level.
    """
    ell, elements = mesh.element_size, []
    for (a, b), r, o in zip(region, mesh.roi, mesh.origin):
        lo, hi = max(a, r.start), min(b, r.stop)
        if lo >= hi:
            return None
        elements.append(((lo - o) // ell, (hi - 1 - o) // ell + 1))
    return Block(tuple(elements))


def corrected_task(c: Correction, region, block: Block, u_block: np.ndarray, brightness, out_path: str,
                   active=None):
    """Task: the corrected image and the residual over one chunk, written to that chunk.

    Parameters
    ----------
    c : Correction
    region : tuple of 3 (start, stop)
        The chunk, voxels of the result's level (the task owns it in both channels).
    block : Block
        The elements the chunk's in-ROI voxels fall in (:func:`chunk_block`).
    u_block : ndarray, shape (3, ez+1, ey+1, ex+1), float64, voxels of the result's level
    brightness : ndarray, shape (2 or 5, ez, ey, ex), or None
    out_path : str
        The image group (its level-0 array ``"0"``, shape ``(2, nz, ny, nx)``).
    active : ndarray, shape (ez, ey, ex), or None
        The block's elements that took part (a specimen mask): NaN and not counted elsewhere.

    Returns
    -------
    tuple
        ``(Σ r², n_valid, n_excluded, min f̃, max f̃)`` over the chunk's in-ROI voxels
        (float64 sums; ``f̃`` the reference as the engine saw it).
    """
    import zarr

    f, corrected, valid = correct_block(c, block, u_block, brightness, active)
    start, _ = c.mesh.block_core(block)
    inside = [(max(a, r.start), min(b, r.stop)) for (a, b), r in zip(region, c.mesh.roi)]
    take = tuple(slice(lo - s0, hi - s0) for (lo, hi), s0 in zip(inside, start))
    put = tuple(slice(lo - a, hi - a) for (lo, hi), (a, _) in zip(inside, region))
    f, corrected, valid = f[take], corrected[take], valid[take]
    data = np.full((2,) + tuple(b - a for a, b in region), np.nan, np.float32)
    data[(0, *put)] = corrected
    data[(1, *put)] = np.where(valid, f - corrected, np.nan)
    zarr.open_array(store=out_path, path="0", mode="r+")[(slice(None), *(slice(a, b) for a, b in region))] = data
    r = (f - corrected)[valid].astype(np.float64)
    # the grey range over every in-ROI voxel, as the engine's gap (chunkdic.kernels.m)
    return float(r @ r), int(valid.sum()), int(valid.size - valid.sum()), float(f.min()), float(f.max())


def write_corrected(result, out, *, ref=None, deformed=None, interpolation: str | None = None,
                    levels: int | None = None, scheduler=None, overwrite: bool = False,
                    progress: Callable[[float], None] | None = None) -> dict:
    """Write the corrected deformed image and the residual as an OME-NGFF image on the scan's grid.

    Parameters
    ----------
    result : Result or path
        A correlation result (any pyramid level ``s``).
    out : path
        Zarr v3 group to create: an OME-NGFF 0.5 multiscale image, arrays ``"0"`` … ``"k"``,
        axes ``c, z, y, x``, float32, channels :data:`CORRECTED_CHANNELS`. Level 0 has the
        reference scan's level-``s`` shape and frame (scale ``voxel_size * 2^s``, translation
        ``origin + voxel_size (2^s - 1) / 2``); grey levels of level ``s``; NaN outside the ROI
        and where ``X + u(X)`` leaves the deformed scan. Level ``t`` is the NaN-aware 2^t mean.
    ref, deformed : path or array, optional
        The scans (default: the paths recorded in the result).
    interpolation : {"cubic", "linear"}, optional
        Interpolation of ``g`` (default: the result's).
    levels : int, optional
        Pyramid levels above 0 (default: down to an edge of 8 voxels).
    scheduler
        As in :func:`chunkdic.correlate`.
    overwrite : bool
        Replace a corrected image an earlier export wrote (nothing else).
    progress : callable(float), optional
        Fraction of level-0 chunks done.

    Returns
    -------
    dict
        ``path``, ``gap`` (matching gap of paper section 5.1 over the valid voxels, which
        equals the result's ``final_gap`` up to float round-off), ``valid`` and ``excluded``
        voxel counts, ``levels`` (shapes).

    References
    ----------
    Paper sections 3 ("corrected deformed image") and 5.3 (mid-plane cuts, Figs. 6-8).

    Examples
    --------
    >>> chunkdic.write_corrected("result.zarr", "corrected.zarr")  # doctest: +SKIP
    """
    result = as_result(result)
    interpolation = interpolation or interpolation_of(result)
    if interpolation not in ("cubic", "linear"):
        raise InputError(f"interpolation must be cubic or linear, got {interpolation!r}")
    if levels is not None and (int(levels) != levels or levels < 0):
        raise InputError(f"levels must be a whole number >= 0, got {levels!r}")
    out = Path(out)
    plan = Outputs(inputs=input_paths(result, ref, deformed), overwrite=overwrite)
    entry = plan.add(out, "corrected")
    scans = input_scans(result, ref, deformed)  # every input checked before anything is written
    plan_corrected(scans[0].shape(0), result.level, out, levels=levels)  # and the free disk
    with plan:
        return _write_corrected(result, entry.work, out, scans, interpolation, levels, scheduler, progress)


def plan_corrected(shape0, level: int, out, *, levels: int | None = None, also: int = 0) -> dict:
    """The size of a corrected image and the free disk for it, refused when it cannot fit.

    The image lies on the scan's grid at the result's level ``s`` (what the engine compared,
    voxel for voxel): ``2 x 8^-s`` of the scan's level-0 voxels, float32, plus its pyramid.
    No coarser grid is offered: a mean of the corrected image over coarse voxels is what the
    image's own pyramid levels hold; a coarse look at the residual is ``export --fields
    --fields-level S`` (the mean ``|r|``), which the refusal names.

    Parameters
    ----------
    shape0 : tuple of 3 int
        The reference scan's level-0 shape.
    level : int
        The result's level ``s``.
    out : path
        Where the image goes.
    levels : int, optional
        As in :func:`write_corrected`.
    also : int
        Bytes other outputs of the same command put on that file system first.

    Returns
    -------
    dict
        ``shape``, ``shapes``, ``bytes`` (upper bound, uncompressed), ``free``, ``line``.

    Raises
    ------
    DiskSpaceError
        One line: the need, the free space, and what to do.
    """
    shape = tuple(int(n) >> int(level) for n in shape0)
    shapes = field_levels(shape, levels)
    size = image_bytes(shapes, len(CORRECTED_CHANNELS), int(config.get("chunk-size")))
    room = diskspace.free_bytes(out)
    if (size + also) * diskspace.DISK_MARGIN > room:
        diskspace.check_disk(size + also, out, f"the corrected image at the result's level {level} "
                                               f"({'x'.join(map(str, shape))} voxels x {len(CORRECTED_CHANNELS)} "
                                               "channels)",
                             "free some disk or write it to a larger one; --fields with --fields-level S holds "
                             "the residual (mean |r|) on a coarser grid")
    line = (f"{len(CORRECTED_CHANNELS)} channels on the scan's level-{level} grid ({'x'.join(map(str, shape))} "
            f"voxels, {len(shapes)} levels): up to {diskspace.format_bytes(size)} (uncompressed), "
            f"{diskspace.format_bytes(room)} free")
    return {"shape": shape, "shapes": shapes, "bytes": size, "free": room, "line": line}


def _write_corrected(result: Result, work: Path, out: Path, scans, interpolation: str, levels, scheduler,
                     progress) -> dict:
    """:func:`write_corrected` into ``work`` (renamed to ``out`` by the caller); ``scans``:
    the result's reference and deformed scans, opened and checked."""

    mesh = result.mesh
    s = result.level
    c = int(config.get("chunk-size"))
    u = result.displacement
    scale0, shift0, unit = scan_frame(scans[0], result.info)
    # the image's level 0 is the scan's level s: its frame
    frame = (*level_frame(scale0, shift0, s), unit)
    description = (f"channels corrected (gain * g~(X + u(X)) + offset) and residual (f~ - corrected), grey "
                   f"levels of pyramid level {s} (2^{s} sums); NaN outside the ROI. Level 0 lies on the "
                   f"reference scan's level {s}; level t is the NaN-aware mean over 2^t voxels per axis")
    level0 = None if progress is None else (lambda stage, f: progress(f) if stage == "corrected" else None)
    # the runner first: with a cluster, missing levels are then written to scratch by its
    # workers, not by the client (as crosscheck and the engine do)
    with open_runner(scheduler) as runner, level_refs(result, scans=scans) as (f_ref, g_ref):
        corr = Correction.of_result(result, f_ref, g_ref, interpolation)
        shape = tuple(int(n) for n in f_ref.shape)
        meta = {
            "kind": "corrected", "complete": False, "result": result.path, "level": s,
            "roi": [[r.start, r.stop] for r in mesh.roi], "element_size": mesh.element_size,
            "interpolation": interpolation, "channels": list(CORRECTED_CHANNELS),
            "voxel_size": result.info.get("voxel_size"), "unit": result.info.get("unit"),
            "smoothing": corr.inputs.sigma, "grey_level": corr.inputs.grey,
            "description": "corrected = gain * g~(X + u(X)) + offset(X), residual = f~(X) - corrected over the "
                           "ROI, with f~, g~ the scans low-passed as the engine did and the brightness it found "
                           "(chunkdic.export.correction); image level 0 is the reference scan's level `level` (same "
                           "shape and frame), NaN outside the ROI; `roi` in voxels of that level",
        }
        brightness = brightness_fields(result)  # per element, made once (mesh-sized)
        args = []
        for z in range(0, shape[0], c):
            for y in range(0, shape[1], c):
                for x in range(0, shape[2], c):
                    region = tuple((a, min(a + c, n)) for a, n in zip((z, y, x), shape))
                    blk = chunk_block(mesh, region)
                    if blk is not None:  # a chunk outside the ROI keeps the fill value (NaN)
                        args.append((corr, region, blk, np.ascontiguousarray(u[(slice(None), *blk.node_slices)]),
                                     element_slice(brightness, blk), str(work), active_slice(result, blk)))
        shapes = field_levels(shape, levels)
        write_image(runner, work, corrected_task, args, meta=meta, channels=CORRECTED_CHANNELS, shapes=shapes,
                    chunk=c, frame=frame, description=description, summarize=_gap, progress=level0,
                    stage="corrected")
    log.info("corrected image and residual written to %s (gap %.4g)", out, meta["gap"])
    return {"path": str(out), "gap": meta["gap"], "valid": meta["valid_voxels"], "excluded": meta["excluded_voxels"],
            "levels": shapes}


def _gap(results: list) -> dict:
    """The matching gap (paper 5.1) and voxel counts from the tasks' ``(Σ r², n_valid,
    n_excluded, min f̃, max f̃)`` (:func:`corrected_task`)."""
    ssr = sum(r[0] for r in results)
    n_valid, n_bad = sum(r[1] for r in results), sum(r[2] for r in results)
    fmin, fmax = min((r[3] for r in results), default=math.inf), max((r[4] for r in results), default=-math.inf)
    gap = math.sqrt(ssr / n_valid) / (fmax - fmin) if n_valid and fmax > fmin else math.nan
    return {"gap": gap, "valid_voxels": n_valid, "excluded_voxels": n_bad}


def open_corrected(path):
    """Open a corrected image written by :func:`write_corrected`.

    Returns
    -------
    corrected, residual : dask.array.Array, shape ROI shape ``(Lz, Ly, Lx)``, float32
        Lazily read over the ROI (``attrs["roi"]``, voxels of the result's level); voxel
        ``(i, j, k)`` is ROI start + ``(i, j, k)`` of that level.
    attrs : dict
        ``attrs["chunkdic"]`` of the group.

    An incomplete group is refused. Groups of the earlier layout (arrays ``corrected`` and
    ``residual`` of the ROI's shape) are read too.
    """
    import dask.array as da
    import zarr

    try:
        g = zarr.open_group(str(path), mode="r")
        meta = dict(g.attrs["chunkdic"])
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{path} is not a corrected-image group ({exc.__class__.__name__})") from None
    if not meta.get("complete"):
        raise InputError(f"{path} is incomplete (the run that wrote it was interrupted)")
    if "corrected" in g:  # the layout before the OME-NGFF image: ROI-shaped arrays
        return da.from_zarr(g["corrected"]), da.from_zarr(g["residual"]), meta
    roi = tuple(slice(a, b) for a, b in meta["roi"])
    level0 = da.from_zarr(g["0"])
    return level0[(0, *roi)], level0[(1, *roi)], meta

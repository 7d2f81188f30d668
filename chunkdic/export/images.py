"""The float images chunkdic writes for viewers: one writer, their pyramid and frame.

Used by the fields image (:mod:`chunkdic.export.fields_image`) and the corrected image
(:mod:`chunkdic.export.corrected_image`). :func:`write_image` writes one OME-NGFF 0.5 multi-channel
image chunk by chunk in tasks: level 0 by the caller's task (one per chunk, writing that
chunk of every channel), coarser levels as NaN-aware 2×2×2 means written one chunk of one
channel per task (:func:`build_mean_levels`), a contrast window per channel from a bounded
sample read by tasks (:func:`chunkdic.io.display.windows`), and the metadata last, placing
level 0 on the reference scan's grid (:func:`scan_frame`; same scale, unit, origin) with
:func:`chunkdic.io.ngff.image_attrs`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..io.display import windows as channel_windows
from ..io.ngff import image_attrs
from ..io.ownership import final_name
from ..io.store import compressors

#: the coarsest pyramid level keeps every axis at least this long (voxels)
MIN_COARSE_EDGE = 8
#: coarse planes a pyramid task computes at a time (bounds its memory)
COARSEN_SLAB = 16


def coarsen_task(out: str, level: int, region, channel: int) -> None:
    """Task: one chunk of one channel of level ``level``, the NaN-aware 2×2×2 mean of
    level ``level - 1``.

    A coarse voxel is NaN only where its 8 fine voxels all are, so the ROI keeps its
    extent on every level; means (not sums) keep the values of level 0. The task owns
    that chunk (chunks are ``(1, c, c, c)``) and reads the finer level in slabs of
    :data:`COARSEN_SLAB` coarse planes, so its memory stays a few chunk-sizes whatever
    the chunk edge.
    """
    import zarr

    fine = zarr.open_array(store=out, path=str(level - 1), mode="r")
    dest = zarr.open_array(store=out, path=str(level), mode="r+")
    (z0, z1), (y0, y1), (x0, x1) = region
    result = np.empty((z1 - z0, y1 - y0, x1 - x0), np.float32)
    for a in range(z0, z1, COARSEN_SLAB):
        b = min(a + COARSEN_SLAB, z1)
        block = np.asarray(fine[channel, 2 * a:2 * b, 2 * y0:2 * y1, 2 * x0:2 * x1], np.float32)
        block = block.reshape(b - a, 2, y1 - y0, 2, x1 - x0, 2)
        finite = np.isfinite(block)
        total = np.where(finite, block, 0.0).sum(axis=(1, 3, 5), dtype=np.float64)
        count = finite.sum(axis=(1, 3, 5))
        # an all-NaN cell stays NaN (0 / 0); np.errstate is thread-local, warnings filters are not
        with np.errstate(invalid="ignore", divide="ignore"):
            result[a - z0:b - z0] = total / count
    dest[channel, z0:z1, y0:y1, x0:x1] = result


def build_mean_levels(runner, out: str, shapes, n_channels: int, chunk: int, progress=None) -> None:
    """Fill levels ``1..k`` of the image ``out`` (arrays ``"1"``…, created beforehand with
    chunks ``(1, chunk, chunk, chunk)``), level by level, with :func:`coarsen_task`.

    One task per chunk and channel, so that a level of a few chunks still keeps every core
    busy; ``progress(stage, fraction)`` with stage ``"level t"``.
    """
    for t in range(1, len(shapes)):
        cs = tuple(min(chunk, n) for n in shapes[t])
        regions = [((z, min(z + cs[0], shapes[t][0])), (y, min(y + cs[1], shapes[t][1])),
                    (x, min(x + cs[2], shapes[t][2])))
                   for z in range(0, shapes[t][0], cs[0]) for y in range(0, shapes[t][1], cs[1])
                   for x in range(0, shapes[t][2], cs[2])]
        tasks = [(str(out), t, r, ch) for r in regions for ch in range(n_channels)]
        for done, _ in enumerate(runner.map_unordered(coarsen_task, tasks), 1):
            if progress is not None:
                progress(f"level {t}", done / len(tasks))


def field_levels(shape0, levels: int | None = None) -> list[tuple[int, int, int]]:
    """Shapes of the image's levels: level ``t`` is level ``t - 1`` halved (odd voxels
    trimmed, as the scans' pyramid). ``levels=None``: as many as keep every axis at least
    :data:`MIN_COARSE_EDGE` long."""
    shapes = [tuple(int(n) for n in shape0)]
    while levels is None or len(shapes) <= levels:
        nxt = tuple(n // 2 for n in shapes[-1])
        if levels is None and min(nxt) < MIN_COARSE_EDGE or min(nxt) < 1:
            break
        shapes.append(nxt)
    return shapes


def image_bytes(shapes, n_channels: int, chunk: int) -> int:
    """Bytes an image of :func:`write_image` takes at most: every chunk of every level and
    channel stored whole and uncompressed (float32; a chunk left at the fill value is not
    stored and compression only shrinks the rest, so this is an upper bound). The pyramid
    adds at most 1/7 to level 0 (``8/7`` in all).

    Examples
    --------
    >>> image_bytes([(256, 256, 256), (128, 128, 128)], 7, 128) / 2**20  # 7 x 64 MiB + 7 x 8 MiB
    504.0
    """
    total = 0
    for shape in shapes:
        stored = 1
        for n in shape:
            c = min(chunk, n)
            stored *= -(-n // c) * c  # edge chunks are stored whole
        total += n_channels * stored * 4
    return total


# --------------------------------------------------------------------------- metadata


def scan_frame(scan, info: dict) -> tuple[list[float], list[float], str | None]:
    """Level-0 ``scale``, ``translation`` and unit of the reference scan's OME-NGFF metadata
    (a scan without it: its voxel size, else the result's, else 1 voxel; origin 0)."""
    if scan is not None and scan.path:
        try:
            import zarr

            attrs = zarr.open_group(scan.path, mode="r").attrs.asdict()
            m = ((attrs.get("ome") or {}).get("multiscales") or attrs.get("multiscales"))[0]
            scale, shift = [1.0] * 3, [0.0] * 3
            for t in m["datasets"][0].get("coordinateTransformations", []):
                if t.get("type") == "scale":
                    scale = [float(v) for v in t["scale"][-3:]]
                elif t.get("type") == "translation":
                    shift = [float(v) for v in t["translation"][-3:]]
            units = {a.get("unit") for a in m.get("axes", [])[-3:] if isinstance(a, dict)}
            return scale, shift, (units.pop() if len(units) == 1 else None)
        except Exception:  # noqa: BLE001 - not an NGFF group: fall back to the voxel size
            pass
    vs = getattr(scan, "voxel_size", None) or info.get("voxel_size")
    unit = getattr(scan, "unit", None) or info.get("unit")
    return ([float(v) for v in vs] if vs else [1.0] * 3), [0.0] * 3, (unit if vs else None)


def image_name(work) -> str:
    """The name an image staged at ``work`` will have once in place: the CLI stages all
    its outputs and calls the writer on its staged path, which stages again (two partial
    tags)."""
    name, prev = Path(work).name, None
    while name != prev:
        name, prev = final_name(name), name
    return name


# --------------------------------------------------------------------------- writer


def write_image(runner, work, task: Callable, args: list, *, meta: dict, channels, shapes, chunk: int, frame,
                description: str, summarize: Callable[[list], dict] | None = None,
                progress: Callable[[str, float], None] | None = None, stage: str = "level 0") -> tuple[list, list]:
    """Write one OME-NGFF 0.5 multi-channel float image for viewers, chunk by chunk in tasks.

    In order: the group ``work`` with ``attrs["chunkdic"] = meta`` (``complete`` false) and
    its level arrays ``"0"``…``"k"`` (float32, NaN fill, chunks ``(1, chunk, chunk, chunk)``,
    axes ``c, z, y, x``); level 0 by ``task(*a)`` for every ``a`` in ``args`` (each task
    writes the chunk it owns, in every channel, and returns what ``summarize`` reads); the
    mean levels (:func:`build_mean_levels`); a contrast window per channel from the
    coarsest level (:func:`chunkdic.io.display.windows`: a bounded sample, read by tasks);
    last, ``meta`` updated with ``summarize(results)`` and ``complete = True`` and the
    ``ome`` attributes (:func:`chunkdic.io.ngff.image_attrs`).

    Parameters
    ----------
    runner
        A runner of :mod:`chunkdic.scheduler` (open: the caller's inputs live in it).
    work : path
        The group to create (a staged path: its metadata names the final one, :func:`image_name`).
    task : callable
        The level-0 task.
    args : list of tuple
        Its arguments, one tuple per chunk that holds data (the others keep the fill, NaN).
    meta : dict
        The ``chunkdic`` attributes (``kind`` …); updated in place.
    channels : sequence of str
        Channel labels, in order.
    shapes : list of tuple of 3 int
        The levels' shapes ``(nz, ny, nx)`` (:func:`field_levels`).
    chunk : int
        Chunk edge (voxels).
    frame : tuple
        ``(scale0, shift0, unit)`` of the image's level 0 (:func:`scan_frame`,
        :func:`chunkdic.io.ngff.level_frame`).
    description : str
        What the channels hold (the NGFF ``metadata.description``).
    summarize : callable(list) -> dict, optional
        Extra ``chunkdic`` attributes from the tasks' results.
    progress : callable(str, float), optional
        ``(stage, fraction)``: ``stage`` for level 0, then ``"level t"``.
    stage : str
        The name of the level-0 stage in ``progress``.

    Returns
    -------
    results : list
        The level-0 tasks' results (in completion order).
    windows : list of (start, end, min, max)
        Per channel.
    """
    import zarr

    root = zarr.open_group(str(work), mode="w", zarr_format=3)
    root.attrs["chunkdic"] = meta
    for t, shape in enumerate(shapes):
        root.create_array(str(t), shape=(len(channels),) + tuple(shape),
                          chunks=(1,) + tuple(min(chunk, n) for n in shape), dtype="float32",
                          fill_value=float("nan"), compressors=compressors("float32"),
                          dimension_names=("c", "z", "y", "x"))
    results = []
    for done, r in enumerate(runner.map_unordered(task, args), 1):
        results.append(r)
        if progress is not None:
            progress(stage, done / len(args))
    build_mean_levels(runner, str(work), shapes, len(channels), chunk, progress)
    found = channel_windows(str(work), str(len(shapes) - 1), channels=range(len(channels)), runner=runner)
    wins = [tuple(w) if w is not None else (0.0, 1.0, 0.0, 1.0) for w in found]  # an all-NaN channel: (0, 1)
    meta.update(summarize(results) if summarize is not None else {})
    meta["complete"] = True
    scale0, shift0, unit = frame
    root = zarr.open_group(str(work), mode="r+")
    root.update_attributes({"chunkdic": meta, "ome": image_attrs(image_name(work), scale0, shift0, unit,
                                                                 len(shapes), channels, wins, description)})
    return results, wins

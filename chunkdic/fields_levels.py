"""The pyramid and OME-NGFF metadata of the float images chunkdic writes for viewers.

Used by the fields image (:mod:`chunkdic.fields_export`) and the corrected image
(:mod:`chunkdic.corrected`): coarser levels are NaN-aware 2×2×2 means written one chunk
of one channel per task (:func:`build_mean_levels`); the metadata places level 0 on the
reference scan's grid (same scale, unit, origin) and gives each channel a contrast window
from the coarsest level.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .mesh import level0_position
from .ownership import final_name

#: channel labels of the image, in order (``|U|`` is the displacement's norm)
CHANNELS = ("Uz", "Uy", "Ux", "|U|", "eps_zz", "eps_eq", "residual")
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


def level_frame(scale0, shift0, level: int) -> tuple[list[float], list[float]]:
    """Scale and translation of pyramid level ``level`` of a grid whose level 0 has
    ``scale0``, ``shift0``: ``scale0 * 2^s`` and ``shift0 + scale0 (2^s - 1) / 2``
    (the voxel-centre offset of shared/DESIGN.md)."""
    f = 2**int(level)
    return [v * f for v in scale0], [o + v * float(level0_position(0.0, f)) for o, v in zip(shift0, scale0)]


def image_attrs(name: str, scale0, shift0, unit, n_levels: int, channels, windows, description: str,
                method: str = "chunkdic.fields_levels.coarsen_task") -> dict:
    """OME-NGFF 0.5 ``ome`` attributes of a float image for viewers: axes ``c, z, y, x``,
    level ``t`` at scale ``scale0 * 2^t`` and translation ``shift0 + scale0 (2^t - 1) / 2``
    (:func:`level_frame`: the scan's own pyramid frame), ``omero`` channels labelled
    ``channels`` with their contrast windows ``(start, end, min, max)``; the first one active."""
    axes = [{"name": "c", "type": "channel"}]
    axes += [{"name": a, "type": "space", **({"unit": unit} if unit else {})} for a in "zyx"]
    datasets = []
    for t in range(n_levels):
        scale, shift = level_frame(scale0, shift0, t)
        datasets.append({"path": str(t), "coordinateTransformations": [
            {"type": "scale", "scale": [1.0] + scale},
            {"type": "translation", "translation": [0.0] + shift},
        ]})
    omero = []
    for i, (label, (lo, hi, vmin, vmax)) in enumerate(zip(channels, windows)):
        omero.append({"label": label, "active": i == 0, "color": "FFFFFF", "coefficient": 1.0,
                      "family": "linear", "inverted": False,
                      "window": {"start": lo, "end": hi, "min": vmin, "max": vmax}})
    return {
        "version": "0.5",
        "multiscales": [{
            "name": name, "axes": axes, "datasets": datasets, "type": "mean",
            "metadata": {"description": description, "method": method},
        }],
        "omero": {"name": name, "channels": omero, "rdefs": {"model": "greyscale", "defaultZ": 0}},
    }


def ngff_attrs(name: str, scale0, shift0, unit, n_levels: int, windows, disp_unit: str) -> dict:
    """:func:`image_attrs` of the fields image (channels :data:`CHANNELS`)."""
    return image_attrs(
        name, scale0, shift0, unit, n_levels, CHANNELS, windows,
        f"channels {', '.join(CHANNELS)}: displacement ({disp_unit}), its norm, eps_zz and "
        "the von Mises equivalent strain (per element, dimensionless), residual f - "
        "corrected g (grey levels of the result's level); NaN outside the ROI. Level t is "
        "the NaN-aware mean over 2^t voxels per axis of level 0")


def image_name(work) -> str:
    """The name an image staged at ``work`` will have once in place: the CLI stages all
    its outputs and calls the writer on its staged path, which stages again (two partial
    tags)."""
    name, prev = Path(work).name, None
    while name != prev:
        name, prev = final_name(name), name
    return name


def contrast_windows(coarsest: np.ndarray) -> list[tuple[float, float, float, float]]:
    """Per channel ``(1st percentile, 99th percentile, min, max)`` of the finite voxels of
    the coarsest level (``(0, 1, 0, 1)`` for an all-NaN channel)."""
    out = []
    for c in coarsest:
        v = c[np.isfinite(c)]
        if v.size == 0:
            out.append((0.0, 1.0, 0.0, 1.0))
            continue
        lo, hi = (float(q) for q in np.percentile(v, [1, 99]))
        if hi <= lo:  # a constant channel (a pure translation's strain)
            lo, hi = lo - 0.5 * abs(lo) - 1e-6, hi + 0.5 * abs(hi) + 1e-6
        out.append((lo, hi, float(v.min()), float(v.max())))
    return out

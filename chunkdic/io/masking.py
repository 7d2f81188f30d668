"""A specimen mask made from a scan, chunk by chunk: ``chunkdic mask SCAN -o mask.zarr``.

Material is ``scan > threshold`` (Otsu's threshold by default), optionally inside a cylinder
(axis along z) or a box, with the holes of every z-slice filled and, optionally, only the
largest connected component kept. The mask is written as an OME-NGFF 0.5 *labels* image
(``image-label`` metadata, value 1 = material): napari (napari-ome-zarr) shows it as a
Labels layer on the scan's grid (same scale and unit), and ``correlate --mask mask.zarr``
reads it (array ``"0"``, uint8, as a scan level).

Out of core (shared/DESIGN.md): no process holds the scan. Tasks work on slabs of whole
z-chunks (a slab is ``chunk`` planes of the full y-x extent, the unit of ``ingest``):

1. the histogram, accumulated by tasks: integer scans one bin per grey level (as
   ``skimage.filters.threshold_otsu`` bins integer images, so the threshold is the same),
   float scans 256 bins over the exact range (a first pass gives the range); Otsu's
   threshold from it on the client;
2. *holes*: filled in 2-D, slice by slice (``scipy.ndimage.binary_fill_holes`` of each z
   plane). Exact per slice and local to a task. Its limit: a pore that is closed in 3-D but
   open in some slice (touches that slice's outline) is not filled there, and a cavity
   whose slices are closed is filled even if it reaches the surface through another plane;
   for the usual specimen (a cylinder or a prism along z, pores inside) both agree;
3. *largest component* (face connectivity): each task labels its slab in 3-D and returns the
   component sizes and the labels of its first and last planes; the client joins the labels
   that touch across slab faces (union-find on those plane pairs: plane-sized, not
   volume-sized), sums the sizes and picks the largest; a last pass relabels each slab (the
   same computation again, deterministic) and keeps that component's labels. The client
   holds two label planes per slab boundary.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import config
from ..errors import InputError
from ..scheduler import check_scheduler, open_runner
from .formats.anyscan import open_any
from .handles import ArrayRef
from .levels import create_level, mark_complete
from .ngff import multiscales
from .outputs import Outputs
from .owntree import remove
from .scratch import make_scratch
from .siblings import final_name

__all__ = ["make_mask", "otsu", "parse_cylinder", "parse_box", "MASK_COLOR"]

#: the Labels colour of material (RGBA): napari's label colours are per value
MASK_COLOR = [255, 140, 0, 160]


def otsu(counts: np.ndarray, centers: np.ndarray) -> float:
    """Otsu's threshold of a histogram (the bin centre that maximises the between-class
    variance; material is ``> threshold``), as ``skimage.filters.threshold_otsu(hist=...)``."""
    counts = np.asarray(counts, np.float64)
    centers = np.asarray(centers, np.float64)
    keep = np.nonzero(counts)[0]
    if keep.size < 2:
        raise InputError("the scan has a single grey value: no threshold separates material from background; "
                         "give --threshold, or --cylinder/--box with --threshold none")
    counts, centers = counts[keep[0]:keep[-1] + 1], centers[keep[0]:keep[-1] + 1]
    w1 = np.cumsum(counts)
    w2 = np.cumsum(counts[::-1])[::-1]
    m1 = np.cumsum(counts * centers) / w1
    m2 = (np.cumsum((counts * centers)[::-1]) / w2[::-1])[::-1]
    between = w1[:-1] * w2[1:] * (m1[:-1] - m2[1:]) ** 2
    return float(centers[int(np.argmax(between))])


def parse_cylinder(text) -> tuple[float, float, float] | None:
    """``"CY,CX,R"`` (voxels; the axis along z) -> ``(cy, cx, r)``."""
    if text is None:
        return None
    try:
        cy, cx, r = (float(v) for v in str(text).split(","))
    except ValueError:
        raise InputError(f"--cylinder {text!r}: expected CY,CX,R in voxels (axis along z)") from None
    if not r > 0 or not all(np.isfinite([cy, cx, r])):
        raise InputError(f"--cylinder {text!r}: the radius must be a positive number")
    return cy, cx, r


def parse_box(text, shape) -> tuple[tuple[int, int], ...] | None:
    """``"z0:z1,y0:y1,x0:x1"`` (voxels) -> bounds, checked inside ``shape``."""
    if text is None:
        return None
    try:
        pairs = [tuple(int(v) for v in part.split(":")) for part in str(text).split(",")]
    except ValueError:
        raise InputError(f"--box {text!r}: expected z0:z1,y0:y1,x0:x1 in voxels") from None
    if len(pairs) != 3 or any(len(p) != 2 for p in pairs):
        raise InputError(f"--box {text!r}: expected three ranges z0:z1,y0:y1,x0:x1")
    for (a, b), n, ax in zip(pairs, shape, "zyx"):
        if not 0 <= a < b <= n:
            raise InputError(f"--box {text!r}: {ax} range {a}:{b} is empty or outside the scan (0:{n})")
    return tuple(pairs)


@dataclass(frozen=True)
class MaskJob:
    """What every task shares: the scan's level 0, the rule, the output."""

    scan: ArrayRef
    threshold: float | None
    fill_holes: bool
    cylinder: tuple[float, float, float] | None
    box: tuple[tuple[int, int], ...] | None
    out: str | None = None


def _read(job: MaskJob, z0: int, z1: int) -> np.ndarray:
    return np.asarray(job.scan.open()[z0:z1])


def range_task(job: MaskJob, z0: int, z1: int) -> tuple[float, float]:
    v = _read(job, z0, z1)
    return float(np.nanmin(v)), float(np.nanmax(v))


def histogram_task(job: MaskJob, z0: int, z1: int, lo: float, hi: float, bins: int | None):
    """Counts of one slab: one bin per integer grey level ``lo..hi`` (``bins`` None), else
    ``bins`` bins over ``[lo, hi]`` (``numpy.histogram``)."""
    v = _read(job, z0, z1)
    if bins is None:
        return np.bincount((v.ravel().astype(np.int64) - int(lo)), minlength=int(hi - lo) + 1)
    return np.histogram(v[np.isfinite(v)], bins=bins, range=(lo, hi))[0]


def slab_mask(job: MaskJob, z0: int, z1: int) -> np.ndarray:
    """The mask of planes ``z0:z1`` before the component step: threshold, shape, holes."""
    v = _read(job, z0, z1)
    m = np.ones(v.shape, bool) if job.threshold is None else v > job.threshold
    ny, nx = v.shape[1:]
    if job.cylinder is not None:
        cy, cx, r = job.cylinder
        yy, xx = np.ogrid[:ny, :nx]
        m &= ((yy - cy) ** 2 + (xx - cx) ** 2 <= r * r)[None]
    if job.box is not None:
        (bz0, bz1), (by0, by1), (bx0, bx1) = job.box
        inside = np.zeros(v.shape, bool)
        inside[max(bz0 - z0, 0):max(min(bz1, z1) - z0, 0), by0:by1, bx0:bx1] = True
        m &= inside
    if job.fill_holes:
        from scipy import ndimage as ndi

        for k in range(m.shape[0]):
            m[k] = ndi.binary_fill_holes(m[k])
    return m


def _labels(job: MaskJob, z0: int, z1: int) -> tuple[np.ndarray, int]:
    from scipy import ndimage as ndi

    return ndi.label(slab_mask(job, z0, z1))  # face connectivity


def component_task(job: MaskJob, z0: int, z1: int):
    """Sizes of the slab's components (index = label) and its first and last label planes."""
    lab, n = _labels(job, z0, z1)
    return z0, np.bincount(lab.ravel(), minlength=n + 1), lab[0].copy(), lab[-1].copy()


def write_task(job: MaskJob, z0: int, z1: int, keep: np.ndarray | None) -> int:
    """Write planes ``z0:z1`` (the task owns those whole chunks): 1 = material; with ``keep``
    (labels of the slab to keep) only those components. Returns the material voxels."""
    import zarr

    if keep is None:
        m = slab_mask(job, z0, z1)
    else:
        lab, _ = _labels(job, z0, z1)
        m = np.isin(lab, keep) & (lab > 0)
    arr = zarr.open_array(store=job.out, path="0", mode="r+")
    arr[z0:z1] = m.astype(np.uint8)
    return int(m.sum())


def _largest(parts) -> dict[int, np.ndarray]:
    """Union-find over the labels of all slabs joined across slab faces: the labels of the
    largest component in each slab (by the slab's first plane ``z0``)."""
    parts = sorted(parts, key=lambda p: p[0])
    offset, base = 0, []
    for _, sizes, _, _ in parts:
        base.append(offset)
        offset += len(sizes)
    parent = np.arange(offset)

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for k in range(len(parts) - 1):
        last, first = parts[k][3], parts[k + 1][2]
        both = (last > 0) & (first > 0)
        if both.any():
            pairs = np.unique(np.stack([last[both] + base[k], first[both] + base[k + 1]], axis=1), axis=0)
            for a, b in pairs:
                ra, rb = find(int(a)), find(int(b))
                if ra != rb:
                    parent[rb] = ra
    size = np.zeros(offset, np.int64)
    for (_, sizes, _, _), b in zip(parts, base):
        for lab in range(1, len(sizes)):
            size[find(b + lab)] += sizes[lab]
    if not size.any():
        raise InputError("the mask is empty: no voxel above the threshold (inside --cylinder/--box)")
    best = int(np.argmax(size))
    return {z0: np.array([lab for lab in range(1, len(sizes)) if find(b + lab) == best], np.int64)
            for (z0, sizes, _, _), b in zip(parts, base)}


def make_mask(scan, out, *, threshold: float | str | None = "otsu", fill_holes: bool = True,
              largest: bool = False, cylinder=None, box=None, scheduler=None, overwrite: bool = False,
              progress: Callable[[str], None] | None = None) -> dict:
    """Make a specimen mask of ``scan`` and write it as an OME-NGFF labels image.

    Parameters
    ----------
    scan : path
        The scan (any format ``correlate --mask`` reads: Zarr, .npy, TIFF, HDF5); level 0 is used.
    out : path
        The labels image to create (Zarr v3 group; array ``"0"``, uint8, 1 = material).
    threshold : "otsu", float or None, keyword-only
        Material is ``scan > threshold``; ``"otsu"`` (default): Otsu's threshold of the
        scan's histogram (accumulated by tasks); ``None``: every voxel (then a ``cylinder``
        or ``box`` alone makes the mask).
    fill_holes : bool, keyword-only
        Fill the holes of every z-slice (module docstring: 2-D, its limits).
    largest : bool, keyword-only
        Keep only the largest connected component (face connectivity, across slabs).
    cylinder : (cy, cx, r) or str "CY,CX,R", optional, keyword-only
        Keep only voxels inside this cylinder (axis along z), voxels.
    box : str "z0:z1,y0:y1,x0:x1" or bounds, optional, keyword-only
        Keep only voxels inside this box, voxels.
    scheduler
        Where the tasks run, as in :func:`chunkdic.correlate`.
    overwrite : bool, keyword-only
        Replace a mask that chunkdic wrote (nothing else).
    progress : callable(str), optional
        One message per pass.

    Returns
    -------
    dict
        ``path``, ``threshold`` (None without one), ``material`` (voxels), ``fraction``,
        ``shape``, ``seconds``.

    Examples
    --------
    >>> chunkdic.make_mask("scan.zarr", "mask.zarr", largest=True)  # doctest: +SKIP
    """
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    src = open_any(scan)
    shape = tuple(int(n) for n in src.shape(0))
    dtype = np.dtype(src.dtype(0))
    if isinstance(threshold, str):
        if threshold.lower() == "otsu":
            threshold = "otsu"
        elif threshold.lower() == "none":
            threshold = None
        else:
            try:
                threshold = float(threshold)
            except ValueError:
                raise InputError(f"--threshold {threshold!r}: expected otsu, none or a grey value") from None
    if isinstance(threshold, float) and not np.isfinite(threshold):
        raise InputError(f"--threshold {threshold}: expected a finite grey value")
    cyl = parse_cylinder(cylinder) if isinstance(cylinder, str) or cylinder is None else tuple(map(float, cylinder))
    bounds = parse_box(box, shape) if isinstance(box, str) or box is None else tuple(tuple(b) for b in box)
    if threshold is None and cyl is None and bounds is None:
        raise InputError("--threshold none keeps every voxel: give --cylinder or --box to shape the mask")
    check_scheduler(scheduler)
    plan = Outputs(inputs=[scan], overwrite=overwrite)
    entry = plan.add(out, "mask")
    c = int(config.get("chunk-size"))
    slabs = [(z, min(z + c, shape[0])) for z in range(0, shape[0], c)]
    scratch = make_scratch()
    try:
        with plan, open_runner(scheduler) as runner:
            ref = src.refs([0], scratch, runner=runner)[0]
            job = MaskJob(ref, None, fill_holes, cyl, bounds)
            if threshold == "otsu":
                threshold = _otsu_of(runner, job, slabs, dtype)
                say(f"Otsu threshold {threshold:g} (histogram of {len(slabs)} slabs)")
            job = MaskJob(ref, threshold, fill_holes, cyl, bounds, str(entry.work))
            _create(entry.work, shape, c, src, threshold, fill_holes, largest, cyl, bounds, scan)
            keep = {z0: None for z0, _ in slabs}
            if largest:
                parts = list(runner.map_unordered(component_task, [(job, a, b) for a, b in slabs]))
                keep = _largest(parts)
                say(f"largest component found over {len(slabs)} slabs")
            material = sum(runner.map_unordered(write_task, [(job, a, b, keep[a]) for a, b in slabs]))
            if material == 0:
                raise InputError("the mask is empty: no voxel above the threshold (inside --cylinder/--box)")
            _finish(entry.work, material, shape)
    finally:
        remove(scratch)
    total = int(np.prod(shape))
    return {"path": str(out), "threshold": threshold, "material": int(material), "fraction": material / total,
            "shape": shape, "seconds": time.perf_counter() - t0}


def _otsu_of(runner, job: MaskJob, slabs, dtype: np.dtype) -> float:
    """Otsu's threshold from the histogram that tasks accumulate (module docstring)."""
    ranges = list(runner.map_unordered(range_task, [(job, a, b) for a, b in slabs]))
    lo, hi = min(r[0] for r in ranges), max(r[1] for r in ranges)
    if not np.isfinite(lo) or not np.isfinite(hi) or lo == hi:
        raise InputError("the scan has a single grey value: no threshold separates material from background; "
                         "give --threshold, or --cylinder/--box with --threshold none")
    integer = dtype.kind in "iub" and hi - lo < 2**24
    bins = None if integer else 256
    counts = sum(runner.map_unordered(histogram_task, [(job, a, b, lo, hi, bins) for a, b in slabs]))
    if integer:
        centers = np.arange(int(lo), int(hi) + 1, dtype=np.float64)
    else:
        edges = np.histogram_bin_edges([lo, hi], bins=256, range=(lo, hi))
        centers = (edges[:-1] + edges[1:]) / 2
    return otsu(counts, centers)


def _create(work: Path, shape, chunk: int, src, threshold, fill_holes, largest, cyl, bounds, scan) -> None:
    """The labels group and its level-0 array, flagged incomplete."""
    import zarr

    root = zarr.open_group(str(work), mode="w", zarr_format=3)
    root.attrs["chunkdic"] = {
        "kind": "mask", "complete": False, "source": str(Path(str(scan)).resolve()) if isinstance(scan, (str, Path))
        else None, "threshold": threshold, "rule": "material = scan > threshold" if threshold is not None else
        "every voxel", "fill_holes": "per z-slice (2-D)" if fill_holes else False, "largest": bool(largest),
        "cylinder": list(cyl) if cyl else None, "box": [list(b) for b in bounds] if bounds else None,
        "voxel_size": list(src.voxel_size) if src.voxel_size else None, "unit": src.unit}
    create_level(str(work), 0, shape, np.uint8, tuple(min(chunk, n) for n in shape))


def _finish(work: Path, material: int, shape) -> None:
    """Metadata last: the NGFF ``multiscales`` and ``image-label``, complete."""
    import zarr

    mark_complete(str(work), 0)
    root = zarr.open_group(str(work), mode="r+")
    meta = root.attrs.asdict()["chunkdic"]
    vs = meta.get("voxel_size")
    ome = multiscales(final_name(Path(work).name), [0], vs or [1.0] * 3, [0.0] * 3, meta.get("unit") if vs else None,
                      kind="mask", description="specimen mask: 1 = material, 0 = background", method="chunkdic mask")
    ome["image-label"] = {"version": "0.5", "colors": [{"label-value": 1, "rgba": MASK_COLOR}],
                          "properties": [{"label-value": 1, "name": "material"}]}
    root.update_attributes({"ome": ome, "chunkdic": {**meta, "complete": True, "material": int(material),
                                                      "fraction": material / float(np.prod(shape))}})

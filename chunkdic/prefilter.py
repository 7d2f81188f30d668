"""Cubic B-spline coefficients of the deformed image, computed once per level.

Cubic B-spline interpolation needs the image prefiltered (the coefficients solve a
recursive filter along each axis). Prefiltering each task's window every iteration costs
about as much as the interpolation itself, because the window must carry a halo of
``chunkdic.bspline-halo`` voxels for the result to equal a whole-volume prefilter. Since
``g`` never changes, the engine instead prefilters, once per level, the box of ``g`` that
the current field can reach (plus a margin), chunk by chunk on the workers, into a float32
scratch array; every iteration then only gathers from it. A task whose window leaves
the box falls back to prefiltering its own window, so the result never depends on the box.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi

from .mesh import Mesh
from .volume import ArrayRef

#: chunk edge of the coefficient store: small, so a block's window reads little extra
CHUNK = 64
#: edge of the region one prefilter task computes (a multiple of CHUNK: whole chunks)
TASK_EDGE = 128


@dataclass(frozen=True)
class Coefficients:
    """B-spline coefficients of ``g`` over ``box`` (absolute level indices)."""

    ref: ArrayRef
    box: tuple[tuple[int, int], tuple[int, int], tuple[int, int]]

    def covers(self, window: tuple[slice, slice, slice]) -> bool:
        return all(a <= w.start and w.stop <= b for w, (a, b) in zip(window, self.box))

    def read(self, window: tuple[slice, slice, slice]) -> np.ndarray:
        local = tuple(slice(w.start - a, w.stop - a) for w, (a, _) in zip(window, self.box))
        return self.ref.read(local)


def reachable_box(mesh: Mesh, u: np.ndarray, g_shape, *, margin: int):
    """Box of ``g`` holding every ``X + u(X)`` of the mesh (cubic support) plus ``margin``."""
    box = []
    for axis, r in enumerate(mesh.roi):
        lo = r.start + float(np.min(u[axis])) - 1 - margin
        hi = r.stop - 1 + float(np.max(u[axis])) + 3 + margin
        a, b = max(int(np.floor(lo)), 0), min(int(np.ceil(hi)), int(g_shape[axis]))
        if b <= a:
            return None
        box.append((a, b))
    return tuple(box)


def prefilter_task(g_ref: ArrayRef, out: ArrayRef, box, region, halo: int) -> int:
    """Task: coefficients of ``region`` (absolute slices) into the store ``out``.

    The region is read with ``halo`` extra voxels per side (clipped to the volume, where
    the mirror boundary is then exact), filtered, cropped and written; in a Zarr store the
    region covers whole chunks, so concurrent tasks never share a chunk.
    """
    grown = tuple(slice(max(r.start - halo, 0), min(r.stop + halo, n)) for r, n in zip(region, g_ref.shape))
    data = g_ref.read(grown).astype(np.float32, copy=False)
    coeffs = ndi.spline_filter(data, order=3, mode="mirror", output=np.float32)
    crop = tuple(slice(r.start - s.start, r.stop - s.start) for r, s in zip(region, grown))
    local = tuple(slice(r.start - a, r.stop - a) for r, (a, _) in zip(region, box))
    if out.kind == "npy":
        target = np.load(out.path, mmap_mode="r+")
    else:
        import zarr

        target = zarr.open_array(out.path, mode="r+")
    target[local] = coeffs[crop]
    return int(np.prod([r.stop - r.start for r in region]))


def build_coefficients(g_ref: ArrayRef, box, path: Path, map_tasks, *, halo: int, local: bool) -> Coefficients:
    """Prefilter ``box`` of ``g`` into a new float32 array at ``path``.

    ``map_tasks(fn, args)`` runs the tasks and yields their results: a runner's
    ``map_unordered``, or the engine's wrapper of it that reports progress (at level 0 of
    2048³ this is 8.6 G voxels).

    ``local``: every task runs on this machine, so the store is a memory-mapped ``.npy``
    file, whose windows read 3-4x cheaper than from Zarr chunks (no chunk assembly; it
    is on the hot path of every iteration). Otherwise an uncompressed Zarr array, safe
    for workers on other hosts sharing the file system.
    """
    shape = tuple(b - a for a, b in box)
    if local:
        path = path.with_suffix(".npy")
        np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=shape).flush()
        out = ArrayRef("npy", str(path), "", shape, "float32")
    else:
        import zarr

        zarr.create_array(str(path), shape=shape, chunks=(CHUNK,) * 3, dtype="float32",
                          compressors=None, zarr_format=3, overwrite=True)
        out = ArrayRef("zarr", str(path), "", shape, "float32")
    starts = [range(a, b, TASK_EDGE) for a, b in box]
    regions = [
        tuple(slice(s, min(s + TASK_EDGE, b)) for s, (_, b) in zip(corner, box))
        for corner in ((z, y, x) for z in starts[0] for y in starts[1] for x in starts[2])
    ]
    for _ in map_tasks(prefilter_task, [(g_ref, out, box, r, halo) for r in regions]):
        pass
    return Coefficients(out, box)

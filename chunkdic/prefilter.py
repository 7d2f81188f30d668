"""Cubic B-spline coefficients of the deformed image, computed once per level.

Cubic B-spline interpolation needs the image prefiltered (the coefficients solve a
recursive filter along each axis). Prefiltering each task's window every iteration costs
about as much as the interpolation itself, because the window must carry a halo of
``chunkdic.bspline-halo`` voxels for the result to equal a whole-volume prefilter. Since
``g`` never changes, the engine instead prefilters, once per level, the box of ``g`` that
the current field can reach (plus a margin), chunk by chunk on the workers, into a float32
scratch Zarr array; every iteration then only gathers from it. A task whose window leaves
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


def prefilter_task(g_ref: ArrayRef, out_path: str, box, region, halo: int) -> int:
    """Task: coefficients of ``region`` (absolute slices) into the store at ``out_path``.

    The region is read with ``halo`` extra voxels per side (clipped to the volume, where
    the mirror boundary is then exact), filtered, cropped and written; the region covers
    whole chunks of the store, so concurrent tasks never share a chunk.
    """
    import zarr

    grown = tuple(slice(max(r.start - halo, 0), min(r.stop + halo, n)) for r, n in zip(region, g_ref.shape))
    data = g_ref.read(grown).astype(np.float32, copy=False)
    coeffs = ndi.spline_filter(data, order=3, mode="mirror", output=np.float32)
    crop = tuple(slice(r.start - s.start, r.stop - s.start) for r, s in zip(region, grown))
    local = tuple(slice(r.start - a, r.stop - a) for r, (a, _) in zip(region, box))
    zarr.open_array(out_path, mode="r+")[local] = coeffs[crop]
    return int(np.prod([r.stop - r.start for r in region]))


def build_coefficients(g_ref: ArrayRef, box, path: Path, runner, *, halo: int) -> Coefficients:
    """Prefilter ``box`` of ``g`` into a new float32 Zarr array at ``path``, on the runner."""
    import zarr

    shape = tuple(b - a for a, b in box)
    zarr.create_array(str(path), shape=shape, chunks=(CHUNK,) * 3, dtype="float32",
                      compressors=None, zarr_format=3, overwrite=True)
    starts = [range(a, b, TASK_EDGE) for a, b in box]
    regions = [
        tuple(slice(s, min(s + TASK_EDGE, b)) for s, (_, b) in zip(corner, box))
        for corner in ((z, y, x) for z in starts[0] for y in starts[1] for x in starts[2])
    ]
    for _ in runner.map_unordered(prefilter_task, [(g_ref, str(path), box, r, halo) for r in regions]):
        pass
    ref = ArrayRef("zarr", str(path), "", shape, "float32")
    return Coefficients(ref, box)

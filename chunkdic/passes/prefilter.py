"""Preparing the images of one level: low-pass of both scans, B-spline coefficients of ``g``.

Real CT scans have sharp edges and noise at the voxel scale, where interpolation is least
accurate: a cubic B-spline's interpolation error on them dominated the measurement
uncertainty, and a Gaussian low-pass of both scans (σ ≈ 1 voxel) cut it several times
(docs/engine.md, "Image preparation"). So, per level:

- the reference ``f`` is low-passed block by block in the ``M`` pass
  (:func:`prepare_reference`), which reads each block with a halo of the filter's radius
  and keeps the result as the block's haloed copy (:mod:`chunkdic.passes.haloed`);
- the deformed ``g`` is low-passed and, for cubic interpolation, turned into B-spline
  coefficients (:func:`prepare_deformed`) once per level over the box of ``g`` that the
  current field can reach (plus a margin), chunk by chunk on the workers, into a float32
  scratch store (:func:`build_prepared`). A task whose window leaves that box prepares its
  own window, read with the same halo (:func:`prepared_halo`), so results never depend on
  the box or on the block size.

Both filters run on a region read with a halo and clipped to the volume: the Gaussian
(``mode="mirror"``, truncated at ``TRUNCATE`` σ) is exact on the crop when the halo is at
least its radius; the B-spline prefilter (recursive, influence decaying as ``0.268^d``)
needs ``chunkdic.bspline-halo`` voxels more (12: float32 precision). At a true volume face
the region ends where the volume ends and the mirror boundary of both filters is that of
the whole volume.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import config
from ..errors import InputError
from ..io.chunkread import z_order_key
from ..io.handles import ArrayRef
from ..kernels.lowpass import TRUNCATE, lowpass_bspline
from ..kernels.pwrite import write_rows
from ..kernels.quantize import quantize_u16
from ..mesh import Mesh
from . import scratchstore

#: chunk edge of the prepared store: small, so a block's window reads little extra
CHUNK = 64
#: largest edge of the region one preparation task computes by default
#: (``chunkdic.prepare-voxels``); the box is split into equal parts no longer than this
#: (multiples of CHUNK when the store is Zarr: whole chunks)
TASK_EDGE = 160


def gaussian_radius(sigma: float) -> int:
    """Radius (voxels) of the truncated Gaussian of scipy.ndimage with :data:`TRUNCATE`."""
    return int(TRUNCATE * float(sigma) + 0.5) if sigma > 0 else 0


def prepared_halo(sigma: float, interpolation: str, bspline_halo: int) -> int:
    """Halo (voxels) a window of raw ``g`` needs to be prepared exactly on its crop."""
    return gaussian_radius(sigma) + (int(bspline_halo) if interpolation == "cubic" else 0)


def face_margin(sigma: float) -> int:
    """Voxels near a face of ``g`` whose low-pass is too unlike the specimen's to be used.

    Within ``2 σ`` of a face the low-pass gives more than 2 % of its weight to the mirror
    extension of the image instead of the specimen's continuation (beyond ``2 σ``, under
    2.3 %, fading as the Gaussian tail): positions mapped there are excluded.
    """
    return int(math.ceil(2.0 * sigma)) if sigma > 0 else 0


def check_finite(data: np.ndarray, what: str, region) -> None:
    """Refuse NaN/Inf voxels (InputError naming the scan and the region)."""
    if data.dtype.kind == "f" and not np.isfinite(data).all():
        bad = np.argwhere(~np.isfinite(data))[0]
        where = tuple(int(r.start) + int(i) for r, i in zip(region, bad))
        raise InputError(f"the {what} scan has NaN or Inf voxels (the first at voxel {where} of this level): "
                         "replace them before correlating")


def lowpass(data: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass (σ in voxels, mirror boundary) in float32; a float32 copy if σ = 0.

    :func:`scipy.ndimage.gaussian_filter` to float32 round-off, by the kernel that also
    prefilters ``g`` (:mod:`chunkdic.kernels.lowpass`).
    """
    return lowpass_bspline(data, sigma, False)


def prepare_reference(raw: np.ndarray, region, inner, sigma: float) -> np.ndarray:
    """Low-pass a block of ``f`` read over ``region`` and crop it to ``inner`` (absolute slices)."""
    out = lowpass(raw, sigma)
    return out[tuple(slice(i.start - r.start, i.stop - r.start) for i, r in zip(inner, region))]


def prepare_deformed(raw: np.ndarray, sigma: float, interpolation: str) -> np.ndarray:
    """Low-pass a window of ``g`` and, for cubic, prefilter it into B-spline coefficients
    (both filters in one sweep per axis: :func:`chunkdic.kernels.lowpass.lowpass_bspline`)."""
    return lowpass_bspline(raw, sigma, interpolation == "cubic")


def overshoot(sigma: float, interpolation: str) -> float:
    """How far (fraction of the input's range) the prepared ``g`` may leave that range.

    The low-pass alone stays within it (positive weights); its cubic B-spline coefficients
    may not: the bound is the negative part of the separable 3-D kernel (Gaussian, then the
    B-spline prefilter), 0.019 at σ = 1, 0.27 at σ = 0.8, 0.71 at σ = 0.5.
    """
    if interpolation != "cubic":
        return 0.0
    n = 256
    w = 2 * np.pi * np.fft.fftfreq(n)
    h = np.real(np.fft.ifft(np.exp(-0.5 * (float(sigma) * w) ** 2) * 3.0 / (2.0 + np.cos(w))))
    p, m = float(h[h > 0].sum()), float(-h[h < 0].sum())
    return 3 * p * p * m + m**3


def prepared_grid(dtype, sigma: float, interpolation: str) -> tuple[float, float]:
    """``(offset, step)`` of the 16-bit grid the prepared ``g`` of a level of ``dtype`` is stored on;
    ``(0, 0)``: float32 (a float or wider scan, no low-pass, an overshoot above 0.5 of the
    range, or ``chunkdic.scratch-precision`` ``"float32"``). The grid covers the dtype's
    range widened by :func:`overshoot` on each side, so nothing is clipped: 1.04 grey
    levels per step for a 16-bit scan at σ = 1, 16.6 in the compact layout
    (:mod:`chunkdic.passes.scratchstore`; docs/engine.md, "Scratch disk")."""
    if dtype is None or sigma <= 0 or config.get("scratch-precision") != "uint16":
        return 0.0, 0.0
    dtype = np.dtype(dtype)
    if dtype.kind not in "iu" or dtype.itemsize > 2:
        return 0.0, 0.0
    over = overshoot(sigma, interpolation)
    if over > 0.5:
        return 0.0, 0.0
    info = np.iinfo(dtype)
    span = float(info.max) - float(info.min)
    step = span * (1 + 2 * over) / 65535.0 * (1 + 1e-9)
    return float(info.min) - over * span, step * scratchstore.step_factor()


def quantize(data: np.ndarray, grid: tuple[float, float]) -> np.ndarray:
    """``data`` on the 16-bit ``grid`` (uint16; ``grid[1] == 0``: float32 as it is)."""
    offset, step = grid
    if step <= 0:
        return np.asarray(data, np.float32)
    return quantize_u16(data, offset, step, wide=False)[0]


def on_grid(data: np.ndarray, grid: tuple[float, float]) -> np.ndarray:
    """``dequantize(quantize(data, grid), grid)`` in one sweep: float32 values as stored."""
    offset, step = grid
    if step <= 0:
        return np.asarray(data, np.float32)
    return quantize_u16(data, offset, step, wide=False)[1]


def dequantize(q: np.ndarray, grid: tuple[float, float]) -> np.ndarray:
    """Float32 values of ``q`` on ``grid`` (float data: as it is)."""
    offset, step = grid
    if step <= 0:
        return q
    out = q.astype(np.float32)  # float32 arithmetic: 0.004 grey level off at most, and on every read
    out *= np.float32(step)
    out += np.float32(offset)
    return out


@dataclass(frozen=True)
class PreparedImage:
    """The prepared ``g`` (samples or B-spline coefficients) over ``box`` (absolute level indices),
    stored as float32 or on the 16-bit ``grid`` (:func:`prepared_grid`); ``compressed``: a
    compact layout's Zarr array of :data:`CHUNK`³ chunks, read from its chunk files
    (:func:`chunkdic.passes.scratchstore.read_window`)."""

    ref: ArrayRef
    box: tuple[tuple[int, int], tuple[int, int], tuple[int, int]]
    grid: tuple[float, float] = (0.0, 0.0)
    compressed: bool = False

    def covers(self, window: tuple[slice, slice, slice]) -> bool:
        return all(a <= w.start and w.stop <= b for w, (a, b) in zip(window, self.box))

    def read(self, window: tuple[slice, slice, slice]) -> np.ndarray:
        local = tuple(slice(w.start - a, w.stop - a) for w, (a, _) in zip(window, self.box))
        if self.compressed:
            return dequantize(scratchstore.read_window(self.ref.path, local, CHUNK, self.ref.dtype, True), self.grid)
        return dequantize(self.ref.read(local), self.grid)


def reachable_box(mesh: Mesh, u: np.ndarray, g_shape, *, margin: int):
    """Box of ``g`` holding every ``X + u(X)`` of the mesh (cubic support) plus ``margin``."""
    box = []
    for axis, r in enumerate(mesh.roi):
        lo = r.start + float(np.min(u[axis])) - 1 - margin
        hi = r.stop - 1 + float(np.max(u[axis])) + 3 + margin
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return None
        a, b = max(int(np.floor(lo)), 0), min(int(np.ceil(hi)), int(g_shape[axis]))
        if b <= a:
            return None
        box.append((a, b))
    return tuple(box)


def prepare_task(g_ref: ArrayRef, out: ArrayRef, box, region, halo: int, sigma: float, interpolation: str,
                 grid: tuple[float, float] = (0.0, 0.0)) -> int:
    """Task: the prepared ``g`` of ``region`` (absolute slices) into the store ``out``.

    The region is read with ``halo`` extra voxels per side (clipped to the volume), filtered,
    cropped and written; in a Zarr store the region covers whole chunks, so concurrent tasks
    never share a chunk.
    """
    grown = tuple(slice(max(r.start - halo, 0), min(r.stop + halo, n)) for r, n in zip(region, g_ref.shape))
    data = g_ref.read(grown)
    check_finite(data, "deformed", grown)
    prepared = prepare_deformed(data, sigma, interpolation)
    crop = tuple(slice(r.start - s.start, r.stop - s.start) for r, s in zip(region, grown))
    prepared = quantize(prepared[crop], grid)
    local = tuple(slice(r.start - a, r.stop - a) for r, (a, _) in zip(region, box))
    write_region(out, local, prepared)
    return int(np.prod([r.stop - r.start for r in region]))


def write_region(out: ArrayRef, local, data: np.ndarray) -> None:
    """Write ``data`` into ``local`` (slices of the store) of the prepared store ``out``.

    A ``.npy`` store is written with ``pwrite``, one call per contiguous run of the file
    (a row of the region, or more when it spans whole rows), never through a memory map:
    writing a task's region through a shared mapping of the file mapped whole large
    folios of the page cache (ext4 on Linux 6.16+), so the writing process's resident
    memory grew with the scan's plane, not the task (+270 MiB for a 147³ task of a 1024³
    store, +97 MiB at 2048³, measured by ``validation/scale/bench_prefilter_memory.py``), the
    page faults into the new file took 0.5-2.3 s per task against 0.04-0.08 s for the
    ``pwrite`` calls, and the store's windows read later by the passes came back in
    those large folios too (+250 MiB mapped per 136³ window read at 1024³, against
    +50 MiB when the file was written by ``pwrite``). docs/distributed.md, "The plan's
    memory at 512³-2048³".
    """
    if out.kind != "npy":
        import zarr

        # every chunk written, even one of zeros (a scan's empty background in float32): a
        # resumed run adopts the store only when every chunk file is there (adopt_prepared)
        zarr.open_array(out.path, mode="r+").with_config({"write_empty_chunks": True})[local] = data
    elif not hasattr(os, "pwrite"):  # not POSIX (Windows): through a memory map
        target = np.load(out.path, mmap_mode="r+")
        target[local] = data
        del target
    else:
        write_npy_region(out.path, local, data)


def npy_layout(path) -> tuple[int, tuple, np.dtype]:
    """``(offset of the data in bytes, shape, dtype)`` of a C-ordered ``.npy`` file."""
    with open(path, "rb") as fh:
        major, _ = np.lib.format.read_magic(fh)
        read_header = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(fh)
        if fortran:
            raise ValueError(f"{path}: a Fortran-ordered .npy store")
        return fh.tell(), tuple(shape), np.dtype(dtype)


def write_npy_region(path, local, data: np.ndarray) -> None:
    """``data`` into the slices ``local`` of the 3-D ``.npy`` array at ``path``, by ``pwrite``
    of each contiguous run of the file: a row of the region (all of them in one ``nogil``
    kernel, :func:`chunkdic.kernels.pwrite.write_rows`), a plane when it spans whole rows,
    all of it when it spans whole planes. Concurrent writers of disjoint regions never
    touch each other's bytes (the same file pages, shared through the page cache)."""
    offset, shape, dtype = npy_layout(path)
    starts = [s.start for s in local]
    if data.dtype != dtype or data.strides[-1] != dtype.itemsize:
        data = np.ascontiguousarray(data, dtype=dtype)  # else rows are written from the view: no copy
    if data.shape != tuple(s.stop - s.start for s in local):
        raise ValueError(f"a region of shape {data.shape} written into {local}")
    item = dtype.itemsize
    row, plane = shape[2] * item, shape[1] * shape[2] * item
    whole = data.flags.c_contiguous
    fd = os.open(path, os.O_WRONLY)
    try:
        if whole and data.shape[1:] == shape[1:]:  # whole planes: one run
            _pwrite_all(fd, data, offset + starts[0] * plane)
        elif whole and data.shape[2] == shape[2]:  # whole rows: one run per plane
            for z in range(data.shape[0]):
                _pwrite_all(fd, data[z], offset + (starts[0] + z) * plane + starts[1] * row)
        elif write_rows(fd, data, offset + starts[0] * plane + starts[1] * row + starts[2] * item, row, plane):
            raise OSError(f"{path}: writing a region of the prepared store failed (is the disk full?)")
    finally:
        os.close(fd)


def _pwrite_all(fd: int, a: np.ndarray, offset: int) -> None:
    """All of the contiguous array ``a`` at ``offset`` (a regular file may write less at once)."""
    view = memoryview(a).cast("B")
    while view.nbytes:
        n = os.pwrite(fd, view, offset)
        if n <= 0:
            raise OSError(f"pwrite wrote nothing at offset {offset}")
        view, offset = view[n:], offset + n


def prepare_voxels() -> int:
    """Largest edge of a prefilter task: ``chunkdic.prepare-voxels``, else :data:`TASK_EDGE`."""
    return int(config.get("prepare-voxels") or TASK_EDGE)


def task_edge(extent: int, unit: int, largest: int | None = None) -> int:
    """Edge of the preparation tasks along an axis of ``extent`` voxels: equal parts of at
    most ``largest`` (default ``chunkdic.prepare-voxels``, :data:`TASK_EDGE`; a memory
    target lowers it, :mod:`chunkdic.engine.costs`), rounded up to a multiple of ``unit``.

    Each task reads ``prepared_halo`` (16 voxels at σ = 1, cubic) more per side, so small
    remainder tasks are costly: a 316-voxel axis cut 128 + 128 + 60 filtered 1.30× its
    voxels per axis (2.2× in 3-D); cut 158 + 158, 1.20× (1.73×).
    """
    largest = int(largest or prepare_voxels())
    parts = max(1, -(-int(extent) // largest))
    edge = -(-int(extent) // parts)
    return -(-edge // unit) * unit


def build_prepared(g_ref: ArrayRef, box, path: Path, map_tasks, *, halo: int, local: bool, sigma: float = 0.0,
                   interpolation: str = "cubic") -> PreparedImage:
    """Prepare ``box`` of ``g`` into a new array at ``path`` (float32, or uint16 on the
    grid of :func:`prepared_grid`).

    ``map_tasks(fn, args)`` runs the tasks and yields their results: a runner's
    ``map_unordered``, or the engine's wrapper of it that reports progress (at level 0 of
    2048³ this is 8.6 G voxels). ``halo``: :func:`prepared_halo`.

    ``local``: every task runs on this machine, so the store is a memory-mapped ``.npy``
    file, whose windows read 3-4x cheaper than from Zarr chunks (no chunk assembly; it
    is on the hot path of every iteration). (Hence tasks that write into it rather than
    ``dask.array.map_overlap``, whose result would still have to be stored, as Zarr.) Otherwise an uncompressed Zarr array, safe
    for workers on other hosts sharing the file system; in the compact layout
    (:mod:`chunkdic.passes.scratchstore`) a compressed Zarr array in either case.
    """
    shape = tuple(b - a for a, b in box)
    grid = prepared_grid(g_ref.dtype, sigma, interpolation)
    dtype = "uint16" if grid[1] > 0 else "float32"
    compact = scratchstore.compact() and grid[1] > 0
    if local and not compact:
        path = path.with_suffix(".npy")
        np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape).flush()
        out = ArrayRef("npy", str(path), "", shape, dtype)
    else:
        import zarr

        zarr.create_array(str(path), shape=shape, chunks=(CHUNK,) * 3, dtype=dtype,
                          compressors=scratchstore.compressors("g", np.dtype(dtype).itemsize) if compact else None,
                          zarr_format=3, overwrite=True)
        out = ArrayRef("zarr", str(path), "", shape, dtype)
    edges = [task_edge(b - a, 1 if out.kind == "npy" else CHUNK) for a, b in box]
    starts = [range(a, b, e) for (a, b), e in zip(box, edges)]
    # in Z-order of the task grid: neighbouring tasks, whose halos share the scan's chunks,
    # run close in time and find those chunks decoded (io.chunkread.chunk_cache)
    corners = sorted(((z, y, x) for z in starts[0] for y in starts[1] for x in starts[2]),
                     key=lambda c: z_order_key([(v - a) // e for v, (a, _), e in zip(c, box, edges)]))
    regions = [tuple(slice(s, min(s + e, b)) for s, e, (_, b) in zip(corner, edges, box)) for corner in corners]
    args = [(g_ref, out, box, r, halo, float(sigma), interpolation, grid) for r in regions]
    for _ in map_tasks(prepare_task, args):
        pass
    prepared = PreparedImage(out, box, grid, compact)
    _write_record(prepared)
    return prepared


def record_path(store) -> Path:
    """The record of a prepared store (``g-level0-1.npy`` -> ``g-level0-1.prepared.json``)."""
    store = Path(store)
    return store.with_name(store.name.rsplit(".", 1)[0] + ".prepared.json")


def _write_record(prepared: PreparedImage) -> None:
    """Mark a prepared store complete (every task returned): what :func:`adopt_prepared` checks."""
    ref = prepared.ref
    record = {"kind": ref.kind, "file": Path(ref.path).name, "shape": list(ref.shape), "dtype": ref.dtype,
              "box": [list(b) for b in prepared.box], "grid": list(prepared.grid), "compressed": prepared.compressed}
    path = record_path(ref.path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(record))
    os.replace(tmp, path)


def adopt_prepared(scratch: Path, level: int, grid: tuple[float, float], *, local: bool):
    """The prepared ``g`` of ``level`` an interrupted run completed in ``scratch`` (its latest
    build), as ``(PreparedImage, build number)``; None when there is none this run can use.

    Used only when its record is there (written after every task returned), its grid is the
    one this run prepares on (the same scratch layout and precision), it is of a kind this
    run may read (a memory-mapped ``.npy`` file only when every task is local) and its data
    are whole: the ``.npy`` file at its full length, every chunk file of a Zarr store whole
    (:func:`chunkdic.io.store.chunk_file_is_whole`).
    """
    found = []
    for rec in Path(scratch).glob(f"g-level{int(level)}-*.prepared.json"):
        try:
            found.append((int(rec.name[len(f"g-level{int(level)}-"):].split(".")[0]), rec))
        except ValueError:
            continue
    if not found:
        return None
    k, rec = max(found)
    try:
        info = json.loads(rec.read_text())
        ref = ArrayRef(info["kind"], str(Path(scratch, info["file"])), "", tuple(info["shape"]), info["dtype"])
        box = tuple(tuple(int(v) for v in b) for b in info["box"])
        same = (tuple(float(v) for v in info["grid"]) == tuple(float(v) for v in grid)
                and tuple(b - a for a, b in box) == ref.shape and (ref.kind == "zarr" or local)
                and _whole(ref, bool(info["compressed"])))
    except Exception:  # noqa: BLE001 - a record or store that cannot be read: prepare again
        return None
    return (PreparedImage(ref, box, tuple(grid), bool(info["compressed"])), k) if same else None


def _whole(ref: ArrayRef, compressed: bool) -> bool:
    """The prepared store holds all its bytes (and is what its record says)."""
    if ref.kind == "npy":
        arr = np.load(ref.path, mmap_mode="r")
        whole = (tuple(arr.shape) == ref.shape and arr.dtype == np.dtype(ref.dtype)
                 and Path(ref.path).stat().st_size == arr.offset + arr.nbytes)
        del arr
        return whole
    import zarr

    from ..io.store import chunk_file_is_whole

    arr = zarr.open_array(ref.path, mode="r")
    if tuple(arr.shape) != ref.shape or arr.dtype != np.dtype(ref.dtype) or bool(tuple(arr.compressors)) != compressed:
        return False
    grid = [-(-n // c) for n, c in zip(arr.shape, arr.chunks)]
    return all(chunk_file_is_whole(arr, index) for index in np.ndindex(*grid))

"""Scans on disk: picklable array handles, ``open_scan``, lazy pyramid levels, safe writes.

Tasks never receive voxels: they receive an :class:`ArrayRef` (a path and a key) and read
the region they need straight from the store.

A stored scan is one Zarr v3 group with arrays ``"0"``, ``"1"``, ... (level ``s`` is the
sum over ``2^s`` voxels per axis of level 0, odd trailing voxels trimmed) and OME-NGFF 0.5
``multiscales`` metadata. Every level array is created with
``attrs["chunkdic"] = {"level": s, "complete": False}``, filled region by region by Dask
tasks that each own whole Zarr chunks, and only then marked ``complete``; readers ignore
levels that are not complete.

References
----------
Roux, Hild, Viot, Bernard, *Three dimensional image correlation from X-ray computed
tomography of solid foam*, sections 3 (multiscale) and 4.1 (4^3 super-voxel compression,
which is pyramid level 2 here).
"""

from __future__ import annotations

import concurrent.futures
import functools
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import config
from .errors import InputError

log = logging.getLogger(__name__)

Region = tuple[slice, slice, slice]


@functools.lru_cache(maxsize=64)
def _open_zarr_array(path: str, key: str):
    import zarr

    return zarr.open_array(store=path, path=key or None, mode="r")


@functools.lru_cache(maxsize=64)
def _open_npy(path: str):
    return np.load(path, mmap_mode="r")


@dataclass(frozen=True)
class ArrayRef:
    """A 3-D array on disk that any process can open by path.

    Parameters
    ----------
    kind : {"zarr", "npy"}
        Storage kind.
    path : str
        File-system path of the Zarr store root, or of the ``.npy`` file.
    key : str
        Path of the array inside the Zarr store (``""`` for a root array).
    shape : tuple of 3 int
        Array shape ``(nz, ny, nx)``.
    dtype : str
        NumPy dtype name.
    """

    kind: str
    path: str
    key: str
    shape: tuple[int, int, int]
    dtype: str

    def open(self):
        """Return the opened array (cached per process); supports ``[...]`` slicing."""
        if self.kind == "zarr":
            return _open_zarr_array(self.path, self.key)
        if self.kind == "npy":
            return _open_npy(self.path)
        raise ValueError(f"unknown array kind {self.kind!r}")

    def read(self, region: Region) -> np.ndarray:
        """Read ``region`` (slices clipped to the array by the caller) as a NumPy array."""
        return np.asarray(self.open()[region])

    @property
    def ndim(self) -> int:
        return 3


def forget_open_arrays() -> None:
    """Forget cached handles in this process (a store may have been rewritten)."""
    _open_zarr_array.cache_clear()
    _open_npy.cache_clear()


# --------------------------------------------------------------------------------------
# Units, voxel sizes, dtypes
# --------------------------------------------------------------------------------------

# OME-NGFF space units (UDUNITS-2 names) and the spellings users type.
_SPACE_UNITS = {
    "angstrom", "attometer", "centimeter", "decimeter", "exameter", "femtometer", "foot",
    "gigameter", "hectometer", "inch", "kilometer", "megameter", "meter", "micrometer",
    "mile", "millimeter", "nanometer", "parsec", "petameter", "picometer", "terameter",
    "yard", "yoctometer", "yottameter", "zeptometer", "zettameter",
}
_UNIT_ALIASES = {
    "um": "micrometer", "µm": "micrometer", "μm": "micrometer", "micron": "micrometer",
    "microns": "micrometer", "micrometre": "micrometer", "mm": "millimeter",
    "millimetre": "millimeter", "nm": "nanometer", "nanometre": "nanometer",
    "cm": "centimeter", "m": "meter", "metre": "meter", "a": "angstrom", "å": "angstrom",
    "pm": "picometer",
}


def _normalize_unit(unit) -> str | None:
    """Return the OME-NGFF spelling of ``unit`` (``"um"`` -> ``"micrometer"``)."""
    if unit is None:
        return None
    u = str(unit).strip()
    if not u:
        return None
    low = u.lower()
    low = _UNIT_ALIASES.get(low, low)
    if low not in _SPACE_UNITS:
        raise InputError(
            f"unknown length unit {unit!r}: use an OME-NGFF unit such as micrometer, "
            "millimeter or nanometer (um, mm, nm also accepted)"
        )
    return low


def _normalize_voxel_size(voxel_size) -> tuple[float, float, float] | None:
    """``4.9`` or ``(vz, vy, vx)`` -> a tuple of 3 positive floats (or ``None``)."""
    if voxel_size is None:
        return None
    if isinstance(voxel_size, str):
        voxel_size = [v for v in voxel_size.replace(" ", ",").split(",") if v]
    try:
        values = [float(v) for v in np.atleast_1d(np.asarray(voxel_size, dtype=object))]
    except (TypeError, ValueError):
        raise InputError(f"voxel size {voxel_size!r} is not a number or 3 numbers (z,y,x)") from None
    if len(values) == 1:
        values = values * 3
    if len(values) != 3 or not all(np.isfinite(v) and v > 0 for v in values):
        raise InputError(f"voxel size {voxel_size!r} must be one positive number or 3 (z,y,x)")
    return tuple(values)


def pyramid_dtype(base_dtype, s: int) -> np.dtype:
    """Dtype of pyramid level ``s`` for a level-0 scan of ``base_dtype``.

    Integers: the smallest integer dtype holding ``max(base) * 8**s`` (and
    ``min(base) * 8**s``) exactly, unsigned if the base is unsigned. Floats: float32
    (float64 stays float64). Level 0 keeps the base dtype.

    Parameters
    ----------
    base_dtype : dtype-like
        Level-0 dtype.
    s : int
        Pyramid level (0, 1, ...).

    Returns
    -------
    numpy.dtype

    Examples
    --------
    >>> [pyramid_dtype("uint8", s).name for s in range(4)]
    ['uint8', 'uint16', 'uint16', 'uint32']
    """
    base = np.dtype(base_dtype)
    if base.kind not in "buif":
        raise InputError(f"unsupported scan dtype {base} (use an integer or float type)")
    base = base.newbyteorder("=")
    if s < 0:
        raise InputError(f"pyramid level must be >= 0, got {s}")
    if s == 0:
        return base
    if base.kind == "f":
        return np.dtype(np.float64) if base.itemsize >= 8 else np.dtype(np.float32)
    if base.kind == "b":
        base = np.dtype(np.uint8)
    info = np.iinfo(base)
    lo, hi = int(info.min) * 8**s, int(info.max) * 8**s
    candidates = ("uint8", "uint16", "uint32", "uint64") if lo >= 0 else ("int8", "int16", "int32", "int64")
    for name in candidates:
        ci = np.iinfo(name)
        if ci.min <= lo and hi <= ci.max:
            return np.dtype(name)
    raise InputError(f"level {s} sums of {base} data do not fit in 64-bit integers: use fewer levels")


# --------------------------------------------------------------------------------------
# 2x2x2 sums
# --------------------------------------------------------------------------------------


def _coarsen_block_numpy(block: np.ndarray, dtype) -> np.ndarray:
    """2x2x2 sum of one NumPy block (odd trailing voxels dropped) in ``dtype``; NumPy twin."""
    dtype = np.dtype(dtype)
    work = np.float64 if dtype.kind == "f" else dtype
    nz, ny, nx = (n // 2 for n in block.shape)
    x = block[: 2 * nz, : 2 * ny, : 2 * nx]
    x = np.add(x[0::2], x[1::2], dtype=work)  # z pairs, widened on the first add
    x = x[:, 0::2] + x[:, 1::2]
    x = x[:, :, 0::2] + x[:, :, 1::2]
    return x.astype(dtype, copy=False)


def _sum2_kernel(x, out):  # pragma: no cover - compiled by numba
    """``out[k, j, i]`` = sum of the 2x2x2 voxels of ``x`` at ``(2k, 2j, 2i)``; one pass."""
    nz, ny, nx = out.shape
    for k in range(nz):
        for j in range(ny):
            a, b = x[2 * k, 2 * j], x[2 * k, 2 * j + 1]
            c, d = x[2 * k + 1, 2 * j], x[2 * k + 1, 2 * j + 1]
            o = out[k, j]
            for i in range(nx):
                i2 = 2 * i
                o[i] = (np.int64(a[i2]) + a[i2 + 1] + b[i2] + b[i2 + 1]
                        + c[i2] + c[i2 + 1] + d[i2] + d[i2 + 1])


@functools.lru_cache(maxsize=1)
def _sum2_numba():
    """The numba-compiled :func:`_sum2_kernel` (serial, ``nogil``: Dask gives the
    parallelism), or ``None`` without numba. About 10x the NumPy twin (4 GB/s vs
    0.3-0.4 GB/s per core on 256^3 uint8 blocks)."""
    try:
        import numba
    except ImportError:  # pragma: no cover
        return None
    return numba.njit(nogil=True, cache=True)(_sum2_kernel)


def _coarsen_block(block: np.ndarray, dtype) -> np.ndarray:
    """2x2x2 sum of one NumPy block (odd trailing voxels dropped) in ``dtype``.

    Integer data up to 32 bits go through the numba kernel (exact: int64 accumulation,
    ``dtype`` holds the sums by :func:`pyramid_dtype`); floats and the rest through NumPy.
    """
    dtype = np.dtype(dtype)
    src = block.dtype
    if dtype.kind in "ui" and src.kind in "ui" and src.itemsize <= 4 and src.isnative:
        kernel = _sum2_numba()
        if kernel is not None:
            out = np.empty(tuple(n // 2 for n in block.shape), dtype)
            kernel(block, out)
            return out
    return _coarsen_block_numpy(block, dtype)


def _default_sum_dtype(dtype) -> np.dtype:
    d = np.dtype(dtype)
    return pyramid_dtype(d, 1)


def _even_chunks(chunks: tuple[int, ...], n: int, target: int) -> tuple[int, ...]:
    """Chunks of an axis of (even) length ``n``: keep them if all even, else regular ``target``."""
    if all(c % 2 == 0 for c in chunks):
        return chunks
    target = max(2, target - target % 2)
    full, rest = divmod(n, target)
    return (target,) * full + ((rest,) if rest else ())


def coarsen_sum(a, dtype=None, *, chunk: int | None = None):
    """Sum over 2x2x2 voxels (one pyramid step), odd trailing voxels trimmed.

    Parameters
    ----------
    a : dask.array.Array or numpy.ndarray, shape (nz, ny, nx)
        Level ``s`` of a scan (any numeric dtype).
    dtype : dtype-like, optional
        Output dtype; default ``pyramid_dtype(a.dtype, 1)`` (integers widened so that
        sums stay exact, floats float32).
    chunk : int, optional
        Chunk edge of the result (dask input only); default: half the input chunks.

    Returns
    -------
    Same kind as ``a``, shape ``(nz // 2, ny // 2, nx // 2)``, ``dtype``.

    Examples
    --------
    >>> import numpy as np
    >>> coarsen_sum(np.ones((5, 4, 4), np.uint8)).shape
    (2, 2, 2)
    """
    dtype = _default_sum_dtype(a.dtype) if dtype is None else np.dtype(dtype)
    if a.ndim != 3:
        raise InputError(f"coarsen_sum needs a 3-D array, got shape {a.shape}")
    if isinstance(a, np.ndarray):
        return _coarsen_block(a, dtype)
    a = a[tuple(slice(0, 2 * (n // 2)) for n in a.shape)]
    if chunk is not None:
        a = a.rechunk(tuple(min(2 * chunk, max(n, 1)) for n in a.shape))
    a = a.rechunk(tuple(_even_chunks(c, n, max(c)) for c, n in zip(a.chunks, a.shape)))
    out_chunks = tuple(tuple(c // 2 for c in cs) for cs in a.chunks)
    return a.map_blocks(_coarsen_block, dtype, dtype=dtype, chunks=out_chunks,
                        meta=np.empty((0, 0, 0), dtype))


# --------------------------------------------------------------------------------------
# Safe chunk-aligned writes
# --------------------------------------------------------------------------------------


def _compressors(dtype):
    """Compressor of every array chunkdic writes (measurements in docs/scans.md).

    ``chunkdic.compressor`` (dask config): ``"auto"`` (default: zstd level 1 for 1-byte
    samples, blosc-lz4 with bit shuffle for wider ones, i.e. 16/32-bit scans and every
    pyramid level), ``"zstd"``, ``"lz4"`` (blosc-lz4 + bit shuffle) or ``"none"``.
    """
    import dask.config
    from zarr.codecs import BloscCodec, ZstdCodec

    name = str(dask.config.get("chunkdic.compressor", default="auto")).lower()
    itemsize = np.dtype(dtype).itemsize
    if name == "auto":
        name = "zstd" if itemsize == 1 else "lz4"
    if name == "zstd":
        return (ZstdCodec(level=1),)
    if name == "lz4":
        return (BloscCodec(cname="lz4", clevel=5, shuffle="bitshuffle", typesize=itemsize),)
    if name == "none":
        return None
    raise InputError(f"chunkdic.compressor={name!r}: use auto, zstd, lz4 or none")


def _chunk_shape(shape, chunks) -> tuple[int, int, int]:
    if chunks is None:
        chunks = config.get("chunk-size")
    c = tuple(int(v) for v in np.broadcast_to(np.asarray(chunks), (3,)))
    if any(v < 1 for v in c):
        raise InputError(f"chunk edge must be a positive integer, got {chunks!r}")
    return tuple(max(1, min(v, n)) for v, n in zip(c, shape))


def check_write_alignment(dask_chunks, shape, unit, name: str = "array") -> None:
    """Raise :class:`InputError` unless each Dask block covers whole write units.

    Zarr 3.1 loses data silently when concurrent tasks write parts of the same chunk or
    shard, so every block boundary must fall on a multiple of the write unit (the shard
    shape for a sharded array, else the chunk shape) or on the array end.

    Parameters
    ----------
    dask_chunks : tuple of 3 tuples of int
        ``dask_array.chunks``.
    shape : tuple of 3 int
        Array shape.
    unit : tuple of 3 int
        Zarr shard shape (sharded) or chunk shape.
    """
    for axis, (cs, n, u) in enumerate(zip(dask_chunks, shape, unit)):
        edges = np.cumsum((0,) + tuple(cs))
        if edges[-1] != n:
            raise InputError(f"{name}: dask chunks cover {edges[-1]} voxels along axis {'zyx'[axis]}, the array has {n}")
        bad = [int(e) for e in edges[1:-1] if e % u]
        if bad:
            raise InputError(
                f"{name}: dask block boundaries along {'zyx'[axis]} at {bad[:4]} are not multiples of the "
                f"Zarr chunk/shard edge {u}; every writing task must own whole chunks/shards "
                f"(zarr 3.1 silently loses data otherwise): rechunk to multiples of {u}"
            )


def _write_block(block: np.ndarray, path: str, key: str, block_info=None) -> np.ndarray:
    import zarr

    loc = block_info[0]["array-location"]
    region = tuple(slice(a, b) for a, b in loc)
    arr = zarr.open_array(store=path, path=key or None, mode="r+")
    # Skipping the per-chunk "all fill value?" test makes zarr 3.1 writes 2-3x faster
    # (measured, docs/scans.md); a chunk of zeros then costs a few bytes on disk.
    arr = arr.with_config({"write_empty_chunks": True})
    arr[region] = block
    return np.ones((1, 1, 1), np.int64)


class _Progress:
    """A ``dask`` local-scheduler callback reporting finished tasks to ``fn(fraction)``.

    ``start``/``end`` map this computation into a sub-range of a longer operation.
    """

    def __init__(self, fn, start=0.0, end=1.0):
        self.fn, self.start, self.end = fn, start, end
        self._cb = None

    def __enter__(self):
        if self.fn is None:
            return self
        from dask.callbacks import Callback

        total, done, last = [1], [0], [-1.0]

        def _start_state(dsk, state):
            total[0] = max(1, len(state["ready"]) + len(state["waiting"]) + len(state["running"]))

        def _posttask(key, result, dsk, state, worker_id):
            done[0] += 1
            frac = self.start + (self.end - self.start) * min(1.0, done[0] / total[0])
            if frac - last[0] >= 0.01:
                last[0] = frac
                self.fn(frac)

        self._cb = Callback(start_state=_start_state, posttask=_posttask)
        self._cb.__enter__()
        return self

    def __exit__(self, *exc):
        if self._cb is not None:
            self._cb.__exit__(*exc)
        if exc[0] is None and self.fn is not None:
            self.fn(self.end)
        return False


def _compute(x, progress=None, start=0.0, end=1.0):
    """Compute the dask array ``x`` (one small block per written chunk), reporting progress.

    On the local threaded scheduler use our own pool and, on failure, wait for the running
    tasks before returning so that callers can clean up safely. On a ``distributed``
    client, progress comes from the blocks' futures as they finish (local-scheduler
    callbacks never fire there).
    """
    import dask
    import dask.threaded
    from dask.base import get_scheduler

    sched = get_scheduler(collections=[x])
    client = getattr(sched, "__self__", None)  # the bound ``Client.get`` of a distributed client
    if progress is not None and client is not None:
        from distributed import Client

        if isinstance(client, Client):
            return _compute_on_client(client, x, progress, start, end)
    with _Progress(progress, start, end):
        if sched is None or sched is dask.threaded.get:
            n = config.get("num-threads") or os.cpu_count() or 1
            pool = concurrent.futures.ThreadPoolExecutor(n)
            try:
                return dask.compute(x, scheduler="threads", pool=pool)[0]
            finally:
                pool.shutdown(wait=True, cancel_futures=True)
        return dask.compute(x)[0]


def _compute_on_client(client, x, progress, start: float, end: float) -> None:
    """Run the blocks of ``x`` on a distributed ``client``, calling ``progress(fraction)``
    (at most every 1 %) as their futures finish; on failure cancel what has not run."""
    from distributed import as_completed

    futures = client.compute(list(x.to_delayed().ravel()))
    done, last = 0, -1.0
    try:
        for fut in as_completed(futures):
            fut.result()  # raises the task's error here
            done += 1
            frac = start + (end - start) * done / len(futures)
            if frac - last >= 0.01:
                last = frac
                progress(float(frac))
    except BaseException:
        client.cancel(futures)
        raise
    if last < end:
        progress(end)


def _store(data, path: str, key: str, progress=None, start=0.0, end=1.0) -> None:
    """Write dask array ``data`` into the existing Zarr array ``path``/``key``, block by block.

    Each task owns whole chunks (shards): checked up front.
    """
    import zarr

    arr = zarr.open_array(store=path, path=key or None, mode="r+")
    if tuple(arr.shape) != tuple(data.shape):
        raise InputError(f"cannot write an array of shape {data.shape} into {path}/{key} of shape {arr.shape}")
    unit = arr.shards if getattr(arr, "shards", None) else arr.chunks
    check_write_alignment(data.chunks, data.shape, unit, name=f"{path}/{key}")
    out_chunks = tuple((1,) * len(c) for c in data.chunks)
    done = data.map_blocks(_write_block, path=str(path), key=key, dtype=np.int64, chunks=out_chunks,
                           meta=np.empty((0, 0, 0), np.int64))
    _compute(done, progress, start, end)


def _aligned(data, chunk_shape):
    """``data`` unchanged if its blocks own whole chunks, else rechunked to the chunk grid."""
    try:
        check_write_alignment(data.chunks, data.shape, chunk_shape)
        return data
    except InputError:
        return data.rechunk(chunk_shape)


# --------------------------------------------------------------------------------------
# Groups, levels, OME-NGFF metadata
# --------------------------------------------------------------------------------------


def _ngff_attrs(levels, voxel_size, unit, name) -> dict:
    vs = voxel_size or (1.0, 1.0, 1.0)
    axes = []
    for ax in "zyx":
        a = {"name": ax, "type": "space"}
        if unit and voxel_size is not None:
            a["unit"] = unit
        axes.append(a)
    datasets = []
    for s in levels:
        f = 2**s
        datasets.append({
            "path": str(s),
            "coordinateTransformations": [
                {"type": "scale", "scale": [v * f for v in vs]},
                {"type": "translation", "translation": [v * (f - 1) / 2 for v in vs]},
            ],
        })
    return {
        "version": "0.5",
        "multiscales": [{
            "name": name,
            "axes": axes,
            "datasets": datasets,
            "type": "sum",
            "metadata": {
                "description": "level s is the sum over 2^s voxels per axis of level 0 (odd trailing voxels "
                               "trimmed); voxel centre of level s at level-0 coordinate 2^s*j + (2^s-1)/2",
                "method": "chunkdic.volume.coarsen_sum",
            },
        }],
    }


def _complete_levels(group) -> list[int]:
    out = []
    for name in sorted((k for k in group.array_keys() if k.isdigit()), key=int):
        info = group[name].attrs.get("chunkdic") or {}
        if info.get("complete") is True:
            out.append(int(name))
    return out


def _update_group_metadata(path: str) -> None:
    """Rewrite the NGFF ``multiscales`` of group ``path`` to list its complete levels 0..k."""
    import zarr

    g = zarr.open_group(store=path, mode="r+")
    info = dict(g.attrs.get("chunkdic") or {})
    complete = _complete_levels(g)
    levels = []
    for s in complete:
        if s != len(levels):
            break
        levels.append(s)
    vs = info.get("voxel_size")
    attrs = {"chunkdic": info}
    if levels:
        attrs["ome"] = _ngff_attrs(levels, tuple(vs) if vs else None, info.get("unit"), Path(path).name)
    else:
        attrs["ome"] = {"version": "0.5"}
    g.update_attributes(attrs)


def _create_level(path: str, s: int, shape, dtype, chunk_shape):
    """(Re)create level array ``s`` of group ``path``, flagged incomplete."""
    import zarr

    g = zarr.open_group(store=path, mode="r+")
    if str(s) in g:
        del g[str(s)]
    g.create_array(
        str(s), shape=tuple(int(n) for n in shape), dtype=np.dtype(dtype), chunks=tuple(chunk_shape),
        compressors=_compressors(dtype), fill_value=0, dimension_names=("z", "y", "x"),
        attributes={"chunkdic": {"level": s, "complete": False}},
    )


def _mark_complete(path: str, s: int) -> None:
    import zarr

    arr = zarr.open_array(store=path, path=str(s), mode="r+")
    arr.update_attributes({"chunkdic": {"level": s, "complete": True}})


def _write_level(path: str, s: int, data, chunk_shape=None, progress=None, start=0.0, end=1.0) -> ArrayRef:
    """Create level ``s`` in group ``path``, store ``data`` chunk by chunk, mark complete."""
    chunk_shape = _chunk_shape(data.shape, chunk_shape)
    _create_level(path, s, data.shape, data.dtype, chunk_shape)
    _store(_aligned(data, chunk_shape), path, str(s), progress, start, end)
    _mark_complete(path, s)
    forget_open_arrays()
    return ArrayRef("zarr", str(path), str(s), tuple(int(n) for n in data.shape), np.dtype(data.dtype).name)


def _is_zarr_store(path: Path) -> bool:
    return (path / "zarr.json").exists() or (path / ".zgroup").exists() or (path / ".zarray").exists()


def _prepare_output(path, overwrite: bool) -> Path:
    """Refuse an existing output unless ``overwrite`` (and then only a Zarr store)."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        if not overwrite:
            raise InputError(f"output {p} already exists: choose another path or pass overwrite (--overwrite)")
        if not (p.is_dir() and _is_zarr_store(p)):
            raise InputError(f"output {p} exists and is not a Zarr store: refusing to overwrite it, remove it yourself")
        shutil.rmtree(p)
    if not p.parent.exists():
        raise InputError(f"output directory {p.parent} does not exist")
    return p


def _remove_partial(p: Path) -> None:
    """Remove a half-written output (twice: tasks on remote workers may still be finishing)."""
    shutil.rmtree(p, ignore_errors=True)
    if p.exists():
        time.sleep(0.5)
        shutil.rmtree(p, ignore_errors=True)


def write_scan(path, data, *, voxel_size=None, unit=None, chunks=None, overwrite: bool = False,
               levels: int = 0, progress: Callable[[float], None] | None = None) -> "Scan":
    """Write a 3-D array as a stored scan: a Zarr v3 group with OME-NGFF 0.5 metadata.

    Level ``"0"`` is ``data``, written chunk by chunk by Dask (``data`` is never computed
    whole); then ``levels`` pyramid levels are added, each from the stored level below.
    A level is marked complete only after all its chunks are written; if anything fails,
    the output is removed.

    Parameters
    ----------
    path : str or Path
        Group to create (e.g. ``"scan.zarr"``).
    data : dask.array.Array or numpy.ndarray, shape (nz, ny, nx)
        Intensities (integer or float; float data must be finite).
    voxel_size : float or tuple of 3 float, optional
        Physical size of a level-0 voxel ``(z, y, x)`` in ``unit``.
    unit : str, optional
        Length unit (OME-NGFF name, ``"um"``/``"mm"`` accepted).
    chunks : int or tuple of 3 int, optional
        Zarr chunk edge; default ``chunkdic.chunk-size`` (128).
    overwrite : bool
        Replace an existing Zarr store at ``path``.
    levels : int
        Number of pyramid levels to build after level 0.
    progress : callable(float), optional
        Called with the fraction done (0..1), on the threaded scheduler as tasks finish
        and on a distributed client (the current one) as the chunk writes finish.

    Returns
    -------
    Scan

    Examples
    --------
    >>> import dask.array as da, tempfile, os
    >>> d = tempfile.mkdtemp()
    >>> scan = write_scan(os.path.join(d, "s.zarr"), da.ones((9, 8, 8), dtype="uint8", chunks=4), levels=1)
    >>> scan.stored_levels(), scan.shape(1), scan.dtype(1).name
    ([0, 1], (4, 4, 4), 'uint16')
    """
    import dask.array as da
    import zarr

    if isinstance(data, np.ndarray):
        data = da.from_array(data, chunks=_chunk_shape(data.shape, chunks))
    if not hasattr(data, "dask") or getattr(data, "ndim", None) != 3:
        raise InputError(f"write_scan needs a 3-D dask or numpy array, got {type(data).__name__} "
                         f"of shape {getattr(data, 'shape', '?')}")
    if min(data.shape) < 1:
        raise InputError(f"cannot write an empty scan of shape {data.shape}")
    pyramid_dtype(data.dtype, 0)  # dtype check
    voxel_size = _normalize_voxel_size(voxel_size)
    unit = _normalize_unit(unit)
    levels = int(levels)
    _check_levels(data.shape, levels)
    p = _prepare_output(path, overwrite)
    forget_open_arrays()
    weights = [1.0] + [8.0 ** -(s - 1) for s in range(1, levels + 1)]
    cuts = np.cumsum([0.0] + weights) / sum(weights)
    t0 = time.perf_counter()
    try:
        g = zarr.open_group(store=str(p), mode="w-", zarr_format=3)
        g.update_attributes({"chunkdic": {"voxel_size": list(voxel_size) if voxel_size else None,
                                          "unit": unit}, "ome": {"version": "0.5"}})
        _write_level(str(p), 0, data, chunks, progress, cuts[0], cuts[1])
        _update_group_metadata(str(p))
        log.info("level 0 %s %s written to %s in %.1f s", data.shape, data.dtype, p, time.perf_counter() - t0)
        if levels:
            from .pyramid import _build_levels

            _build_levels(str(p), levels, rebuild=True, progress=progress, cuts=cuts)
    except BaseException:
        _remove_partial(p)
        raise
    finally:
        forget_open_arrays()
    return open_scan(str(p))


def _check_levels(shape, levels: int) -> None:
    if levels < 0:
        raise InputError(f"levels must be >= 0, got {levels}")
    deepest = 0
    n = min(shape)
    while n // 2 >= 1:
        n //= 2
        deepest += 1
    if levels > deepest:
        raise InputError(f"{levels} pyramid levels requested but a scan of shape {tuple(shape)} "
                         f"allows at most {deepest} (level {levels} would be empty)")


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


class _RefReader:
    """Array-like over an :class:`ArrayRef` for ``dask.array.from_array`` (small, picklable)."""

    def __init__(self, ref: ArrayRef):
        self.ref = ref
        self.shape = tuple(ref.shape)
        self.dtype = np.dtype(ref.dtype)
        self.ndim = 3

    def __getitem__(self, region):
        return self.ref.read(region)


def _ref_chunks(ref: ArrayRef):
    if ref.kind == "zarr":
        try:
            return tuple(ref.open().chunks)
        except Exception:  # noqa: BLE001 - fall back to the default edge
            pass
    return _chunk_shape(ref.shape, None)


def _ref_dask(ref: ArrayRef, chunks=None):
    """Lazy dask array over an on-disk array (tasks open it by path)."""
    import dask.array as da
    from dask.base import tokenize

    chunks = _ref_chunks(ref) if chunks is None else chunks
    name = "scan-" + tokenize(ref.kind, ref.path, ref.key, ref.shape, ref.dtype, _mtime(ref))
    return da.from_array(_RefReader(ref), chunks=chunks, name=name, asarray=False,
                         meta=np.empty((0, 0, 0), np.dtype(ref.dtype)))


def _mtime(ref: ArrayRef) -> float:
    p = Path(ref.path)
    target = p / ref.key / "zarr.json" if ref.kind == "zarr" else p
    try:
        return target.stat().st_mtime_ns
    except OSError:
        return 0


@dataclass
class Scan:
    """A scan: level 0 plus its ``2^s`` sum pyramid, stored or lazy.

    Attributes
    ----------
    path : str or None
        Group (or array / ``.npy``) path when the scan is stored.
    voxel_size : tuple of 3 float or None
        Physical size of a level-0 voxel ``(z, y, x)`` in ``unit``.
    unit : str or None
        OME-NGFF length unit.
    """

    path: str | None
    voxel_size: tuple[float, float, float] | None
    unit: str | None
    _stored: dict = field(default_factory=dict, repr=False)   # level -> ArrayRef (complete, valid)
    _base: object = field(default=None, repr=False)           # in-memory/dask level 0
    _scratch: dict = field(default_factory=dict, repr=False)  # level -> ArrayRef in scratch
    _scratch_group: str | None = field(default=None, repr=False)

    # -- geometry -----------------------------------------------------------------------
    def _known(self) -> dict:
        """Levels available without computing: level -> (shape, dtype)."""
        out = {s: (tuple(r.shape), np.dtype(r.dtype)) for s, r in {**self._scratch, **self._stored}.items()}
        if 0 not in out and self._base is not None:
            out[0] = (tuple(self._base.shape), np.dtype(self._base.dtype))
        return out

    def _source_level(self, s: int) -> int:
        known = [k for k in self._known() if k <= s]
        if not known:
            raise InputError(f"level {s} cannot be built: no finer level is available")
        return max(known)

    def shape(self, level: int) -> tuple[int, int, int]:
        """Shape ``(nz, ny, nx)`` of pyramid level ``level`` (``n_s = n_0 // 2**s``)."""
        known = self._known()
        k = self._source_level(level)
        shp = known[k][0]
        return tuple(int(n) // 2 ** (level - k) for n in shp)

    def dtype(self, level: int) -> np.dtype:
        """Dtype of level ``level`` (stored dtype, else :func:`pyramid_dtype`)."""
        known = self._known()
        if level in known:
            return known[level][1]
        if 0 in known:
            return pyramid_dtype(known[0][1], level)
        k = self._source_level(level)
        return known[k][1] if known[k][1].kind == "f" else pyramid_dtype(known[k][1], level - k)

    def stored_levels(self) -> list[int]:
        """Levels stored complete and valid in the scan's own store."""
        return sorted(self._stored)

    # -- data ---------------------------------------------------------------------------
    def level(self, s: int):
        """Level ``s`` as a dask array: stored if complete, else 2x2x2 sums built lazily
        from the finest available level below (exact integer sums, odd sizes trimmed)."""
        import dask.array as da

        s = int(s)
        if s < 0:
            raise InputError(f"pyramid level must be >= 0, got {s}")
        ref = self._stored.get(s) or self._scratch.get(s)
        if ref is not None:
            return _ref_dask(ref)
        if s == 0:
            if self._base is None:
                raise InputError("level 0 of this scan is not available")
            if isinstance(self._base, np.ndarray):
                return da.from_array(self._base, chunks=_chunk_shape(self._base.shape, None))
            return self._base
        k = self._source_level(s)
        a = self.level(k)
        c = config.get("chunk-size")
        for t in range(k + 1, s + 1):
            a = coarsen_sum(a, self.dtype(t), chunk=c)
        return a

    def refs(self, levels, scratch_dir=None) -> dict[int, ArrayRef]:
        """On-disk handles for ``levels``: stored levels directly; others written chunk by
        chunk into a Zarr group under ``scratch_dir`` (each from the finest level on disk).

        Parameters
        ----------
        levels : iterable of int
        scratch_dir : str or Path, optional
            Directory for the scratch group (created if needed); default
            ``chunkdic.scratch-directory`` or the system temporary directory.

        Returns
        -------
        dict of int to ArrayRef
        """
        import zarr

        out = {}
        for s in sorted({int(v) for v in levels}):
            ref = self._stored.get(s) or self._scratch.get(s)
            if ref is None:
                if self._scratch_group is None:
                    import tempfile

                    root = Path(scratch_dir or config.get("scratch-directory") or tempfile.gettempdir())
                    root.mkdir(parents=True, exist_ok=True)
                    gpath = root / f"scan-{uuid.uuid4().hex[:12]}.zarr"
                    zarr.open_group(store=str(gpath), mode="w-", zarr_format=3).update_attributes(
                        {"chunkdic": {"voxel_size": list(self.voxel_size) if self.voxel_size else None,
                                      "unit": self.unit, "scratch": True}})
                    self._scratch_group = str(gpath)
                data = self.level(s)
                ref = _write_level(self._scratch_group, s, data)
                self._scratch[s] = ref
                log.info("level %d %s written to scratch %s", s, ref.shape, self._scratch_group)
            out[s] = ref
        return out


# --------------------------------------------------------------------------------------
# open_scan
# --------------------------------------------------------------------------------------

_INGEST_SUFFIXES = (".tif", ".tiff", ".h5", ".hdf5", ".hdf", ".nxs", ".raw", ".vol", ".bin")


def _check_3d(shape, what) -> None:
    if len(shape) != 3:
        raise InputError(f"{what} has shape {tuple(shape)}: a scan must be 3-D (z, y, x)")
    if min(shape) < 1:
        raise InputError(f"{what} is empty (shape {tuple(shape)})")


def _npy_ref(path: Path) -> ArrayRef:
    try:
        a = np.load(path, mmap_mode="r")
    except Exception as e:  # noqa: BLE001
        raise InputError(f"cannot read {path} as a .npy file: {e}") from None
    _check_3d(a.shape, str(path))
    pyramid_dtype(a.dtype, 0)
    return ArrayRef("npy", str(path), "", tuple(int(n) for n in a.shape), a.dtype.name)


def _local_root(store) -> str | None:
    root = getattr(store, "root", None)
    return None if root is None else str(root)


def _voxel_from_group_attrs(attrs) -> tuple:
    info = attrs.get("chunkdic") or {}
    if "voxel_size" in info:
        vs = info.get("voxel_size")
        return (tuple(float(v) for v in vs) if vs else None), info.get("unit")
    ome = attrs.get("ome") or {}
    ms = ome.get("multiscales") or attrs.get("multiscales")
    if not ms:
        return None, None
    try:
        m = ms[0]
        scale = np.ones(3)
        for t in m["datasets"][0].get("coordinateTransformations", []):
            if t.get("type") == "scale":
                scale = scale * np.asarray(t["scale"], float)[-3:]
        for t in m.get("coordinateTransformations", []) or []:
            if t.get("type") == "scale":
                scale = scale * np.asarray(t["scale"], float)[-3:]
        units = {a.get("unit") for a in m.get("axes", [])[-3:] if isinstance(a, dict)}
        unit = units.pop() if len(units) == 1 else None
        return tuple(float(v) for v in scale), unit
    except (KeyError, IndexError, TypeError, ValueError):
        return None, None


def _scan_from_group(g, root: str, where: str) -> Scan:
    prefix = g.path.strip("/")
    attrs = g.attrs.asdict()
    names = [k for k in g.array_keys() if k.isdigit()]
    ours = "chunkdic" in attrs or any("chunkdic" in g[k].attrs for k in names)
    stored = {}
    if ours:
        complete = _complete_levels(g)
        if 0 not in complete:
            raise InputError(f"{where}: level 0 is missing or incomplete (interrupted write?): "
                             "write or ingest the scan again")
        candidates = complete
    else:
        ms = (attrs.get("ome") or {}).get("multiscales") or attrs.get("multiscales")
        first = None
        if ms:
            try:
                first = ms[0]["datasets"][0]["path"]
            except (KeyError, IndexError, TypeError):
                first = None
        if first is None and "0" in names:
            first = "0"
        if first is None or first not in g:
            raise InputError(f"{where}: Zarr group without a level '0' array (expected arrays '0', '1', ...)")
        a = g[first]
        _check_3d(a.shape, f"{where}/{first}")
        key = f"{prefix}/{first}" if prefix else first
        stored[0] = ArrayRef("zarr", root, key, tuple(int(n) for n in a.shape), a.dtype.name)
        candidates = []
    for s in candidates:
        a = g[str(s)]
        key = f"{prefix}/{s}" if prefix else str(s)
        if s == 0:
            _check_3d(a.shape, f"{where}/0")
            pyramid_dtype(a.dtype, 0)
            stored[0] = ArrayRef("zarr", root, key, tuple(int(n) for n in a.shape), a.dtype.name)
            continue
        shp0, d0 = stored[0].shape, np.dtype(stored[0].dtype)
        expected = tuple(n // 2**s for n in shp0)
        if tuple(a.shape) != expected or np.dtype(a.dtype) != pyramid_dtype(d0, s):
            log.warning("%s: level %d has shape %s dtype %s, expected %s %s: ignored", where, s,
                        a.shape, a.dtype, expected, pyramid_dtype(d0, s))
            continue
        stored[s] = ArrayRef("zarr", root, key, expected, a.dtype.name)
    vs, unit = _voxel_from_group_attrs(attrs)
    return Scan(path=os.path.join(root, prefix) if prefix else root, voxel_size=vs, unit=unit, _stored=stored)


def _scan_from_zarr(node, where: str) -> Scan:
    import dask.array as da
    import zarr

    root = _local_root(node.store)
    if isinstance(node, zarr.Group):
        if root is None:
            raise InputError(f"{where}: only Zarr groups on a local file system are supported; "
                             "pass the level array instead")
        return _scan_from_group(node, root, where)
    _check_3d(node.shape, where)
    pyramid_dtype(node.dtype, 0)
    if root is None:  # in-memory or remote store: treat as a lazy array
        return Scan(path=None, voxel_size=None, unit=None, _base=da.from_zarr(node))
    key = node.path.strip("/")
    ref = ArrayRef("zarr", root, key, tuple(int(n) for n in node.shape), node.dtype.name)
    return Scan(path=os.path.join(root, key) if key else root, voxel_size=None, unit=None, _stored={0: ref})


def open_scan(src, *, voxel_size=None, unit=None) -> Scan:
    """Open a scan for reading, whatever form it comes in.

    Parameters
    ----------
    src : str, Path, numpy.ndarray, dask.array.Array, zarr.Array, zarr.Group or Scan
        A Zarr v3 scan group (levels ``"0"``, ``"1"``, ...; voxel size read from its
        metadata), a Zarr array (root array or ``group.zarr/0``), a ``.npy`` file (memory
        mapped, never loaded whole), or an array, shape ``(nz, ny, nx)``.
    voxel_size : float or tuple of 3 float, optional
        Overrides the voxel size found in the metadata.
    unit : str, optional
        Overrides the unit found in the metadata.

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Missing path, unreadable store, unsupported type, not 3-D.

    Examples
    --------
    >>> import numpy as np
    >>> open_scan(np.zeros((4, 5, 6), np.uint8)).shape(1)
    (2, 2, 3)
    """
    scan = _open(src)
    if voxel_size is not None:
        scan.voxel_size = _normalize_voxel_size(voxel_size)
    if unit is not None:
        scan.unit = _normalize_unit(unit)
    return scan


def _open(src) -> Scan:
    import zarr

    if isinstance(src, Scan):
        return Scan(path=src.path, voxel_size=src.voxel_size, unit=src.unit, _stored=dict(src._stored),
                    _base=src._base, _scratch=dict(src._scratch), _scratch_group=src._scratch_group)
    if isinstance(src, np.ndarray):
        _check_3d(src.shape, "the array")
        pyramid_dtype(src.dtype, 0)
        return Scan(path=None, voxel_size=None, unit=None, _base=src)
    if hasattr(src, "dask") and hasattr(src, "chunks") and hasattr(src, "shape"):
        _check_3d(src.shape, "the dask array")
        pyramid_dtype(src.dtype, 0)
        return Scan(path=None, voxel_size=None, unit=None, _base=src)
    if isinstance(src, (zarr.Array, zarr.Group)):
        return _scan_from_zarr(src, str(getattr(src, "store", "zarr")))
    if not isinstance(src, (str, os.PathLike)):
        raise InputError(f"cannot open a scan from {type(src).__name__}: pass a Zarr path, a .npy path, "
                         "a NumPy or Dask array")
    p = Path(src)
    if not p.exists():
        raise InputError(f"scan {p} does not exist")
    if p.is_file():
        if p.suffix.lower() == ".npy":
            ref = _npy_ref(p)
            return Scan(path=str(p), voxel_size=None, unit=None, _stored={0: ref})
        hint = " (convert it with `chunkdic ingest`)" if p.suffix.lower() in _INGEST_SUFFIXES else ""
        raise InputError(f"{p} is not a Zarr store or a .npy file{hint}")
    try:
        node = zarr.open(store=str(p), mode="r")
    except Exception as e:  # noqa: BLE001
        hint = " (a folder of TIFF slices? convert it with `chunkdic ingest`)" if any(
            f.suffix.lower() in (".tif", ".tiff") for f in p.iterdir()) else ""
        raise InputError(f"cannot read {p} as a Zarr store{hint}: {type(e).__name__}: {e}".splitlines()[0]) from None
    return _scan_from_zarr(node, str(p))

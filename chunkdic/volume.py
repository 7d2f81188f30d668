"""Scans on disk: picklable array handles, ``open_scan``, lazy pyramid levels, safe writes.

Tasks never receive voxels: they receive an :class:`ArrayRef` (a path and a key) and read
the region they need straight from the store.

A stored scan is one Zarr v3 group with arrays ``"0"``, ``"1"``, ... (level ``s`` is the
sum over ``2^s`` voxels per axis of level 0, odd trailing voxels trimmed) and OME-NGFF 0.5
``multiscales`` metadata. Every level array is created with
``attrs["chunkdic"] = {"level": s, "complete": False}``, filled region by region by Dask
tasks that each own whole Zarr chunks, and only then marked ``complete``; readers ignore
levels that are not complete.

The 2x2x2 sums live in :mod:`chunkdic.coarsen`, the chunk-aligned Zarr writes in
:mod:`chunkdic.store` and the OME-NGFF metadata in :mod:`chunkdic.ngff`.

References
----------
Roux, Hild, Viot, Bernard, *Three dimensional image correlation from X-ray computed
tomography of solid foam*, sections 3 (multiscale) and 4.1 (4^3 super-voxel compression,
which is pyramid level 2 here).
"""

from __future__ import annotations

import functools
import logging
import os
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import config
from .coarsen import coarsen_sum, pyramid_dtype
from .errors import InputError
from .integrity import check_chunks_present, damaged_read_error
from .outputs import Outputs
from .ngff import (
    _complete_levels,
    _normalize_unit,
    _normalize_voxel_size,
    _update_group_metadata,
    _voxel_from_group_attrs,
)
from .store import _aligned, _chunk_shape, _compressors, _store

log = logging.getLogger(__name__)

Region = tuple[slice, slice, slice]


@functools.lru_cache(maxsize=64)
def _open_zarr_array(path: str, key: str):
    import zarr

    return zarr.open_array(store=path, path=key or None, mode="r")


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
        """Return the opened array, supporting ``[...]`` slicing.

        Zarr handles are cached per process. A ``.npy`` file is mapped anew on every
        call: a mapping kept open counts every page it ever touched in the process's
        RSS, which is what Dask's nanny watches (see :meth:`read`).
        """
        if self.kind == "zarr":
            return _open_zarr_array(self.path, self.key)
        if self.kind == "npy":
            return np.load(self.path, mmap_mode="r")
        raise ValueError(f"unknown array kind {self.kind!r}")

    def read(self, region: Region) -> np.ndarray:
        """Read ``region`` (slices clipped to the array by the caller) as a NumPy array.

        The result is a copy; a ``.npy`` mapping is dropped on return. A worker that
        kept one mapping across the tasks of a level-0 correlation of 1024³ reached
        4.3 GiB RSS (every coefficient page it had read); mapping per read holds it
        to one window.
        """
        try:
            a = self.open()[region]
            return np.array(a) if self.kind == "npy" else np.asarray(a)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - a damaged store: name the chunk (no cost when reads succeed)
            if self.kind == "zarr":
                raise damaged_read_error(self.path, self.key, region, exc) from None
            raise InputError(f"{self.path}: cannot read the region "
                             f"{tuple((s.start, s.stop) for s in region)} ({type(exc).__name__}: {exc}); "
                             "the file is damaged or truncated".splitlines()[0]) from None

    @property
    def ndim(self) -> int:
        return 3


def forget_open_arrays() -> None:
    """Forget cached handles in this process (a store may have been rewritten)."""
    _open_zarr_array.cache_clear()


# --------------------------------------------------------------------------------------
# Groups and levels
# --------------------------------------------------------------------------------------



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


def write_scan(path, data, *, voxel_size=None, unit=None, chunks=None, overwrite: bool = False,
               levels: int = 0, progress: Callable[[float], None] | None = None, inputs=(),
               parents: bool = False) -> "Scan":
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
        Replace an existing scan that chunkdic wrote at ``path`` (nothing else is ever
        replaced; see :mod:`chunkdic.outputs`).
    parents : bool
        Create missing parent directories of ``path`` (removed again if the write fails).
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
    plan = Outputs(inputs=inputs, overwrite=overwrite)
    entry = plan.add(path, "scan", parents=parents)  # every check before anything is written
    forget_open_arrays()
    weights = [1.0] + [8.0 ** -(s - 1) for s in range(1, levels + 1)]
    cuts = np.cumsum([0.0] + weights) / sum(weights)
    t0 = time.perf_counter()
    try:
        with plan:  # written to a hidden sibling, renamed into place once complete
            p = entry.work
            g = zarr.open_group(store=str(p), mode="w-", zarr_format=3)
            g.update_attributes({"chunkdic": {"kind": "scan", "voxel_size": list(voxel_size) if voxel_size else None,
                                              "unit": unit}, "ome": {"version": "0.5"}})
            _write_level(str(p), 0, data, chunks, progress, cuts[0], cuts[1])
            _update_group_metadata(str(p))
            log.info("level 0 %s %s written to %s in %.1f s", data.shape, data.dtype, path,
                     time.perf_counter() - t0)
            if levels:
                from .pyramid import _build_levels

                _build_levels(str(p), levels, rebuild=True, progress=progress, cuts=cuts)
    finally:
        forget_open_arrays()
    return open_scan(str(path))


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

    def stored_refs(self) -> dict[int, ArrayRef]:
        """Level -> on-disk handle of the levels stored in the scan's own store."""
        return dict(self._stored)

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
                        {"chunkdic": {"kind": "scratch", "voxel_size": list(self.voxel_size) if self.voxel_size else None,
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
    for ref in stored.values():  # a missing chunk file would read as zeros (integrity.py)
        check_chunks_present(ref.path, ref.key, ours=ours)
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
    level = (node.attrs.get("chunkdic") or {}).get("level") if hasattr(node.attrs, "get") else None
    check_chunks_present(root, key, ours=level is not None)
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
    try:
        return _scan_from_zarr(node, str(p))
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - a damaged level's metadata (zarr.json), say
        raise InputError(f"cannot read {p} as a Zarr store: {type(e).__name__}: {e}; the store is damaged"
                         .splitlines()[0]) from None

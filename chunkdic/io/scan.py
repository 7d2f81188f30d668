"""Reading scans: ``open_scan`` and the :class:`Scan` with its lazy pyramid levels.

A stored scan is one Zarr v3 group with arrays ``"0"``, ``"1"``, ... (level ``s`` is the
sum over ``2^s`` voxels per axis of level 0, odd trailing voxels trimmed) and OME-NGFF 0.5
``multiscales`` metadata; only levels marked complete are read (:mod:`chunkdic.io.levels`).
A level that is not stored is built lazily by 2x2x2 sums (:mod:`chunkdic.io.coarsen`), and
written to scratch when tasks need it on disk (:meth:`Scan.refs`). Writing scans is
:mod:`chunkdic.io.scanwrite` and :mod:`chunkdic.io.pyramid`; the handles tasks receive are
:mod:`chunkdic.io.handles`.

References
----------
Roux, Hild, Viot, Bernard, *Three dimensional image correlation from X-ray computed
tomography of solid foam*, sections 3 (multiscale) and 4.1 (4^3 super-voxel compression,
which is pyramid level 2 here).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import config
from ..errors import InputError
from ..scheduler import DistributedRunner, ThreadRunner
from .coarsen import coarsen_sum, pyramid_dtype
from .handles import ArrayRef, ref_dask
from .integrity import check_chunks_present
from .levels import write_level
from .ngff import (
    complete_levels,
    normalize_unit,
    normalize_voxel_size,
    voxel_from_group_attrs,
)
from .owntree import remove
from .scratch_levels import build_level
from .store import chunk_is_complete, chunk_shape_for

log = logging.getLogger(__name__)

Region = tuple[slice, slice, slice]


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
            return ref_dask(ref)
        if s == 0:
            if self._base is None:
                raise InputError("level 0 of this scan is not available")
            if self._in_memory():
                return da.from_array(self._base, chunks=chunk_shape_for(self._base.shape, None))
            return self._base
        k = self._source_level(s)
        a = self.level(k)
        c = config.get("chunk-size")
        for t in range(k + 1, s + 1):
            a = coarsen_sum(a, self.dtype(t), chunk=c)
        return a

    def _in_memory(self) -> bool:
        """Level 0 is an array in this process's memory (NumPy, in-memory Zarr), not a graph."""
        return self._base is not None and not hasattr(self._base, "dask")

    def refs(self, levels, scratch_dir=None, runner=None, *, adopt: bool = False) -> dict[int, ArrayRef]:
        """On-disk handles for ``levels``: stored levels directly; others written chunk by
        chunk into a Zarr group under ``scratch_dir``, each from the finest level on disk
        below it, by tasks on ``runner`` (:mod:`chunkdic.io.scratch_levels`).

        A level 0 held in memory is written to scratch first, from this process: the
        levels built from it then read it by path, so no task ever carries voxels (a
        distributed scheduler would otherwise receive the whole array). A level 0 given as
        a Dask array has no path: its levels are its own graph, summed and stored by Dask.

        Parameters
        ----------
        levels : iterable of int
        scratch_dir : str or Path, optional
            Directory for the scratch group (created if needed); default
            ``chunkdic.scratch-directory`` or the system temporary directory.
        runner : ThreadRunner or DistributedRunner, optional
            Where the tasks run (:func:`chunkdic.scheduler.open_runner`); default the
            current ``distributed`` client if there is one (as for Dask collections),
            else an embedded thread pool for this call.
        adopt : bool, keyword-only
            ``scratch_dir`` is an interrupted run's, written for this very scan (the caller
            checked: :func:`chunkdic.io.scratch.adopt_scratch`): its levels marked complete,
            of the expected shape and dtype and whose every chunk is complete
            (:func:`chunkdic.io.store.chunk_is_complete`), are used instead of built again.

        Returns
        -------
        dict of int to ArrayRef
        """
        wanted = {int(v) for v in levels}
        if self._in_memory() and 0 not in self._scratch:
            wanted.add(0)
        if adopt and scratch_dir is not None:
            self._adopt_scratch_levels(Path(scratch_dir), wanted)
        missing = [s for s in sorted(wanted) if s not in self._stored and s not in self._scratch]
        if missing:
            group = self._make_scratch_group(scratch_dir)
            with _task_runner(runner) as run:
                for s in missing:
                    self._scratch[s] = self._write_scratch(group, s, run)
                    log.info("level %d %s written to scratch %s", s, self._scratch[s].shape, group)
        on_disk = {**self._scratch, **self._stored}
        return {s: on_disk[s] for s in sorted({int(v) for v in levels})}

    def _adopt_scratch_levels(self, scratch_dir: Path, wanted) -> None:
        """Take the complete levels of the scratch group an interrupted run wrote for this scan
        under ``scratch_dir`` (see :meth:`refs`); levels found incomplete are built again into it,
        and levels coarser than every wanted one (done before the interruption) are removed."""
        import concurrent.futures
        import itertools

        import zarr

        groups = sorted(scratch_dir.glob("scan-*.zarr")) if scratch_dir.is_dir() else []
        if self._scratch_group is not None or len(groups) != 1:
            return
        try:
            root = zarr.open_group(store=str(groups[0]), mode="r")
            if dict(root.attrs.get("chunkdic", {})).get("kind") != "scratch":
                return
        except Exception:  # noqa: BLE001 - not a group chunkdic wrote: left alone, a new one is made
            return
        self._scratch_group = str(groups[0])
        for name in list(root.array_keys()):  # levels coarser than any wanted: done before the kill
            if name.isdigit() and int(name) > max(wanted):
                remove(groups[0] / name)
        for s in sorted(wanted - set(self._stored) - set(self._scratch)):
            try:
                arr = zarr.open_array(store=str(groups[0]), path=str(s), mode="r")
                info = dict(arr.attrs.get("chunkdic", {}))
                if (not info.get("complete") or tuple(arr.shape) != self.shape(s)
                        or np.dtype(arr.dtype) != np.dtype(self.dtype(s))):
                    continue
            except Exception:  # noqa: BLE001 - absent or unreadable: built again
                continue
            grid = [range(-(-n // c)) for n, c in zip(arr.shape, arr.chunks)]
            with concurrent.futures.ThreadPoolExecutor(max(1, os.cpu_count() or 1)) as pool:
                whole = all(pool.map(lambda c: chunk_is_complete(arr, c), itertools.product(*grid)))
            if whole:
                self._scratch[s] = ArrayRef("zarr", str(groups[0]), str(s), tuple(int(n) for n in arr.shape),
                                            np.dtype(arr.dtype).name)
                log.info("level %d %s of the interrupted run reused from scratch %s", s, arr.shape, groups[0])

    def _make_scratch_group(self, scratch_dir) -> str:
        """The scan's scratch group (created on first use)."""
        import zarr

        if self._scratch_group is None:
            import tempfile

            root = Path(scratch_dir or config.get("scratch-directory") or tempfile.gettempdir())
            root.mkdir(parents=True, exist_ok=True)
            gpath = root / f"scan-{uuid.uuid4().hex[:12]}.zarr"
            zarr.open_group(store=str(gpath), mode="w-", zarr_format=3).update_attributes(
                {"chunkdic": {"kind": "scratch", "voxel_size": list(self.voxel_size) if self.voxel_size else None,
                              "unit": self.unit, "scratch": True}})
            self._scratch_group = str(gpath)
        return self._scratch_group

    def _write_scratch(self, group: str, s: int, runner) -> ArrayRef:
        """Level ``s`` written into the scratch group: from memory, by tasks, or by Dask."""
        if s == 0 and self._in_memory():
            return write_level(group, 0, self._base)
        on_disk = [k for k in {**self._scratch, **self._stored} if k < s]
        if on_disk:
            k = max(on_disk)
            src = self._scratch.get(k) or self._stored[k]
            dtypes = [self.dtype(t) for t in range(k + 1, s + 1)]
            return build_level(group, s, src, s - k, dtypes, runner)
        return write_level(group, s, self.level(s))  # a Dask level 0: its own graph computes it


@contextlib.contextmanager
def _task_runner(runner):
    """``runner``, else the current ``distributed`` client's, else a thread pool for the call.

    ``distributed`` is only asked when already imported (a client exists only then):
    importing it, as ``dask.base.get_scheduler`` does, costs about a second.
    """
    if runner is not None:
        yield runner
        return

    client = _current_client()
    if client is not None:
        yield DistributedRunner(client)
        return
    pool = ThreadRunner()
    try:
        yield pool
    finally:
        pool.close()


def _current_client():
    """The ``distributed.Client`` Dask collections would compute on now, or None."""
    if "distributed" not in sys.modules:
        return None
    from dask.base import get_scheduler
    from distributed import Client

    client = getattr(get_scheduler(), "__self__", None)
    return client if isinstance(client, Client) else None


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
        complete = complete_levels(g)
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
    vs, unit = voxel_from_group_attrs(attrs)
    return Scan(path=os.path.join(root, prefix) if prefix else root, voxel_size=vs, unit=unit, _stored=stored)


def _scan_from_zarr(node, where: str) -> Scan:
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
        return Scan(path=None, voxel_size=None, unit=None, _base=node)
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
        scan.voxel_size = normalize_voxel_size(voxel_size)
    if unit is not None:
        scan.unit = normalize_unit(unit)
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
    if not p.is_dir():  # a FIFO, a socket, a device: never opened (a FIFO would wait for a writer)
        raise InputError(f"{p} is not a Zarr store, a .npy file or a folder (a FIFO, a socket or a device?)")
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

"""Picklable handles of 3-D arrays on disk: tasks receive these, never voxels.

A task gets an :class:`ArrayRef` (a path and a key) and reads the region it needs straight
from the store; :func:`ref_dask` wraps one as a lazy Dask array whose graph holds only the
handle.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .chunkread import ChunkDamaged, forget_chunks, layout_of, read_region
from .integrity import damaged_read_error
from .store import chunk_shape_for

Region = tuple[slice, slice, slice]


@functools.lru_cache(maxsize=64)
def open_zarr_array(path: str, key: str):
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
            return open_zarr_array(self.path, self.key)
        if self.kind == "npy":
            return np.load(self.path, mmap_mode="r")
        raise ValueError(f"unknown array kind {self.kind!r}")

    def read(self, region: Region) -> np.ndarray:
        """Read ``region`` (slices clipped to the array by the caller) as a NumPy array.

        The result is a copy; a ``.npy`` mapping is dropped on return. A worker that
        kept one mapping across the tasks of a level-0 correlation of 1024³ reached
        4.3 GiB RSS (every coefficient page it had read); mapping per read holds it
        to one window. A Zarr array whose chunk layout :mod:`chunkdic.io.chunkread`
        knows is read from its chunk files through the process's cache of decoded
        chunks (the same voxels; neighbouring regions decode their shared chunks once),
        any other through zarr-python.
        """
        try:
            layout = layout_of(self.path, self.key) if self.kind == "zarr" and _plain(region, self.shape) else None
            if layout is not None and layout.shape == tuple(self.shape):
                return read_region(layout, region)
            a = self.open()[region]
            return np.array(a) if self.kind == "npy" else np.asarray(a)
        except InputError:
            raise
        except ChunkDamaged as exc:
            raise InputError(f"{Path(self.path, self.key) if self.key else Path(self.path)}: chunk {exc.index} "
                             f"(file {exc.file}) cannot be read: {exc}; the store is damaged or truncated") from None
        except Exception as exc:  # noqa: BLE001 - a damaged store: name the chunk (no cost when reads succeed)
            if self.kind == "zarr":
                raise damaged_read_error(self.path, self.key, region, exc) from None
            raise InputError(f"{self.path}: cannot read the region "
                             f"{tuple((s.start, s.stop) for s in region)} ({type(exc).__name__}: {exc}); "
                             "the file is damaged or truncated".splitlines()[0]) from None

    @property
    def ndim(self) -> int:
        return 3


def _plain(region, shape) -> bool:
    """``region`` is 3 slices of step 1 with integer bounds within ``shape``."""
    return len(region) == len(shape) == 3 and all(
        isinstance(s, slice) and s.step in (None, 1) and isinstance(s.start, (int, np.integer))
        and isinstance(s.stop, (int, np.integer)) and 0 <= s.start <= s.stop <= n for s, n in zip(region, shape))


def forget_open_arrays() -> None:
    """Forget cached handles and chunk layouts in this process (a store may have been rewritten)."""
    open_zarr_array.cache_clear()
    layout_of.cache_clear()
    forget_chunks()


class RefReader:
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
    return chunk_shape_for(ref.shape, None)


def ref_dask(ref: ArrayRef, chunks=None):
    """Lazy dask array over an on-disk array (tasks open it by path)."""
    import dask.array as da
    from dask.base import tokenize

    chunks = _ref_chunks(ref) if chunks is None else chunks
    name = "scan-" + tokenize(ref.kind, ref.path, ref.key, ref.shape, ref.dtype, _mtime(ref))
    return da.from_array(RefReader(ref), chunks=chunks, name=name, asarray=False,
                         meta=np.empty((0, 0, 0), np.dtype(ref.dtype)))


def _mtime(ref: ArrayRef) -> float:
    p = Path(ref.path)
    target = p / ref.key / "zarr.json" if ref.kind == "zarr" else p
    try:
        return target.stat().st_mtime_ns
    except OSError:
        return 0

"""Readers of scan files: small picklable array-likes whose tasks open the file by path.

One idea: the ``dask.array.from_array`` source of :func:`chunkdic.io.formats.ingest.ingest`. A reader
holds a path and a layout (shape, dtype, byte order, offset, page or slice list), never
voxels; ``reader[z, y, x]`` opens the file inside the task and reads only that slab
(``pread`` rows of a raw file, a memory map of a ``.npy``, an HDF5 hyperslab, TIFF pages,
slices or tiles). A damaged or truncated file is reported as one :class:`InputError` line
naming the file and the slice. The readers are built by :mod:`chunkdic.io.formats.openers`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...errors import InputError

__all__ = ["Reader", "RawReader", "NpyReader", "H5Reader", "TiffSlicesReader", "TiffVolumeReader",
           "tiff_as_zarr"]


class Reader:
    """Array-like for ``dask.array.from_array``: ``shape``, ``dtype``, ``[z, y, x]``."""

    ndim = 3
    shape: tuple[int, int, int]
    dtype: np.dtype
    label: str

    def __getitem__(self, region):
        try:
            return self._read(region)
        except InputError:
            raise
        except Exception as e:  # noqa: BLE001 - a damaged or truncated file: one line naming it
            z = region[0].indices(self.shape[0])[0]
            raise InputError(f"{self.label}: cannot read {self.describe(z)} onwards ({type(e).__name__}: {e}"
                             .splitlines()[0] + "); the file is damaged or truncated") from None

    def _read(self, region):
        raise NotImplementedError

    def describe(self, z: int) -> str:
        return f"slice z={z}"

    def _token_fields(self) -> tuple:
        return tuple(sorted((k, repr(v)) for k, v in vars(self).items()))

    def __dask_tokenize__(self):
        return (type(self).__name__, self._token_fields())


class RawReader(Reader):
    """Rows of a raw volume read with ``os.preadv`` into one buffer per slab.

    Not ``np.memmap``: a mapping kept by a worker counts every page it touched in the
    process's RSS, which Dask's nanny watches (the ``.npy`` reads of
    :class:`chunkdic.io.handles.ArrayRef` reached 4.3 GiB at 1024³ that way); explicit reads
    hold a worker to its slab.
    """

    def __init__(self, path: str, shape, dtype: np.dtype, offset: int):
        self.path, self.shape, self.file_dtype, self.offset = path, tuple(shape), np.dtype(dtype), int(offset)
        self.dtype = self.file_dtype.newbyteorder("=")
        self.label = path

    def _read(self, region):
        nz, ny, nx = self.shape
        zs, ys, xs = (r.indices(n) for r, n in zip(region, self.shape))
        row = nx * self.file_dtype.itemsize
        y0, y1 = ys[0], max(ys[0], ys[1])
        zr = range(*zs)
        out = np.empty((len(zr), y1 - y0, nx), self.file_dtype)
        with open(self.path, "rb", buffering=0) as f:
            fd = f.fileno()
            for i, z in enumerate(zr):
                start = self.offset + (z * ny + y0) * row
                want = (y1 - y0) * row
                buf = memoryview(out[i]).cast("B")
                got = 0
                while got < want:
                    n = os.preadv(fd, [buf[got:]], start + got)
                    if n <= 0:
                        raise InputError(f"{self.path}: unexpected end of file at z={z}")
                    got += n
        out = out[:, slice(None, None, ys[2]) if ys[2] != 1 else slice(None), slice(*xs)]
        return out.astype(self.dtype, copy=False)


class NpyReader(Reader):
    def __init__(self, path: str, shape, dtype):
        self.path, self.shape, self.file_dtype = path, tuple(shape), np.dtype(dtype)
        self.dtype = self.file_dtype.newbyteorder("=")
        self.label = path

    def _read(self, region):
        a = np.load(self.path, mmap_mode="r")
        return np.array(a[region], dtype=self.dtype)


class H5Reader(Reader):
    def __init__(self, path: str, dataset: str, shape, dtype):
        self.path, self.dataset, self.shape = path, dataset, tuple(shape)
        self.dtype = np.dtype(dtype).newbyteorder("=")
        self.label = f"{path}:{dataset}"

    def _read(self, region):
        import h5py

        with h5py.File(self.path, "r") as f:
            return np.asarray(f[self.dataset][region], dtype=self.dtype)


class TiffSlicesReader(Reader):
    def __init__(self, files: list[str], shape, dtype, memmappable: bool):
        self.files, self.shape, self.memmappable = list(files), tuple(shape), bool(memmappable)
        self.dtype = np.dtype(dtype).newbyteorder("=")
        self.label = str(Path(files[0]).parent)

    def describe(self, z: int) -> str:
        return f"slice z={z} (file {Path(self.files[z]).name})"

    def _read_plane(self, path: str, ys, xs):
        import tifffile

        if self.memmappable:
            try:
                return np.array(tifffile.memmap(path, mode="r")[ys, xs])
            except ValueError:
                pass
        return tifffile.imread(path)[ys, xs]

    def _read(self, region):
        zs, ys, xs = region
        zr = range(*zs.indices(self.shape[0]))
        out = np.empty((len(zr),) + tuple(len(range(*r.indices(n))) for r, n in zip((ys, xs), self.shape[1:])),
                       self.dtype)
        for i, z in enumerate(zr):
            try:
                plane = self._read_plane(self.files[z], ys, xs)
            except Exception as e:  # noqa: BLE001 - name the slice file
                raise InputError(f"{self.files[z]}: cannot read slice z={z} ({type(e).__name__}: {e}"
                                 .splitlines()[0] + "); the file is damaged or truncated") from None
            if plane.shape != out.shape[1:]:
                raise InputError(f"{self.files[z]}: slice changed shape to {plane.shape} while reading")
            out[i] = plane
        return out


class TiffVolumeReader(Reader):
    def __init__(self, path: str, shape, dtype, series: int, memmappable: bool, by_pages: bool):
        self.path, self.shape, self.series = path, tuple(shape), int(series)
        self.dtype = np.dtype(dtype).newbyteorder("=")
        self.memmappable, self.by_pages = bool(memmappable), bool(by_pages)
        self.label = path

    def describe(self, z: int) -> str:
        return f"page z={z}"

    def _read(self, region):
        import tifffile

        zs, ys, xs = region
        if self.memmappable:
            m = tifffile.memmap(self.path, series=self.series, mode="r").reshape(self.shape)
            return np.array(m[region], dtype=self.dtype)
        with tifffile.TiffFile(self.path) as tif:
            if self.by_pages:
                z0, z1, step = zs.indices(self.shape[0])
                data = tif.asarray(key=range(z0, z1, step), series=self.series)
                data = data.reshape((-1,) + self.shape[1:])
                return np.asarray(data[:, ys, xs], dtype=self.dtype)
            # compressed volumetric page(s): through tifffile's chunked store, so that a slab
            # decodes only the tiles / strips it overlaps, not the whole series
            arr = tiff_as_zarr(tif, self.series)
            return np.asarray(arr[_unsqueezed(arr.shape, region)], dtype=self.dtype)


def tiff_as_zarr(tif, series: int):
    import zarr

    return zarr.open_array(tif.aszarr(series=series), mode="r")


def _unsqueezed(shape, region) -> tuple:
    """``region`` over the squeezed 3-D shape as an index of the stored ``shape`` (singleton axes 0)."""
    it = iter(region)
    return tuple(0 if n == 1 else next(it) for n in shape)

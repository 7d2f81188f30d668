"""Any scan format ``ingest`` reads, opened in place as a :class:`chunkdic.io.scan.Scan`.

What a mask needs: a specimen mask often comes as the TIFF stack or HDF5 dataset a
segmentation tool wrote, and converting it first would be a chore. :func:`open_any` opens
Zarr and ``.npy`` as :func:`chunkdic.open_scan` does, and TIFF (a 3-D file or a folder of
slices) and HDF5 (``file.h5`` or ``file.h5:/dataset``) through the readers of
the format readers (:mod:`chunkdic.io.formats.detect`): nothing is read until a level is needed, and level 0 is
then copied to scratch one chunk row at a time (:meth:`chunkdic.io.scan.Scan.refs`). A raw
file needs its shape and dtype: ingest it first.
"""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from ..scan import Scan, open_scan
from .detect import is_foreign, open_source

__all__ = ["open_any"]


class _Slabs:
    """A reader seen as a 3-D array (``shape``, ``dtype``, ``[z0:z1]`` and region slicing)."""

    ndim = 3

    def __init__(self, reader):
        self.reader = reader
        self.shape = tuple(int(n) for n in reader.shape)
        self.dtype = np.dtype(reader.dtype)

    def __getitem__(self, key):
        key = key if isinstance(key, tuple) else (key,)
        key = tuple(key) + (slice(None),) * (3 - len(key))
        region = tuple(slice(*k.indices(n)[:2]) for k, n in zip(key, self.shape))
        return np.asarray(self.reader[region])

    def __array__(self, dtype=None, copy=None):
        a = self[:]
        return a if dtype is None else a.astype(dtype)


def open_any(src) -> Scan:
    """Open a scan in any format ``chunkdic ingest`` reads but raw (Zarr, npy, TIFF, HDF5).

    Parameters
    ----------
    src : str, Path, array or Scan
        As :func:`chunkdic.open_scan`, or a TIFF file, a folder of TIFF slices, an HDF5
        file (``file.h5:/dataset`` when it holds several datasets).

    Returns
    -------
    Scan
        ``path`` is the file or folder; voxel size and unit from the file's metadata.

    Raises
    ------
    InputError
        Unreadable or not 3-D, as ``ingest`` says it.
    """
    if not is_foreign(src):
        return open_scan(src)
    source = open_source(src)
    if source.reader is None:
        return open_scan(src)
    if len(source.reader.shape) != 3:
        raise InputError(f"{src}: shape {tuple(source.reader.shape)}; a scan must be 3-D (z, y, x)")
    return Scan(path=str(source.path), voxel_size=source.voxel_size, unit=source.unit, _base=_Slabs(source.reader))

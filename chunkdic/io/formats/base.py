"""What every scan format shares: the reader interface, the opened source, the format interface.

A :class:`Format` (one module per file type: :mod:`.tiff`, :mod:`.hdf5`, :mod:`.raw`,
:mod:`.npy`, :mod:`.zarr`) says whether it opens a path (:meth:`Format.can_open`) and opens
it (:meth:`Format.open`) into a :class:`Source`: a picklable :class:`Reader` of slabs, the
voxel size and unit found in the file's metadata, and the input path. Only headers are
read when opening; inconsistent or truncated inputs are refused with one
:class:`~chunkdic.errors.InputError` line. :func:`chunkdic.io.formats.open_source` picks the
format, as xarray's ``guess_engine`` does.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Protocol

import numpy as np

from ...errors import InputError
from ..ngff import normalize_unit


@dataclasses.dataclass(frozen=True)
class Layout:
    """What the user tells about a file whose header does not: a raw file's ``shape``,
    ``dtype``, ``byte_order`` and header ``offset``; an HDF5 ``dataset``."""

    shape: object = None
    dtype: object = None
    byte_order: str = "little"
    offset: int = 0
    dataset: str | None = None


@dataclasses.dataclass(frozen=True)
class Source:
    """An opened scan file.

    Attributes
    ----------
    path : Path
        The input (file or folder), for the overlap checks of outputs.
    reader : Reader, optional
        Slab reader (``None`` for a Zarr store, which :func:`chunkdic.open_scan` opens itself).
    voxel_size : tuple of 3 float, optional
        Level-0 voxel size ``(z, y, x)`` from the metadata.
    unit : str, optional
        Its unit (an OME-NGFF unit name).
    """

    path: Path
    reader: "Reader | None" = None
    voxel_size: tuple | None = None
    unit: str | None = None


class Format(Protocol):
    """One file type: ``name``, :meth:`can_open`, :meth:`open`."""

    name: str

    def can_open(self, path: Path, layout: Layout) -> bool:
        """Whether ``path`` (existing) is this format's, from its name, kind or magic bytes."""

    def open(self, path: Path, layout: Layout) -> Source:
        """Read the header, check it, return the source (:class:`InputError` if unusable)."""


class Reader:
    """Array-like for ``dask.array.from_array``: ``shape``, ``dtype``, ``[z, y, x]``.

    A reader holds a path and a layout (shape, dtype, byte order, offset, page or slice
    list), never voxels; ``reader[z, y, x]`` opens the file inside the task and reads only
    that slab. A damaged or truncated file is reported as one :class:`InputError` line
    naming the file and the slice.
    """

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


def natural_key(name: str):
    """Sort key that orders ``slice2`` before ``slice10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def metadata_unit(u) -> str | None:
    """A unit as a file's metadata writes it (``\\u00B5m``, ``um``, ``micron``...), or None if unknown."""
    if not u:
        return None
    u = str(u).replace("\\u00B5", "µ").replace("\\u00b5", "µ")
    try:
        return normalize_unit(u)
    except InputError:
        return None


def check_scan_array(label: str, shape, dtype) -> None:
    """A scan is a 3-D array of integers or floats."""
    if len(shape) != 3:
        raise InputError(f"{label}: array has shape {tuple(shape)}; a scan must be 3-D (z, y, x)")
    if np.dtype(dtype).kind not in "uif":
        raise InputError(f"{label}: unsupported dtype {np.dtype(dtype)}")

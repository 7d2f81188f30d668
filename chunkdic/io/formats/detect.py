"""Which format opens a path: the first of :data:`FORMATS` whose ``can_open`` says yes.

The order settles the overlaps: an HDF5 name (suffix or ``file.h5:/dataset``) first, a Zarr
store before a folder of slices, a raw layout given by the user before the file's suffix,
and raw last (it then asks for ``--shape`` and ``--dtype``).
"""

from __future__ import annotations

from pathlib import Path

from ...errors import InputError
from .base import Layout, Source
from .hdf5 import SUFFIXES as SUFFIXES_HDF5
from .hdf5 import Hdf5, split_dataset
from .npy import Npy
from .raw import Raw
from .tiff import TiffFolder, TiffVolume, is_slice_folder
from .zarr import Zarr

#: the formats, in the order they are asked
FORMATS = (Zarr(), TiffFolder(), TiffVolume(), Npy(), Hdf5(), Raw())


def open_source(src, layout: Layout = Layout()) -> Source:
    """Open ``src`` (a path, or ``file.h5:/dataset``) with the format it is in.

    Raises
    ------
    InputError
        The input does not exist, or its format refuses it (one line).
    """
    path, dataset = split_dataset(str(src), layout.dataset)
    if dataset is not None and layout.dataset is None:
        layout = Layout(layout.shape, layout.dtype, layout.byte_order, layout.offset, dataset)
    if not path.exists():
        raise InputError(f"input {path} does not exist")
    if not (path.is_file() or path.is_dir()):  # never opened: a FIFO would wait for a writer for ever
        raise InputError(f"input {path} is not a file or a folder (a FIFO, a socket or a device?)")
    if path.suffix.lower() in SUFFIXES_HDF5 or layout.dataset is not None:
        return Hdf5().open(path, layout)
    formats = FORMATS if layout.shape is None else (Zarr(), TiffFolder(), Raw())  # a raw layout wins over suffixes
    for fmt in formats:
        if fmt.can_open(path, layout):
            return fmt.open(path, layout)
    raise InputError(f"input {path}: not a scan file or folder")


def is_foreign(src) -> bool:
    """Whether ``src`` is a path :func:`chunkdic.open_scan` refuses but a format reads in place
    (a TIFF file or folder of TIFF slices, an HDF5 file or dataset)."""
    if not isinstance(src, (str, Path)):
        return False
    path, dataset = split_dataset(str(src), None)
    if path.suffix.lower() in SUFFIXES_HDF5 or dataset is not None:
        return True
    if Zarr().can_open(path, Layout()):
        return False
    return TiffVolume().can_open(path, Layout()) or is_slice_folder(path)


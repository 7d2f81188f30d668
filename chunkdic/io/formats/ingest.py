"""Ingest the scan formats users bring into a stored scan (Zarr v3 group, OME-NGFF 0.5).

Formats: a folder of 2-D TIFF slices (natural sort: ``slice_2`` before ``slice_10``), a
3-D / multi-page TIFF, a raw binary file (``shape``, ``dtype``, byte order, header
offset), an HDF5 dataset (``file.h5:/path/to/dataset``), a ``.npy`` file, or an existing
Zarr array / scan group (rechunked, recompressed copy).

Nothing is read whole: a small picklable *reader* (:class:`chunkdic.io.formats.base.Reader`, a path and a
layout, built by the format of the file, :mod:`chunkdic.io.formats.detect`) is wrapped in a Dask array whose blocks are slabs
of whole Zarr chunks (``chunk`` slices deep, full rows if they fit
``chunkdic.ingest-slab-bytes``, 32 MiB by default); each task opens the file by path,
reads its slab (page range, ``pread`` rows, HDF5 hyperslab, memory map) and writes it with
:func:`chunkdic.io.scanwrite.write_scan`. Float input is checked for NaN and infinity slab by
slab during the write; a failure removes the half-written output.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import dask.config
import numpy as np

from ...errors import InputError
from ...inputs import check_finite
from ..handles import RefReader
from ..madeof import made_of
from ..ngff import normalize_unit, normalize_voxel_size
from ..resample import resampled
from ..scan import Scan, open_scan
from ..scanwrite import write_scan
from ..store import chunk_shape_for
from ..units import resample_size
from .base import Layout
from .detect import open_source

log = logging.getLogger(__name__)

_DEFAULT_SLAB_BYTES = 32 * 2**20


# --------------------------------------------------------------------------------------
# Streaming into write_scan
# --------------------------------------------------------------------------------------


def slab_chunks(shape, dtype, chunk_shape):
    """Dask chunks: whole Zarr chunks, ``cz`` deep, full rows while under the slab budget."""
    budget = int(dask.config.get("chunkdic.ingest-slab-bytes", default=_DEFAULT_SLAB_BYTES))
    nz, ny, nx = shape
    cz, cy, cx = chunk_shape
    item = np.dtype(dtype).itemsize
    row = cz * nx * item
    if row * ny <= budget:
        ey, ex = ny, nx
    elif row * cy <= budget:
        ey, ex = cy * max(1, budget // (row * cy)), nx
    else:
        ey, ex = cy, cx * max(1, budget // (cz * cy * cx * item))
    return tuple(min(e, n) for e, n in zip((cz, ey, ex), shape))


def _check_finite(block: np.ndarray, reader=None, block_info=None) -> np.ndarray:
    origin = tuple(r[0] for r in block_info[0]["array-location"])
    check_finite(block, origin, reader.label, where=reader.describe)
    return block


def ingest(src, out, *, voxel_size=None, unit=None, chunks=None, shape=None, dtype=None,
           byte_order: str = "little", offset: int = 0, dataset: str | None = None,
           overwrite: bool = False, levels: int = 0, parents: bool = True,
           progress: Callable[[float], None] | None = None, resample=None) -> Scan:
    """Convert a scan file or folder into a stored scan group (Zarr v3, OME-NGFF 0.5).

    Parameters
    ----------
    src : str or Path
        Folder of 2-D TIFF slices, 3-D TIFF, raw binary file (with ``shape``/``dtype``),
        ``file.h5:/path/to/dataset``, ``.npy``, or a Zarr array / scan group.
    out : str or Path
        Group to create, e.g. ``"scan.zarr"``.
    voxel_size : float or tuple of 3 float, optional
        Level-0 voxel size ``(z, y, x)``; default from TIFF (ImageJ / OME) or HDF5
        (``element_size_um``, ``voxel_size``) metadata, else none.
    unit : str, optional
        Length unit of ``voxel_size`` (``"micrometer"``, ``"um"``, ``"mm"``, ...).
    chunks : int or tuple of 3 int, optional
        Zarr chunk edge; default ``chunkdic.chunk-size`` (128).
    shape : tuple of 3 int or "Z,Y,X", optional
        Raw input only: array shape.
    dtype : {"uint8", "uint16", "float32", "int16", "uint32", "int32", "float64"}, optional
        Raw input only: sample type.
    byte_order : {"little", "big"}
        Raw input only.
    offset : int
        Raw input only: header bytes to skip.
    dataset : str, optional
        HDF5 dataset path (alternative to ``file.h5:/dataset``).
    overwrite : bool
        Replace an existing Zarr store at ``out``.
    levels : int
        Pyramid levels to build after level 0 (2 = the paper's 4^3 compression).
    parents : bool
        Create missing parent directories of ``out`` (default; like ``mkdir -p``, never
        inside an input or a Zarr store; removed again if the run fails).
    progress : callable(float), optional
        Called with the fraction done.
    resample : float, tuple of 3 float or str, optional
        A voxel size to resample the scan onto (trilinear, :mod:`chunkdic.io.resample`):
        ``"20um"``, ``"20,20,25um"``, or numbers in the scan's own unit. The scan needs a
        voxel size (its metadata or ``voxel_size``). Brings a scan onto the voxel size of
        the scan it is to be correlated with (:func:`chunkdic.io.units.check_voxel_sizes`).

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Unreadable or inconsistent input (size mismatch, mixed slices, missing dataset,
        not 3-D, NaN/inf in float data), existing output; nothing is left at ``out``.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> d = tempfile.mkdtemp()
    >>> np.arange(4 * 5 * 6, dtype=np.uint16).reshape(4, 5, 6).byteswap().tofile(os.path.join(d, "v.raw"))
    >>> s = ingest(os.path.join(d, "v.raw"), os.path.join(d, "v.zarr"), shape=(4, 5, 6), dtype="uint16",
    ...            byte_order="big", voxel_size=2.5, unit="um")
    >>> int(s.level(0)[3, 4, 5].compute()), s.voxel_size
    (119, (2.5, 2.5, 2.5))
    """
    import dask.array as da

    user_vs = normalize_voxel_size(voxel_size)
    user_unit = normalize_unit(unit)
    if user_unit is not None and user_vs is None:
        raise InputError("a unit was given without a voxel size: pass both (--voxel-size 4.91 --unit micrometer)")
    source = open_source(src, Layout(shape, dtype, byte_order, offset, dataset))
    reader, meta_vs, meta_unit, in_path = source.reader, source.voxel_size, source.unit, source.path
    out_p = Path(out)
    if reader is None:  # a Zarr array or group
        scan = open_scan(in_path)
        data = scan.level(0)
        meta_vs, meta_unit = scan.voxel_size, scan.unit
        label = str(in_path)
        reader = RefReader(scan.stored_refs()[0])
    else:
        label = reader.label
        cshape = chunk_shape_for(reader.shape, chunks)
        slab = slab_chunks(reader.shape, reader.dtype, cshape)
        name = "ingest-" + dask.base.tokenize(reader, slab, _mtime(in_path))
        data = da.from_array(reader, chunks=slab, name=name, asarray=False,
                             meta=np.empty((0, 0, 0), reader.dtype))
        if reader.dtype.kind == "f":
            data = data.map_blocks(_check_finite, reader=reader, dtype=reader.dtype,
                                   meta=np.empty((0, 0, 0), reader.dtype))
    vs = user_vs if user_vs is not None else meta_vs
    unit_out = user_unit if user_vs is not None else meta_unit
    if resample is not None:
        new = resample_size(resample, vs, unit_out)
        data = resampled(reader, tuple(n / v for n, v in zip(new, vs)), chunk_shape_for(data.shape, chunks))
        log.info("resampling %s from voxel size %s to %s %s", label, vs, new, unit_out)
        vs = new
    log.info("ingesting %s: shape %s %s, voxel size %s %s", label, data.shape, data.dtype, vs, unit_out)
    made = made_of("ingest", [in_path], {"voxel_size": vs, "unit": unit_out, "chunks": chunks, "shape": shape,
                                          "dtype": dtype, "byte_order": byte_order, "offset": offset,
                                          "dataset": dataset, "levels": levels, "resample": resample})
    return write_scan(out_p, data, voxel_size=vs, unit=unit_out, chunks=chunks, overwrite=overwrite,
                      levels=levels, progress=progress, inputs=[in_path], parents=parents, made_of=made)


def _mtime(p: Path) -> int:
    try:
        return p.stat().st_mtime_ns
    except OSError:
        return 0

"""Writing a scan: level 0 from a Dask or NumPy array, then its pyramid, all or nothing.

The output goes through :class:`chunkdic.io.outputs.Outputs` (checked before anything is
written, staged in a hidden sibling and renamed into place once complete).
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from collections.abc import Callable

import numpy as np

from ..errors import InputError
from .coarsen import pyramid_dtype
from .handles import forget_open_arrays
from .jsonfile import json_dict, read_json_object
from .levels import check_levels, write_level
from .ngff import normalize_unit, normalize_voxel_size, update_group_metadata
from .outputs import Outputs
from .owntree import remove
from .pyramid import build_levels
from .scan import Scan, open_scan

log = logging.getLogger(__name__)


def write_scan(path, data, *, voxel_size=None, unit=None, chunks=None, overwrite: bool = False,
               levels: int = 0, progress: Callable[[float], None] | None = None, inputs=(),
               parents: bool = False, made_of: str | None = None) -> "Scan":
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
        replaced; see :mod:`chunkdic.io.outputs`).
    parents : bool
        Create missing parent directories of ``path`` (removed again if the write fails).
    levels : int
        Number of pyramid levels to build after level 0.
    progress : callable(float), optional
        Called with the fraction done (0..1), on the threaded scheduler as tasks finish
        and on a distributed client (the current one) as the chunk writes finish.
    made_of : str, optional
        What the scan is made of (:mod:`chunkdic.io.madeof`), recorded in it: the same call
        again on its own complete scan writes nothing and returns it.

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
    import zarr

    # A NumPy array stays as it is: write_level writes it from this process chunk by chunk
    # (in a Dask graph it would travel whole to a distributed scheduler).
    if (not isinstance(data, np.ndarray) and not hasattr(data, "dask")) or getattr(data, "ndim", None) != 3:
        raise InputError(f"write_scan needs a 3-D dask or numpy array, got {type(data).__name__} "
                         f"of shape {getattr(data, 'shape', '?')}")
    if min(data.shape) < 1:
        raise InputError(f"cannot write an empty scan of shape {data.shape}")
    pyramid_dtype(data.dtype, 0)  # dtype check
    voxel_size = normalize_voxel_size(voxel_size)
    unit = normalize_unit(unit)
    levels = int(levels)
    check_levels(data.shape, levels)
    plan = Outputs(inputs=inputs, overwrite=overwrite)
    entry = plan.add(path, "scan", parents=parents, made_of=made_of)  # every check before anything is written
    if plan.done:
        log.info("%s is already complete (the same source and options): nothing to do", path)
        return open_scan(str(path))
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
            write_level(str(p), 0, data, chunks, progress, cuts[0], cuts[1])
            update_group_metadata(str(p))
            log.info("level 0 %s %s written to %s in %.1f s", data.shape, data.dtype, path,
                     time.perf_counter() - t0)
            if levels:
                build_levels(str(p), levels, rebuild=True, progress=progress, cuts=cuts)
    finally:
        forget_open_arrays()
    return open_scan(str(path))


def write_scan_resumable(path, data, *, attrs: dict, voxel_size=None, unit=None, chunks=None,
                         levels: int = 0, progress: Callable[[float], None] | None = None) -> bool:
    """Write a scan in place inside a folder output, continuing an interrupted write.

    For the scans of a folder that :class:`chunkdic.io.outputs.Outputs` writes in place
    (a synthetic pair: the folder's marker says ``complete: false`` until the end, and the
    folder's lock keeps other writers out). ``attrs`` (JSON) is stored in
    ``attrs["chunkdic"]`` when the group is created, before any chunk: it is what a re-run
    must match to continue. If ``path`` holds a group with the same ``attrs``, the same
    voxel size and a level 0 of the same shape, dtype and chunks, the chunks of level 0
    already stored complete are kept (:func:`chunkdic.io.store.store_array` with
    ``resume=True``) and the pyramid levels are rebuilt; a group with other attributes is
    refused (:class:`InputError`). ``data`` must be deterministic: the resumed scan then
    equals an uninterrupted one bit for bit.

    Returns
    -------
    bool
        True if an earlier, interrupted write was continued.
    """
    import zarr

    from .levels import create_level, mark_complete
    from .store import aligned, chunk_shape_for, store_array

    path = str(path)
    voxel_size = normalize_voxel_size(voxel_size)
    unit = normalize_unit(unit)
    check_levels(data.shape, int(levels))
    chunk_shape = chunk_shape_for(data.shape, chunks)
    own = {"kind": "scan", "voxel_size": list(voxel_size) if voxel_size else None, "unit": unit, **attrs}
    own = json.loads(json.dumps(own))  # as stored (tuples become lists): compared with the stored one
    resumed = _matching_partial_scan(path, own, data, chunk_shape)
    forget_open_arrays()
    cuts = np.cumsum([0.0, 1.0] + [8.0 ** -(s - 1) for s in range(1, levels + 1)])
    cuts = cuts / cuts[-1]
    if resumed:
        _remove_partial_chunk_files(os.path.join(path, "0"))
    else:
        g = zarr.open_group(store=path, mode="w-", zarr_format=3)
        g.update_attributes({"chunkdic": own, "ome": {"version": "0.5"}})
        create_level(path, 0, data.shape, data.dtype, chunk_shape)
    # resumed: every stored chunk is checked (decoded) again, even in a level marked
    # complete, so a chunk damaged since is rewritten rather than read by the pyramid
    n = store_array(aligned(data, chunk_shape), path, "0", progress, cuts[0], cuts[1], resume=resumed)
    log.info("level 0 of %s: %d blocks written%s", path, n, " (resumed)" if resumed else "")
    mark_complete(path, 0)
    update_group_metadata(path)
    if levels:  # cheap (1/7 of level 0's reads); always rebuilt, whatever state it was left in
        build_levels(path, levels, rebuild=True, progress=progress, cuts=cuts)
    forget_open_arrays()
    return resumed


def _remove_partial_chunk_files(level_dir: str) -> None:
    """Remove the temporary files of chunk writes a killed process left in ``level_dir``.

    zarr's local store writes a chunk to ``KEY.<uuid hex>.partial`` and renames it onto
    ``KEY`` (so a chunk file is never half written by a kill); a kill between the two
    leaves the temporary file, which nothing else would ever remove.
    """
    for root, _, names in os.walk(level_dir):
        for name in names:
            if _ZARR_PARTIAL.fullmatch(name):
                remove(os.path.join(root, name))


_ZARR_PARTIAL = re.compile(r".+\.[0-9a-f]{32}\.partial")


def _matching_partial_scan(path: str, own: dict, data, chunk_shape) -> bool:
    """Whether ``path`` holds an interrupted write of the same scan (else it must not exist).

    A group killed before its level 0 array was created is just started again.
    """
    if not os.path.exists(path):
        return False
    try:
        ck = json_dict(read_json_object(os.path.join(path, "zarr.json")).get("attributes") or {}).get("chunkdic")
        ck = json_dict(ck) if ck is not None else None
    except (OSError, ValueError):
        ck = None
    if ck is None:  # killed between mkdir and the group's metadata: nothing of value yet
        remove(path)
        return False
    if any(ck.get(k) != v for k, v in own.items()):  # later stages add keys (levels, display window)
        raise InputError(f"{path} holds an interrupted write of another scan (other settings): "
                         "pass --overwrite to start again")
    try:
        meta = read_json_object(os.path.join(path, "0", "zarr.json"))
    except (OSError, ValueError):
        remove(path)  # killed before level 0 existed: start again
        return False
    try:
        same = (tuple(meta.get("shape", ())) == tuple(data.shape)
                and np.dtype(meta.get("data_type")) == np.dtype(data.dtype)
                and tuple(meta["chunk_grid"]["configuration"]["chunk_shape"]) == tuple(chunk_shape))
    except (KeyError, TypeError, ValueError, AttributeError):
        same = False
    if not same:
        raise InputError(f"{path} holds an interrupted write of another scan (shape, dtype or chunks "
                         "differ): pass --overwrite to start again")
    return True

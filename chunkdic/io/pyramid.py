"""The stored ``2^s`` sum pyramid of a scan, built level by level, chunk by chunk.

Level ``s`` is the sum over 2x2x2 voxels of level ``s - 1`` (odd trailing voxels
trimmed), read back from the store, so building level ``s`` never touches level 0 again
and memory stays at a few chunks per task. Level 2 is the paper's 4^3 super-voxel
compression (a 4^3 sum of 8-bit data fills 14 bits).

References
----------
Roux, Hild, Viot, Bernard, sections 3 (multiscale) and 4.1 (4^3 compression).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError
from .coarsen import coarsen_sum, pyramid_dtype
from .display import (
    DISPLAY_GROUP,
    check_display_slot,
    own_display,
    store_window,
    write_display,
)
from .handles import forget_open_arrays, ref_dask
from .levels import check_levels, write_level
from .ngff import update_group_metadata
from .outputrules import check_writable
from .owntree import check_own_tree, remove
from .locks import OutputLock
from .scan import Scan, open_scan

log = logging.getLogger(__name__)


def build_levels(path: str, levels: int, *, rebuild: bool = False, progress=None, cuts=None) -> Scan:
    """Add levels ``1..levels`` to the scan group ``path`` (see :func:`build_pyramid`)."""
    import zarr

    forget_open_arrays()
    scan = open_scan(path)
    shape0, dtype0 = scan.shape(0), scan.dtype(0)
    check_levels(shape0, levels)
    stored = set(scan.stored_levels())
    todo_from = next((s for s in range(1, levels + 1) if rebuild or s not in stored), None)
    if todo_from is None:
        log.info("%s: levels 1..%d already complete", path, levels)
        if not (zarr.open_group(store=path, mode="r").attrs.get("chunkdic") or {}).get("display_window"):
            store_window(path)
        return scan
    g = zarr.open_group(store=path, mode="r+")
    # Levels at or above the first rebuilt one were built from data that is being replaced
    # (or were interrupted): drop them all before writing anything.
    for name in [k for k in g.array_keys() if k.isdigit() and int(k) >= todo_from]:
        remove(Path(path) / name)
    if own_display(path):  # means of the levels being replaced (never a user's node of that name)
        remove(Path(path) / DISPLAY_GROUP)
    update_group_metadata(path)
    chunk0 = tuple(g["0"].chunks)
    if cuts is None:
        w = [8.0 ** -(s - 1) for s in range(todo_from, levels + 1)]
        edges = np.cumsum([0.0] + w) / sum(w)
        cuts = {s: (edges[i], edges[i + 1]) for i, s in enumerate(range(todo_from, levels + 1))}
    else:
        cuts = {s: (cuts[s], cuts[s + 1]) for s in range(1, levels + 1)}
    for s in range(todo_from, levels + 1):
        t0 = time.perf_counter()
        src = open_scan(path).stored_refs()[s - 1]
        below = ref_dask(src, chunks=tuple(min(2 * c, n) for c, n in zip(chunk0, src.shape)))
        data = coarsen_sum(below, pyramid_dtype(dtype0, s))
        try:
            write_level(path, s, data, chunk0, progress, *cuts[s])
        except Exception:
            # a refusal (damaged input, full disk) removes the level this run began, leaving the
            # scan as it found it; an interrupted run leaves it marked incomplete (rebuilt later)
            remove(Path(path) / str(s))
            update_group_metadata(path)
            raise
        update_group_metadata(path)
        log.info("%s: level %d %s %s built in %.1f s", path, s, data.shape, data.dtype, time.perf_counter() - t0)
    store_window(path)  # the level-0 contrast window of the scan's omero metadata
    forget_open_arrays()
    return open_scan(path)


def build_pyramid(path, levels: int, *, overwrite: bool = False,
                  progress: Callable[[float], None] | None = None, display: bool = False) -> Scan:
    """Add pyramid levels ``"1"``..``"levels"`` to a stored scan group.

    Each level is the 2x2x2 sum of the stored level below (odd sizes trimmed), in
    :func:`chunkdic.io.coarsen.pyramid_dtype` (exact integer sums), written chunk by chunk and
    marked complete last; OME-NGFF ``scale = voxel_size * 2^s`` and
    ``translation = voxel_size * (2^s - 1) / 2`` are updated. Levels that are already
    complete and valid are kept unless ``overwrite``; an incomplete or invalid level is
    rebuilt together with every level above it.

    Parameters
    ----------
    path : str or Path
        Scan group written by :func:`chunkdic.write_scan` or :func:`chunkdic.ingest`.
    levels : int
        Coarsest level wanted (``2`` = the paper's 4^3 compression).
    overwrite : bool
        Rebuild levels ``1..levels`` even if complete.
    progress : callable(float), optional
        Called with the fraction done.
    display : bool
        Also write the mean pyramid for viewers (:func:`chunkdic.io.display.write_display`),
        under the same lock; a ``display`` node the scan holds that chunkdic did not write
        is refused before anything is written.

    Returns
    -------
    Scan

    Examples
    --------
    >>> import dask.array as da, tempfile, os
    >>> from chunkdic.io.scanwrite import write_scan
    >>> p = os.path.join(tempfile.mkdtemp(), "s.zarr")
    >>> _ = write_scan(p, da.ones((8, 8, 8), dtype="uint8", chunks=4))
    >>> build_pyramid(p, 2).stored_levels()
    [0, 1, 2]
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"scan {p} does not exist")
    levels = int(levels)
    if levels < 1:
        raise InputError(f"--levels must be >= 1, got {levels}")
    if not (p / "zarr.json").exists():
        raise InputError(f"{p} is not a Zarr v3 scan group: run `chunkdic ingest` on it first")
    # the levels are written into the scan group itself, and only there: never through a
    # link to a folder or store outside it
    check_own_tree(p, [p / "zarr.json", p / DISPLAY_GROUP, *(p / str(s) for s in range(1, levels + 1))], what="scan")
    import zarr

    try:
        node = zarr.open(store=str(p), mode="r")
    except Exception as e:  # noqa: BLE001
        raise InputError(f"cannot read {p} as a Zarr store: {e}".splitlines()[0]) from None
    if not isinstance(node, zarr.Group) or "chunkdic" not in node.attrs:
        raise InputError(f"{p} is not a chunkdic scan group: convert it with `chunkdic ingest {p} OUT.zarr`")
    check_writable(p)  # the levels are written into the scan group itself
    if display:
        check_display_slot(p)  # before any level is written
    with OutputLock(p):  # one writer per scan: two builds never interleave their levels
        scan = build_levels(str(p), levels, rebuild=overwrite, progress=progress)
        if display:

            write_display(str(p))
    return scan
